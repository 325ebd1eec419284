"""Progress for people and for CI: the reporter's lines, rate and ETA (with a fake clock), and the CLI run
as CI runs it (a subprocess whose stderr is a pipe, not a terminal)."""

from __future__ import annotations

import io
import json
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest
from rich.console import Console

from logpipe.progress import (
    INTERVAL_ENV,
    Mode,
    ProgressReporter,
    format_duration,
    format_rate,
    interval_from_env,
    report_total,
)


class FakeClock:
    def __init__(self) -> None:
        self.now = 0.0

    def __call__(self) -> float:
        return self.now


def _reporter(mode: Mode = "lines", interval: float = 5.0) -> tuple[ProgressReporter, FakeClock, io.StringIO]:
    clock, out = FakeClock(), io.StringIO()
    reporter = ProgressReporter("predict", "samples", mode, interval_s=interval, stream=out, clock=clock)
    return reporter, clock, out


def test_heartbeat_writes_the_due_line_while_a_batch_runs() -> None:
    """A stage blocked in one long batch (here a sleep) still gets a line every interval, and the final line."""
    import threading
    import time

    out = io.StringIO()
    with ProgressReporter("predict", "samples", "lines", interval_s=0.2, stream=out) as reporter:
        assert any(t.name == "logpipe-progress-heartbeat" for t in threading.enumerate())
        reporter.total(10)
        time.sleep(1.1)  # one "batch" of about five intervals, no unit finished
        reporter(10)
    lines = out.getvalue().splitlines()
    beats = [line for line in lines if re.fullmatch(r"predict: 0:00:0\d 0/10 samples \(0%\)", line)]
    assert len(beats) >= 3  # a heartbeat about every 0.2 s, led by the time run (4-5 when the machine is idle)
    assert lines[-1].startswith("predict: 10/10 samples (100%)") and " done in " in lines[-1]
    assert not any(t.name == "logpipe-progress-heartbeat" for t in threading.enumerate())  # stopped with the run


def test_a_stage_without_units_shows_how_long_it_runs() -> None:
    reporter, clock, _ = _reporter(interval=5.0)
    clock.now = 12.0
    assert reporter.line() == "predict: running 0:00:12"


def test_lines_come_every_interval_with_count_rate_and_eta() -> None:
    reporter, clock, out = _reporter()
    reporter.total(5000)
    assert out.getvalue() == ""  # no "0/5,000" line: the first comes with the heartbeat
    clock.now = 4.0
    reporter(1240)
    assert out.getvalue() == ""  # 4 s < the 5 s interval
    clock.now = 5.0
    reporter(310)
    # 1,550 in 5 s = 310/s; 3,450 left at 310/s = 11.1 s, shown rounded up
    assert out.getvalue().splitlines() == ["predict: 0:00:05 1,550/5,000 samples (31%) 310/s ETA 0:00:12"]
    clock.now = 6.0
    reporter(100)
    assert len(out.getvalue().splitlines()) == 1  # next line 5 s after the last one
    clock.now = 20.0
    reporter(3350)
    reporter.close()
    lines = out.getvalue().splitlines()
    assert lines[-2] == "predict: 0:00:20 5,000/5,000 samples (100%) 250/s ETA 0:00:00"
    assert lines[-1] == "predict: 5,000/5,000 samples (100%) 250/s done in 0:00:20"


def test_rate_is_measured_over_the_recent_window() -> None:
    """A burst at the start (shards skipped on resume) stops counting once it is 30 s behind."""
    reporter, clock, _ = _reporter()
    reporter.total(1000)
    clock.now = 1.0
    reporter(500)
    for second in range(2, 101):
        clock.now = float(second)
        reporter(1)
    assert reporter.done == 599
    assert reporter.rate() == pytest.approx(1.0)
    assert reporter.eta() == pytest.approx(401.0)


def test_setup_before_the_total_does_not_lower_the_rate() -> None:
    reporter, clock, _ = _reporter()
    clock.now = 60.0  # a minute of loading before the stage knows its work
    reporter.total(100)
    clock.now = 70.0
    reporter(50)
    assert reporter.rate() == pytest.approx(5.0)
    assert reporter.final_line() == "predict: 50/100 samples (50%) 0.71/s done in 0:01:10"


