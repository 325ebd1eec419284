"""``logpipe predict --backend ray``: the same output bytes as a local run, also when an actor dies mid-run."""

from __future__ import annotations

import json
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pyarrow.parquet as pq
import pytest

from logpipe.stages.ingest import IngestOptions, ingest
from logpipe.storage.write_journal import JOURNAL

pytestmark = pytest.mark.slow  # minutes of end-to-end work

ray = pytest.importorskip("ray", reason="Ray is a dev dependency; install logpipe[dev]")
pytest.importorskip("ray.data", reason="--backend ray needs Ray Data (logpipe[ray])")

REPO = Path(__file__).resolve().parents[2]
ETH_CHECKPOINT = REPO / "model" / "checkpoints" / "ethucy" / "eth"


@pytest.fixture(scope="module", autouse=True)
def ray_cluster() -> Iterator[None]:
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    yield
    ray.shutdown()


@pytest.fixture(scope="module")
def eth(tmp_path_factory: pytest.TempPathFactory) -> Path:
    root = tmp_path_factory.mktemp("eth")
    ingest([REPO / "tests" / "data" / "ethucy"], IngestOptions(out=root / "ds"))
    return root / "ds"


def _both(dataset: Path, tmp_path: Path, **settings: Any) -> tuple[dict[str, Any], dict[str, Any]]:
    from logpipe.stages.predict import predict_dataset

    local = predict_dataset(dataset, tmp_path / "local", backend="local", **settings)
    remote = predict_dataset(dataset, tmp_path / "ray", backend="ray", workers=2, **settings)
    return local, remote


def test_network_forecasts_on_ray_write_the_local_bytes(folder_digests: Callable[[Path], dict[str, str]], eth: Path,
                                                        tmp_path: Path) -> None:
    from logpipe.dataset.sample_filter import parse_filter

    # Small batches so the work is cut into several items over both actors; one torch thread on both sides (the
    # network's float32 reductions round by thread count, locally too).
    local, remote = _both(eth, tmp_path, checkpoint=ETH_CHECKPOINT, batch_size=2, threads=1,
                          sample_filter=parse_filter(["split=eth/test", "time=:60000000000"]))
    assert (local["backend"], remote["backend"]) == ("local", "ray")
    assert remote["samples"] == local["samples"] >= 5 and remote["rows"] == local["rows"] > 0
    files = folder_digests(tmp_path / "local")
    assert {"predictions/part-00000.parquet", "mcap/part-00000/biwi_eth.mcap", "manifest.json"} <= set(files)
    assert folder_digests(tmp_path / "ray") == files


def test_actors_predicting_whole_shards_write_the_local_bytes(folder_digests: Callable[[Path], dict[str, str]],
                                                             tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from logpipe.dataset.sample_filter import parse_filter
    from logpipe.model import ray_predict
    from logpipe.stages import predict

    # A shard per input file, and shard jobs from one shard per actor: each actor cuts, forecasts and writes whole
    # shards, and a killed actor's shard is retried (no partial or duplicate file).
    ingest([REPO / "tests" / "data" / "ethucy"], IngestOptions(out=tmp_path / "ds", batch_files=1))
    monkeypatch.setattr(ray_predict, "SHARDS_PER_WORKER", 1)
    monkeypatch.setattr(predict, "ray_forecasts", None)  # the batch-forecast path would fail
    monkeypatch.setenv(ray_predict.KILL_ONCE_ENV, str(tmp_path / "killed"))
    local, remote = _both(tmp_path / "ds", tmp_path, checkpoint=ETH_CHECKPOINT, batch_size=4, threads=1,
                          sample_filter=parse_filter(["time=:30000000000"]))
    assert (tmp_path / "killed").exists()
    assert remote["shards"] == local["shards"] == 3 and remote["samples"] == local["samples"] >= 30
    assert remote["mcap_files"] == 3 and remote["rows"] == local["rows"] > 0
    assert folder_digests(tmp_path / "ray") == folder_digests(tmp_path / "local")


def test_baseline_on_ray_writes_the_local_bytes(folder_digests: Callable[[Path], dict[str, str]], eth: Path,
                                                tmp_path: Path) -> None:
    from logpipe.dataset.sample_filter import parse_filter

    local, remote = _both(eth, tmp_path, predictor="cv", batch_size=16,
                          sample_filter=parse_filter(["time=:60000000000"]))
    assert remote["samples"] == local["samples"] > 100 and remote["mcap_files"] == 3
    assert folder_digests(tmp_path / "ray") == folder_digests(tmp_path / "local")


def test_constant_velocity_shard_tasks_on_ray_write_the_local_bytes(folder_digests: Callable[[Path], dict[str, str]],
                                                                    tmp_path: Path) -> None:
    # Parquet only: the columnar path, where each Ray task writes its shard's file and the driver commits.
    ingest([REPO / "tests" / "data" / "ethucy"], IngestOptions(out=tmp_path / "ds", write_mcap=False, batch_files=1))
    local, remote = _both(tmp_path / "ds", tmp_path, predictor="cv", write_mcap=False)
    assert remote["shards"] == local["shards"] >= 2 and remote["rows"] == local["rows"] > 0
    assert folder_digests(tmp_path / "ray") == folder_digests(tmp_path / "local")


def test_a_killed_actor_is_retried_without_duplicate_or_partial_output(folder_digests: Callable[[Path],
                                                                       dict[str, str]], eth: Path, tmp_path: Path,
                                                                       monkeypatch: pytest.MonkeyPatch) -> None:
    from logpipe.dataset.sample_filter import parse_filter
    from logpipe.model.ray_predict import KILL_ONCE_ENV

    marker = tmp_path / "killed"
    monkeypatch.setenv(KILL_ONCE_ENV, str(marker))
    local, remote = _both(eth, tmp_path, predictor="cv_sampler", modes=5, batch_size=16,
                          sample_filter=parse_filter(["time=:60000000000"]))
    assert marker.exists()  # an actor did die (os._exit at its first work item)
    assert remote["samples"] == local["samples"] > 100
    keys = ["sample_id", "track_id", "mode"]
    table = pq.read_table(tmp_path / "ray" / "predictions" / "part-00000.parquet", columns=keys)
    rows = list(zip(*(table.column(k).to_pylist() for k in keys), strict=True))
    assert len(rows) == len(set(rows)) == remote["rows"]  # each sample's targets and modes once
    assert folder_digests(tmp_path / "ray") == folder_digests(tmp_path / "local")
    manifest = json.loads((tmp_path / "ray" / "manifest.json").read_text())
    assert sorted(manifest["files"]) == sorted(k for k in folder_digests(tmp_path / "ray")
                                               if k not in ("manifest.json", JOURNAL))
