"""The executor runs batches in order locally (inline or in a process pool) and on Ray, with equal results."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from logpipe.errors import LogpipeError
from logpipe.executor import run_ordered
from logpipe.stages.ingest import IngestOptions, ingest


def square(x: int) -> int:
    return x * x


@pytest.mark.parametrize("workers", [1, 2])
def test_local_results_come_back_in_order(workers: int) -> None:
    assert list(run_ordered(square, list(range(9)), workers=workers)) == [x * x for x in range(9)]


@pytest.mark.slow
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


def test_on_ray_each_task_runs_queued_on_its_own_item_first(tmp_path: Path) -> None:
    # Read-ahead belongs on the node that reads the files: the task itself, not the driver.
    ray = pytest.importorskip("ray", reason="Ray is a dev dependency; install logpipe[dev]")

    # Local functions: Ray's workers cannot import this test module, so these travel by value.
    def _mark(item: tuple[Path, int]) -> None:
        (item[0] / f"queued-{item[1]}-{os.getpid()}").touch()

    def _marked_here(item: tuple[Path, int]) -> bool:
        return (item[0] / f"queued-{item[1]}-{os.getpid()}").exists()

    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    try:
        items = [(tmp_path, i) for i in range(5)]
        done = list(run_ordered(_marked_here, items, workers=2, backend="ray", queued=_mark))
    finally:
        ray.shutdown()
    assert done == [True] * 5  # each item's mark was made in the process that ran it, before it ran
    assert not any(p.name.endswith(f"-{os.getpid()}") for p in tmp_path.iterdir())  # none by the driver


@pytest.mark.parametrize("fork", [True, False])
def test_forked_and_served_workers_give_the_same_results(fork: bool, monkeypatch: pytest.MonkeyPatch) -> None:
    from logpipe import executor

    monkeypatch.setattr(executor, "_fork_is_safe", lambda: fork)
    assert executor._context(square).get_start_method() == ("fork" if fork else "forkserver")
    assert list(run_ordered(square, list(range(7)), workers=2)) == [x * x for x in range(7)]


def test_workers_fork_only_without_threads_torch_or_opencv(monkeypatch: pytest.MonkeyPatch) -> None:
    """A lock held by another thread would stay locked in a forked child, and the thread pools of torch and
    OpenCV do not survive a fork: then the pool's workers come from the worker server instead."""
    import sys
    import threading

    from logpipe import executor
    from logpipe.executor import _fork_is_safe

    monkeypatch.delitem(sys.modules, "torch", raising=False)
    monkeypatch.delitem(sys.modules, "cv2", raising=False)
    release = threading.Event()
    thread = threading.Thread(target=release.wait)
    thread.start()
    try:
        assert not _fork_is_safe()  # a real second thread (whatever else this test process runs)
    finally:
        release.set()
        thread.join()
    # This test process may run threads of its own (e.g. left by other tests): count only the main one.
    monkeypatch.setattr(executor.threading, "active_count", lambda: 1)
    assert _fork_is_safe()
    for unsafe in ("torch", "cv2"):  # any module object stands for the loaded library
        with monkeypatch.context() as patched:
            patched.setitem(sys.modules, unsafe, sys)
            assert not _fork_is_safe()
    assert _fork_is_safe()


@pytest.mark.parametrize("workers", [1, 2])
def test_each_item_is_announced_before_its_result(workers: int) -> None:
    events: list[tuple[str, int]] = []
    for result in run_ordered(square, list(range(6)), workers=workers, queued=lambda x: events.append(("queued", x))):
        events.append(("result", result))
    announced = [x for kind, x in events if kind == "queued"]
    assert announced == list(range(6))
    for x in range(6):
        assert events.index(("queued", x)) < events.index(("result", x * x))


def _die_on_three(item: int) -> int:
    if item == 3:
        os._exit(1)  # as the OOM killer would end it: no exception, no cleanup
    return item


def test_a_worker_that_dies_is_one_clear_error() -> None:
    with pytest.raises(LogpipeError, match="a worker process running _die_on_three died"):
        list(run_ordered(_die_on_three, list(range(6)), workers=2))


def test_the_command_runs_without_pandas_yet_pandas_apis_still_work(bundled: Path, tmp_path: Path) -> None:
    """``logpipe`` skips pyarrow's pandas probe (a large part of its start-up), an ingest and the Parquet reads after it
    never load pandas, and an explicit pandas API of pyarrow still loads and uses it. In a fresh interpreter: this
    one may hold pandas already."""
    script = f"""
import sys
from logpipe.cli import main
sys.argv = ["logpipe", "-q", "ingest", {str(bundled / "ethucy")!r}, "--out", {str(tmp_path / "ds")!r}, "--no-mcap"]
try:
    main()
except SystemExit as stop:
    assert stop.code in (0, None), stop.code
from logpipe.dataset.reader import Dataset
samples = Dataset.open({str(tmp_path / "ds")!r}).samples()
assert samples.num_rows > 0 and "pandas" not in sys.modules, "pandas was loaded"
frame = samples.slice(0, 3).to_pandas()
assert "pandas" in sys.modules and len(frame) == 3
import pyarrow as pa
assert pa.Table.from_pandas(frame).num_rows == 3
"""
    run = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=300, check=False)
    assert run.returncode == 0, run.stderr[-2000:]
