"""``logpipe predict`` then ``logpipe score`` on its output folder, for every dataset kind with a sample; and the
prediction run's guarantees: log ids never escape ``--out``, OS errors are one line with the committed state
intact, one writer per folder, and an interrupted run resumes to the same bytes as an uninterrupted one."""

from __future__ import annotations

import errno
import json
import os
import subprocess
import sys
from pathlib import Path
from typing import Any

import pyarrow as pa
import pyarrow.compute as pc
import pytest

from logpipe.dataset.reader import Dataset
from logpipe.dataset.sample_filter import parse_filter
from logpipe.errors import ArtifactBusyError, DatasetError, LogpipeError, OutputError
from logpipe.prediction.runs import PredictionRun
from logpipe.stages.ingest import IngestOptions, ingest
from logpipe.stages.predict import predict_dataset
from logpipe.stages.score import score
from logpipe.storage.folder_lock import LOCK_FILE, FolderLock
from logpipe.storage.write_journal import JOURNAL

REPO = Path(__file__).resolve().parents[2]
BUNDLED = REPO / "tests" / "data"
SHARED = (REPO.parent / "shared" / "data").resolve()

# kind -> (inputs, score options); small samples, every kind logpipe ingests
KINDS: dict[str, tuple[list[Path], dict[str, Any]]] = {
    "argoverse1": ([BUNDLED / "maps" / "2645.csv", BUNDLED / "maps" / "3861.csv"], {"agents": "focal"}),
    "ethucy": ([BUNDLED / "ethucy"], {"split": "eth/test", "min_agents": 2}),
    "apolloscape": ([BUNDLED / "apolloscape"], {}),
    "rosbag": ([BUNDLED / "rosbags" / "datmo" / "intersection.bag"], {}),
    "av2": ([SHARED / "av2" / "scenario_0a1e6f0a-1817-4a98-b02e-db8c9327d151.parquet"], {"agents": "focal"}),
    "mcap": ([SHARED / "mcap" / "evo" / "nav2_turtlebot.mcap"], {}),
}


# A predict run in its own process, for LOGPIPE_CRASH_AT/TRACE (read at import): cv_sampler over 3 shards.
_CRASHING_RUN = """
import sys
from pathlib import Path
from logpipe.dataset.sample_filter import parse_filter
from logpipe.stages.predict import predict_dataset
predict_dataset(Path(sys.argv[1]), Path(sys.argv[2]), predictor="cv_sampler",
                sample_filter=parse_filter(["time=:12000000000"]), threads=1)
"""


def _files(root: Path) -> dict[str, bytes]:
    """Every file under ``root`` (relative POSIX path -> bytes), but the write journal: it records the files' inodes
    and times, which no two runs share (``logpipe.storage.write_journal``)."""
    return {p.relative_to(root).as_posix(): p.read_bytes() for p in sorted(root.rglob("*"))
            if p.is_file() and p.name != JOURNAL}


@pytest.fixture(scope="module")
def eth_dataset(tmp_path_factory: pytest.TempPathFactory) -> Path:
    root = tmp_path_factory.mktemp("eth")
    ingest([BUNDLED / "ethucy"], IngestOptions(out=root / "ds", workers=1, batch_files=1))  # 3 shards
    return root / "ds"


@pytest.mark.parametrize("kind", list(KINDS))
def test_score_reads_the_folder_predict_wrote(kind: str, tmp_path: Path) -> None:
    inputs, options = KINDS[kind]
    if not all(p.exists() for p in inputs):
        pytest.skip(f"sample of {kind} absent ({inputs[0]}; ../shared/data holds it)")
    ingest(inputs, IngestOptions(out=tmp_path / "ds", workers=1))
    split = options.get("split")
    sample_filter = parse_filter([f"split={split}"] if split else [])
    summary = predict_dataset(tmp_path / "ds", tmp_path / "cv", predictor="cv", sample_filter=sample_filter,
                              threads=1)
    assert summary["samples"] > 0 and summary["mcap_files"] == summary["logs_selected"]
    report = score([tmp_path / "cv"], tmp_path / "ds", tmp_path / "report", plots=False, **options)
    entry = report["methods"]["cv"]
    run = PredictionRun.open(tmp_path / "cv")
    assert entry["num_modes"] == run.meta.num_modes == summary["num_modes"]
    assert entry["metadata"]["protocol"] == report["protocol"]["dataset_protocol"]["name"]
    assert entry["metadata"]["pred_len"] == report["protocol"]["pred_len"] and entry["same_dataset"] is True
    assert entry["overall"]["agents"] > 0 and entry["counts"]["agents_missing"] == 0
    assert entry["source"] == str(tmp_path / "cv")
    committed = json.loads((tmp_path / "report" / "manifest.json").read_text())
    assert set(committed["files"]) == {"report.json", "report.md"}