def test_unknown_total_shows_the_count_and_rate_only() -> None:
    reporter, clock, out = _reporter(interval=0)
    clock.now = 4.0
    reporter(12)
    assert out.getvalue() == "predict: 0:00:04 12 samples 3.0/s\n"


def test_a_failed_run_says_where_it_stopped() -> None:
    reporter, clock, out = _reporter()

    def stage() -> None:
        with reporter:
            reporter.total(10)
            clock.now = 2.0
            reporter(3)
            raise RuntimeError("boom")

    with pytest.raises(RuntimeError):
        stage()
    assert out.getvalue().splitlines()[-1] == "predict: 3/10 samples (30%) 1.5/s stopped after 0:00:02"


def test_off_writes_nothing_and_plain_callbacks_ignore_the_total() -> None:
    reporter, _, out = _reporter(mode="off", interval=0)
    with reporter:
        report_total(reporter, 10)
        reporter(10)
    assert reporter.expected == 10 and out.getvalue() == ""
    seen: list[int] = []
    report_total(seen.append, 10)  # a plain callable has no total: left alone
    report_total(None, 10)
    assert seen == []


def test_bar_shows_done_total_and_eta_on_a_terminal() -> None:
    file = io.StringIO()
    console = Console(file=file, force_terminal=True, width=120)
    reporter = ProgressReporter("predict", "samples", "bar", console=console)
    with reporter:
        reporter.total(50)
        reporter(12)
        reporter(38)  # the last advance redraws however soon it comes
    text = file.getvalue()
    assert "50/50" in text and "samples" in text and "ETA" in text


def test_formatting_helpers(monkeypatch: pytest.MonkeyPatch) -> None:
    assert format_duration(0.2) == "0:00:01" and format_duration(3725) == "1:02:05" and format_duration(0) == "0:00:00"
    assert (format_rate(1234.4), format_rate(4.25), format_rate(0.371)) == ("1,234", "4.2", "0.37")
    monkeypatch.setenv(INTERVAL_ENV, "0.5")
    assert interval_from_env() == 0.5
    monkeypatch.setenv(INTERVAL_ENV, "soon")
    assert interval_from_env() == 5.0


# -- the CLI as CI runs it ---------------------------------------------------------------------------------

LINE = re.compile(r"^(\w+): (?:\d+:\d\d:\d\d )?([\d,]+)/([\d,]+) (\w+)")


def _logpipe(*args: str, interval: str = "0", columns: str | None = None) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, INTERVAL_ENV: interval}
    if columns is not None:
        env["COLUMNS"] = columns
    return subprocess.run([sys.executable, "-m", "logpipe.cli", *args], capture_output=True, text=True, env=env,
                          timeout=600, check=False)


def _progress_lines(stderr: str, label: str) -> list[tuple[int, int, str]]:
    found = [LINE.match(line) for line in stderr.splitlines()]
    return [(int(m[2].replace(",", "")), int(m[3].replace(",", "")), m[0]) for m in found if m and m[1] == label]


@pytest.fixture(scope="module")
def apollo(bundled: Path, tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, subprocess.CompletedProcess[str]]:
    """An ApolloScape dataset ingested in a subprocess with --json, one input per batch."""
    out = tmp_path_factory.mktemp("progress") / "apollo"
    run = _logpipe("ingest", str(bundled / "apolloscape"), "--out", str(out), "--batch-files", "1", "-j", "1",
                   "--no-mcap", "--json")
    assert run.returncode == 0, run.stderr
    return out, run


def test_ingest_off_a_terminal_prints_progress_lines_to_stderr_only(
        apollo: tuple[Path, subprocess.CompletedProcess[str]]) -> None:
    _, run = apollo
    summary = json.loads(run.stdout)  # stdout is exactly the one JSON object
    lines = _progress_lines(run.stderr, "ingest")
    assert [(done, total) for done, total, _ in lines] == [(1, 2), (2, 2), (2, 2)]  # no "0/2" line first
    assert summary["inputs_found"] == 2 == lines[0][1]
    assert re.fullmatch(r"ingest: 2/2 inputs \(100%\) [\d.,]+/s done in \d+:\d\d:\d\d", run.stderr.splitlines()[-1])


