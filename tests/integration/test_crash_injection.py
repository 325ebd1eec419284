"""Crash injection: kill a stage (SIGKILL, as a power cut or the OOM killer would) at every step of its commit
(each step's first and last pass where a stage commits shard after shard)
and at random times; the rerun must give the same bytes as an uninterrupted run, and no stray file or
process may remain.

Every stage runs as a real ``logpipe`` process. ``LOGPIPE_CRASH_TRACE`` lists the commit steps a run
reaches (``logpipe.storage.durability.crash_point``); ``LOGPIPE_CRASH_AT=N`` makes the process kill itself at the
N-th. Random-time kills hit the whole process group, workers included, at any instruction.
"""

from __future__ import annotations

import os
import random
import re
import shutil
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import pytest

from logpipe.dataset.reader import Dataset
from logpipe.storage.artifact import MANIFEST, verify_folder
from logpipe.storage.write_journal import JOURNAL

pytestmark = pytest.mark.slow  # minutes of end-to-end work

REPO = Path(__file__).resolve().parents[2]
DATA = REPO / "tests" / "data"
LOGPIPE = [sys.executable, "-m", "logpipe.cli"]
RANDOM_KILLS = int(os.environ.get("LOGPIPE_RANDOM_KILLS", "6"))
"""Random-time kills per stage: 6 in ``make test``, 20 in ``make fuzz``."""


@dataclass
class Stage:
    """A stage to crash: how to make its starting state, its command, and the folder it writes."""

    name: str
    prepare: Callable[[Path], None]
    command: Callable[[Path], list[str]]
    output: Callable[[Path], Path]


def _ingest_inputs(work: Path) -> Path:
    src = work / "inputs"
    src.mkdir(parents=True, exist_ok=True)
    for p in sorted((DATA / "argoverse1").glob("*.csv"))[:4]:
        shutil.copy(p, src / p.name)
    return src


def _prepare_nothing(work: Path) -> None:
    _ingest_inputs(work)


def _prepare_dataset(work: Path) -> None:
    """An ingested dataset (two shards) as the starting state of index, rasterise and predict."""
    src = _ingest_inputs(work)
    _run([*LOGPIPE, "ingest", str(src), "--out", str(work / "ds"), "--batch-files", "2", "--workers", "1"])


def _prepare_ethucy(work: Path) -> None:
    _run([*LOGPIPE, "ingest", str(DATA / "ethucy"), "--out", str(work / "ds"), "--no-mcap"])


STAGES = [
    Stage("ingest", _prepare_nothing,
          lambda w: [*LOGPIPE, "ingest", str(w / "inputs"), "--out", str(w / "ds"), "--batch-files", "1",
                     "--workers", "2"],
          lambda w: w / "ds"),
    Stage("index", _prepare_ethucy,
          lambda w: [*LOGPIPE, "index", str(w / "ds"), "--min-targets", "2"],
          lambda w: w / "ds"),
    Stage("rasterise", _prepare_dataset,
          lambda w: [*LOGPIPE, "rasterise", str(w / "ds"),
                     "--map", f"MIA={DATA / 'maps/MIA_lane_centerlines_crop_2645.npz'}",
                     "--map", f"PIT={DATA / 'maps/PIT_lane_centerlines_crop_3861.npz'}", "--shard-size", "1",
                     "--workers", "2"],
          lambda w: w / "ds" / "rasters"),
    Stage("predict", _prepare_dataset,
          lambda w: [*LOGPIPE, "predict", str(w / "ds"), "--predictor", "cv", "--out", str(w / "pred")],
          lambda w: w / "pred"),
]


def _run(cmd: list[str], env: dict[str, str] | None = None) -> subprocess.CompletedProcess[str]:
    result = subprocess.run(cmd, env={**os.environ, **(env or {})}, capture_output=True, text=True, cwd=REPO,
                            timeout=300, check=False)
    if env is None or "LOGPIPE_CRASH_AT" not in env:
        assert result.returncode == 0, result.stderr[-2000:]
    return result


def _tree(folder: Path) -> dict[str, bytes]:
    """Every file under ``folder`` (relative path → bytes): what 'byte-identical' compares. Not the write journal:
    it records inodes and times of the files, which no two runs share."""
    if not folder.exists():
        return {}
    return {p.relative_to(folder).as_posix(): p.read_bytes() for p in sorted(folder.rglob("*"))
            if p.is_file() and p.name != JOURNAL}


def _session_processes(sid: int) -> list[int]:
    """Live processes of session ``sid`` (zombies excluded): the stage and every worker it started."""
    found = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            stat = (entry / "stat").read_text()
        except OSError:
            continue
        fields = stat[stat.rindex(")") + 2:].split()
        if int(fields[3]) == sid and fields[0] != "Z":
            found.append(int(entry.name))
    return found


def _no_process_left(sid: int) -> bool:
    deadline = time.monotonic() + 10
    while _session_processes(sid):
        if time.monotonic() > deadline:
            return False
        time.sleep(0.05)
    return True