def test_two_folders_are_two_methods_and_a_rerun_gives_the_same_report(eth_dataset: Path, tmp_path: Path) -> None:
    """ETH test split with the constant-velocity baseline and the shipped checkpoint of the ETH fold."""
    f = parse_filter(["split=eth/test"])
    predict_dataset(eth_dataset, tmp_path / "cv", predictor="cv", sample_filter=f, write_mcap=False, threads=1)
    net = predict_dataset(eth_dataset, tmp_path / "zhu", sample_filter=f, write_mcap=False, threads=1)
    assert net["predictor"] == "zhu2020" and net["num_modes"] == 20
    runs = [tmp_path / "cv", tmp_path / "zhu"]
    report = score(runs, eth_dataset, tmp_path / "r", split="eth/test", min_agents=2, plots=True, plot_samples=2)
    assert list(report["methods"]) == ["cv", "zhu2020"]
    assert report["methods"]["zhu2020"]["ks"] == [1, 20] and report["methods"]["cv"]["ks"] == [1, 20]
    zhu = report["methods"]["zhu2020"]["overall"]
    assert zhu["k20"]["ade"] < report["methods"]["cv"]["overall"]["k20"]["ade"]  # best-of-20 beats CV
    assert zhu["agents"] == report["methods"]["cv"]["overall"]["agents"] > 0
    first = _files(tmp_path / "r")
    assert {"report.json", "report.md", "manifest.json", "horizon.png", "scenes_cv.png", "scenes_zhu2020.png"} \
        == set(first)
    score(runs, eth_dataset, tmp_path / "r", split="eth/test", min_agents=2, plots=True, plot_samples=2)
    assert _files(tmp_path / "r") == first
    # Two runs of one predictor are told apart by their folder names.
    predict_dataset(eth_dataset, tmp_path / "cv-again", predictor="cv", sample_filter=f, write_mcap=False, threads=1)
    both = score([tmp_path / "cv", tmp_path / "cv-again"], eth_dataset, tmp_path / "r2", split="eth/test",
                 plots=False)
    assert list(both["methods"]) == ["cv", "cv-again"]


def test_a_damaged_run_is_one_line_and_score_never_overwrites_another_artifact(eth_dataset: Path,
                                                                              tmp_path: Path) -> None:
    predict_dataset(eth_dataset, tmp_path / "cv", predictor="cv", sample_filter=parse_filter(["time=:8000000000"]),
                    write_mcap=False, threads=1)
    with pytest.raises(LogpipeError, match="not a prediction run"):
        score([eth_dataset], eth_dataset, tmp_path / "r", plots=False)
    with pytest.raises(LogpipeError, match="another logpipe artifact"):
        score([tmp_path / "cv"], eth_dataset, tmp_path / "cv", plots=False)
    part = tmp_path / "cv" / "predictions" / "part-00000.parquet"
    part.write_bytes(part.read_bytes()[:-100])
    with pytest.raises(LogpipeError, match="truncated") as err:
        score([tmp_path / "cv"], eth_dataset, tmp_path / "r", plots=False)
    assert "\n" not in str(err.value)


def test_a_log_id_that_is_a_path_is_refused_and_nothing_is_written(eth_dataset: Path, tmp_path: Path,
                                                                  monkeypatch: pytest.MonkeyPatch) -> None:
    """A hand-made dataset (ingest refuses such ids) whose logs table names a log ``../../x``: the reader's
    table is what predict sees."""
    read_logs = Dataset.logs

    def escaping(dataset: Dataset) -> pa.Table:
        logs = read_logs(dataset)
        ids = pc.replace_substring(logs.column("log_id"), "biwi_eth", "../../x")
        return logs.set_column(logs.schema.get_field_index("log_id"), "log_id", ids)

    monkeypatch.setattr(Dataset, "logs", escaping)
    out = tmp_path / "deep" / "er" / "out"
    with pytest.raises(DatasetError, match="not a single file name"):
        predict_dataset(eth_dataset, out, predictor="cv", threads=1)
    assert not out.exists() and not list(tmp_path.rglob("x.mcap"))