def test_predict_off_a_terminal_counts_every_selected_sample(
        apollo: tuple[Path, subprocess.CompletedProcess[str]], tmp_path: Path) -> None:
    from logpipe.dataset.reader import Dataset

    dataset, _ = apollo
    run = _logpipe("predict", str(dataset), "--predictor", "cv", "--out", str(tmp_path / "p"), "--no-mcap",
                   "--batch-size", "16", "--json")
    assert run.returncode == 0, run.stderr
    summary = json.loads(run.stdout)
    samples = Dataset.open(dataset).samples().num_rows
    lines = _progress_lines(run.stderr, "predict")
    assert len(lines) >= 3 and {total for _, total, _ in lines} == {samples} == {summary["samples_selected"]}
    dones = [done for done, _, _ in lines]
    assert dones == sorted(dones) and dones[-1] == samples
    eta = re.compile(r"predict: \d+:\d\d:\d\d [\d,]+/[\d,]+ samples \(\d+%\) [\d.,]+/s ETA \d+:\d\d:\d\d")
    assert any(eta.fullmatch(line) for line in run.stderr.splitlines())


def test_quiet_prints_no_progress_and_no_summary(
        apollo: tuple[Path, subprocess.CompletedProcess[str]], tmp_path: Path) -> None:
    dataset, _ = apollo
    run = _logpipe("-q", "predict", str(dataset), "--predictor", "cv", "--out", str(tmp_path / "p"), "--no-mcap")
    assert run.returncode == 0, run.stderr
    assert run.stdout == "" and run.stderr == ""
    assert (tmp_path / "p" / "manifest.json").is_file()
    failing = _logpipe("-q", "index", str(tmp_path / "missing"), "--min-targets", "2")
    assert failing.returncode == 2 and failing.stderr.startswith("error:")


def test_verbose_logs_per_batch_timings(bundled: Path, tmp_path: Path) -> None:
    run = _logpipe("-v", "ingest", str(bundled / "apolloscape"), "--out", str(tmp_path / "a"), "--batch-files", "1",
                   "-j", "1", "--no-mcap", interval="60")
    assert run.returncode == 0, run.stderr
    timings = [line for line in run.stderr.splitlines() if line.startswith("INFO logpipe.executor: _ingest_batch:")]
    assert [t.split(":")[2].split()[0] for t in timings] == ["1/2", "2/2"]
    # with a 60 s interval only the final progress line comes
    assert [done for done, _, _ in _progress_lines(run.stderr, "ingest")] == [2]


def test_train_off_a_terminal_counts_optimiser_steps(bundled: Path, tmp_path: Path) -> None:
    """``fit`` reports its step budget as the total and one unit per optimiser step."""
    data = tmp_path / "e"
    assert _logpipe("-q", "ingest", str(bundled / "ethucy"), "--out", str(data), "--no-mcap").returncode == 0
    config = tmp_path / "c.toml"
    config.write_text("[train]\nsteps = 3\neval_every = 3\nval_max_samples = 8\nnum_threads = 1\n")
    run = _logpipe("train", str(data), "--train-split", "eth/train", "--val-split", "hotel/test", "--config",
                   str(config), "--out", str(tmp_path / "run"), "--json")
    assert run.returncode == 0, run.stderr
    assert json.loads(run.stdout)["steps"] == 3
    lines = _progress_lines(run.stderr, "train")
    assert [(done, total) for done, total, _ in lines][-1] == (3, 3) and {t for _, t, _ in lines} == {3}


def test_a_run_with_nothing_to_do_writes_no_progress_line() -> None:
    """A rerun whose work is all done (a finished predict run) announces a total of 0: no "0/0 ... done" line."""
    reporter, clock, out = _reporter()
    reporter.total(0)
    clock.now = 2.0
    reporter.close()
    assert out.getvalue() == ""
