"""The executor runs batches in order locally (inline or in a process pool) and on Ray, with equal results."""

from __future__ import annotations

from pathlib import Path

import pytest

from logpipe.executor import run_ordered
from logpipe.stages.ingest import IngestOptions, ingest


def square(x: int) -> int:
    return x * x


@pytest.mark.parametrize("workers", [1, 2])
def test_local_results_come_back_in_order(workers: int) -> None:
    assert list(run_ordered(square, list(range(9)), workers=workers)) == [x * x for x in range(9)]


def test_ray_backend_writes_the_same_shards_as_local(bundled: Path, tmp_path: Path) -> None:
    ray = pytest.importorskip("ray", reason="Ray is a dev dependency; install logpipe[dev]")
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    try:
        remote = ingest([bundled / "argoverse1"], IngestOptions(out=tmp_path / "ray", backend="ray", batch_files=2))
    finally:
        ray.shutdown()
    local = ingest([bundled / "argoverse1"], IngestOptions(out=tmp_path / "local", batch_files=2))
    assert remote["shards_written"] == local["shards_written"]
    for shard in local["shards_written"]:
        assert (tmp_path / "ray" / shard).read_bytes() == (tmp_path / "local" / shard).read_bytes()