def _assert_consistent(stage: Stage, work: Path) -> None:
    """After a crash the folder is at a committed state: old or new, never a mixture."""
    out = stage.output(work)
    folders = [out] if stage.name != "rasterise" else [p.parent for p in out.glob(f"*/{MANIFEST}")]
    for folder in folders:
        if not (folder / MANIFEST).exists():
            continue
        problems, _ = verify_folder(folder)
        assert not problems, [p.line() for p in problems]
        if stage.name in ("ingest", "index"):
            ds = Dataset.open(folder)
            assert ds.samples().num_rows == ds.manifest["totals"]["samples"]


Reference = tuple[Path, Path, dict[str, bytes], list[str], float]


@pytest.fixture(scope="module")
def references(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Reference]:
    """Per stage: its prepared starting state, the folder every run of it uses (manifests record absolute
    input paths, so the reference and the crashed runs share one), the uninterrupted output, the commit steps
    it passes and its time."""
    refs = {}
    for stage in STAGES:
        root = tmp_path_factory.mktemp(stage.name)
        base, work = root / "base", root / "work"
        base.mkdir()
        stage.prepare(base)
        shutil.copytree(base, work)
        trace = root / "trace.tsv"
        started = time.perf_counter()
        _run(stage.command(work), {"LOGPIPE_CRASH_TRACE": str(trace)})
        seconds = time.perf_counter() - started
        steps = [line.split("\t", 1)[1] for line in trace.read_text().splitlines()]
        refs[stage.name] = (base, work, _tree(stage.output(work)), steps, seconds)
        shutil.rmtree(work)
    return refs


def distinct_steps(steps: list[str]) -> list[int]:
    """The 1-based positions of ``steps`` worth a kill: the first and the last time each step is reached.

    A step is its label with file names' numbers dropped: a stage that commits shard after shard passes the same
    instructions once per shard (``before rename part-00001.parquet`` is ``before rename part-00000.parquet`` one
    shard later). The first pass has nothing committed before it, the last has everything else committed before
    it; the passes between repeat one of those states with another count of finished shards.
    """
    shape = [re.sub(r"\d+", "#", step) for step in steps]
    first = {s: shape.index(s) for s in shape}
    last = {s: len(shape) - 1 - shape[::-1].index(s) for s in shape}
    return sorted(i + 1 for i in {*first.values(), *last.values()})


def test_distinct_steps_keep_each_step_s_first_and_last_pass() -> None:
    commit = ["before sync", "before rename manifest.json", "after manifest"]
    shards = [f"move tracks/part-0000{k}.parquet" for k in range(4)]
    assert distinct_steps(shards + commit) == [1, 4, 5, 6, 7]
    assert distinct_steps(commit * 3) == [1, 2, 3, 7, 8, 9]
    assert distinct_steps(commit) == [1, 2, 3]


@pytest.mark.parametrize("stage", STAGES, ids=[s.name for s in STAGES])
def test_kill_at_every_commit_step_then_rerun_is_identical(
    stage: Stage, references: dict[str, Reference]
) -> None:
    base, work, expected, steps, _ = references[stage.name]
    assert len(steps) >= 4, steps  # the stage reaches its commit steps (renames, sync, manifest)
    assert any("manifest" in s for s in steps)
    for n in distinct_steps(steps):
        shutil.copytree(base, work)
        crashed = _run(stage.command(work), {"LOGPIPE_CRASH_AT": str(n)})
        assert crashed.returncode == -signal.SIGKILL, (n, steps[n - 1], crashed.stderr[-1000:])
        _assert_consistent(stage, work)
        _run(stage.command(work))
        assert _tree(stage.output(work)) == expected, f"{stage.name}: rerun after a kill at {steps[n - 1]!r} differs"
        shutil.rmtree(work)


@pytest.mark.parametrize("stage", STAGES, ids=[s.name for s in STAGES])
def test_kill_at_random_times_then_rerun_is_identical(
    stage: Stage, references: dict[str, Reference]
) -> None:
    base, work, expected, _, seconds = references[stage.name]
    rng = random.Random(f"crash-{stage.name}")
    for k in range(RANDOM_KILLS):
        shutil.copytree(base, work)
        proc = subprocess.Popen(stage.command(work), cwd=REPO, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                                start_new_session=True)
        time.sleep(rng.uniform(0.0, seconds))
        # Odd kills hit only the stage's own process: its workers must die with it.
        os.kill(proc.pid, signal.SIGKILL) if k % 2 else os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()
        assert _no_process_left(proc.pid), f"{stage.name}: processes outlived a kill: {_session_processes(proc.pid)}"
        _assert_consistent(stage, work)
        _run(stage.command(work))
        assert _tree(stage.output(work)) == expected, f"{stage.name}: rerun after a kill at {k} differs"
        shutil.rmtree(work)