def test_an_os_error_is_one_line_and_keeps_the_committed_state(eth_dataset: Path, tmp_path: Path,
                                                              monkeypatch: pytest.MonkeyPatch) -> None:
    """A run killed (SIGKILL, at a crash point) just after committing shard 0, then a read-only file system
    (os.replace refused; tests run as root, so chmod cannot show it): OutputError, the folder as committed; a
    rerun then skips shard 0 and finishes the run to an uninterrupted run's bytes."""
    f = parse_filter(["time=:12000000000"])  # _CRASHING_RUN's
    trace = tmp_path / "trace"
    subprocess.run([sys.executable, "-c", _CRASHING_RUN, str(eth_dataset), str(tmp_path / "whole")],
                   env={**os.environ, "LOGPIPE_CRASH_TRACE": str(trace)}, check=True)
    assert len(json.loads((tmp_path / "whole" / "manifest.json").read_text())["shards"]) == 3
    assert len(list((tmp_path / "whole" / "mcap").rglob("*.mcap"))) == 3
    steps = trace.read_text().splitlines()
    first_commit = next(int(s.split("\t")[0]) for s in steps if s.endswith("\tafter manifest"))
    out = tmp_path / "out"
    killed = subprocess.run([sys.executable, "-c", _CRASHING_RUN, str(eth_dataset), str(out)],
                            env={**os.environ, "LOGPIPE_CRASH_AT": str(first_commit)}, check=False)
    assert killed.returncode == -9
    committed = _files(out)
    assert committed.pop(LOCK_FILE)  # the killed writer's note; the next writer's lock replaces and removes it
    assert json.loads(committed["manifest.json"])["shards"][0]["file"] == "predictions/part-00000.parquet"
    assert len(json.loads(committed["manifest.json"])["shards"]) == 1

    def read_only(src: object, dst: object) -> None:
        raise OSError(errno.EROFS, "Read-only file system", str(dst))

    with monkeypatch.context() as m:
        m.setattr(os, "replace", read_only)
        with pytest.raises(OutputError, match="read-only file system") as err:
            predict_dataset(eth_dataset, out, predictor="cv_sampler", sample_filter=f, threads=1)
    assert "\n" not in str(err.value) and "previous state" in str(err.value)
    assert _files(out) == committed
    again = predict_dataset(eth_dataset, out, predictor="cv_sampler", sample_filter=f, threads=1)
    assert again["shards_skipped_done"] == 1
    assert _files(out) == _files(tmp_path / "whole")


def test_a_second_writer_fails_at_once_naming_the_first(eth_dataset: Path, tmp_path: Path) -> None:
    out = tmp_path / "out"
    out.mkdir()
    lock = FolderLock(out)
    lock.acquire()
    try:
        with pytest.raises(ArtifactBusyError, match=f"pid {os.getpid()}"):
            predict_dataset(eth_dataset, out, predictor="cv", threads=1)
    finally:
        lock.release()
    assert not (out / "manifest.json").exists()


def test_a_crash_at_any_commit_step_resumes_to_the_same_bytes(eth_dataset: Path, tmp_path: Path) -> None:
    """A subprocess killed (SIGKILL) at commit steps of the protocol, then a rerun: every file as an uninterrupted
    run writes it. Steps: first, the middle and the last but one of the traced run (each costs a process)."""
    env = {**os.environ, "LOGPIPE_CRASH_TRACE": str(tmp_path / "trace")}
    subprocess.run([sys.executable, "-c", _CRASHING_RUN, str(eth_dataset), str(tmp_path / "whole")], env=env,
                   check=True)
    steps = (tmp_path / "trace").read_text().splitlines()
    assert any("after manifest" in s for s in steps)
    whole = _files(tmp_path / "whole")
    for at in sorted({1, len(steps) // 2, len(steps) - 1}):
        out = tmp_path / f"crash{at}"
        env = {**os.environ, "LOGPIPE_CRASH_AT": str(at)}
        done = subprocess.run([sys.executable, "-c", _CRASHING_RUN, str(eth_dataset), str(out)], env=env, check=False)
        assert done.returncode == -9, steps[at - 1]
        predict_dataset(eth_dataset, out, predictor="cv_sampler", sample_filter=parse_filter(["time=:12000000000"]),
                        threads=1)
        assert _files(out) == whole, steps[at - 1]
