"""Runs independent work items on this machine's cores (default) or on a Ray cluster, results in order.

Work functions must be module-level and take one picklable argument. Locally, small jobs run inline
(no pool start-up cost); larger ones use a process pool, since parsing holds the GIL. With ``ray`` every
item is a Ray task; outputs must then go to a file system all nodes share.
"""

from __future__ import annotations

import importlib.abc
import logging
import multiprocessing
import os
import sys
import threading
import time
from collections.abc import Callable, Generator, Iterator, Sequence
from concurrent.futures import ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from typing import Any, Literal, TypeVar

from logpipe.errors import LogpipeError
from logpipe.progress import HEARTBEAT_THREAD

T = TypeVar("T")
R = TypeVar("R")
Backend = Literal["local", "ray"]

logger = logging.getLogger(__name__)


def default_workers() -> int:
    """Cores this process may use."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)


def _die_with(main_pid: int) -> None:
    """End this worker when the stage process ``main_pid`` dies (a killed stage must leave no worker behind:
    each holds ~100 MB and would wait forever for work).

    A forked worker asks the kernel for SIGKILL when its parent dies. A forkserver worker's parent is the
    server, which itself waits for its workers (each holds the server's keep-alive pipe), so there a daemon
    thread waits on a pidfd of the stage process and exits when it ends.
    """
    if sys.platform != "linux":
        return
    import ctypes
    import select
    import signal

    if os.getppid() == main_pid:
        pr_set_pdeathsig = 1
        ctypes.CDLL(None, use_errno=True).prctl(pr_set_pdeathsig, signal.SIGKILL, 0, 0, 0)
    try:
        pidfd = os.pidfd_open(main_pid)
    except ProcessLookupError:  # the stage ended before this worker started
        os._exit(1)
    except (OSError, AttributeError):  # a kernel without pidfds: the parent-death signal must do
        return

    def watch() -> None:
        select.select([pidfd], [], [])  # readable once the process has exited
        os._exit(1)

    threading.Thread(target=watch, name="logpipe-die-with-stage", daemon=True).start()


def _init_worker(main_pid: int) -> None:
    _die_with(main_pid)
    # One thread per worker process: the pool already uses every core.
    import pyarrow as pa

    pa.set_cpu_count(1)
    pa.set_io_thread_count(1)
    if "pandas" not in sys.modules:
        sys.meta_path.insert(0, _NoPandas())


class _NoPandas(importlib.abc.MetaPathFinder):
    """Makes ``import pandas`` fail (for good in a pool worker, for a moment in ``skip_pyarrow_pandas_probe``).

    pyarrow imports pandas, when it is installed, on its first conversion of any value (~1 s of CPU per
    process, the largest part of a worker's start-up) only to ask whether the value is a pandas object;
    work items never are, and on ImportError pyarrow treats pandas as absent. (A None entry in
    ``sys.modules`` would not do: pyarrow's compiled import takes the None for the module.)
    """

    def find_spec(self, name: str, path: Sequence[str] | None = None, target: object = None) -> None:
        if name == "pandas" or name.startswith("pandas."):
            raise ModuleNotFoundError("logpipe does not load pandas here", name=name)


def skip_pyarrow_pandas_probe() -> None:
    """Answer pyarrow's "is this a pandas object?" probe with no in this process, without loading pandas.

    For the ``logpipe`` command (~0.4 s of CPU per run here, ~1 s on slower machines, a large part of its
    start-up): pyarrow remembers the failed probe and no longer asks, while its explicit pandas APIs
    (``to_pandas``, ``from_pandas``, which Ray Data uses) try the import again once the refusal is lifted.
    """
    if "pandas" in sys.modules:
        return
    refusal = _NoPandas()
    sys.meta_path.insert(0, refusal)
    try:
        import pyarrow as pa

        pa.scalar(0)  # a first conversion asks whether the value is a pandas object
    finally:
        sys.meta_path.remove(refusal)


_FORK_UNSAFE_MODULES = ("torch", "cv2")
"""Libraries whose thread pools (OpenMP, OpenCV's own) do not survive a fork once loaded."""


def _fork_is_safe() -> bool:
    """Whether workers may be forked from this process directly.

    Forking copies only the calling thread: a lock another thread held stays locked in the child. Safe
    here when this process runs no Python threads besides the main one (a progress bar's refresh thread,
    a thread pool; progress heartbeats excepted: they hold their lock only while writing, and a fork takes
    it) and has not loaded torch or OpenCV, whose thread pools (OpenMP, OpenCV's own) do not survive a fork.
    The native threads numpy and pyarrow start at import (OpenBLAS workers, jemalloc's
    background thread) re-initialise in the child through their fork handlers.
    """
    others = [t for t in threading.enumerate() if t is not threading.current_thread() and t.name != HEARTBEAT_THREAD]
    return (sys.platform == "linux" and not others
            and not any(name in sys.modules for name in _FORK_UNSAFE_MODULES))


def _context(fn: Callable[..., Any]) -> multiprocessing.context.BaseContext:
    if _fork_is_safe():
        # Workers start in milliseconds with every module this process imported; a worker server would
        # first import them again (~0.4 s of a core, on a 2-core machine half a core-second per ingest).
        return multiprocessing.get_context("fork")
    context = multiprocessing.get_context("forkserver")
    # Workers fork from a server that already imported the work function's module: each worker then starts
    # in milliseconds instead of re-importing for ~0.5 s. Under the ``logpipe`` console script every worker
    # also re-imports that script (spawn semantics), i.e. the CLI: preloaded too, that costs nothing per worker.
    preload = [fn.__module__] + [m for m in ("logpipe.cli",) if m in sys.modules]
    context.set_forkserver_preload(preload)
    return context


def warm_up(fn: Callable[..., Any], *, workers: int = 0, backend: Backend = "local") -> None:
    """Start the local worker server for ``fn`` now, in the background.

    Its imports take ~1-2 s of one core; started before the caller's own serial work (finding and hashing
    inputs) they overlap it instead of delaying the first batch. A no-op when ``run_ordered`` would not use
    a pool or would fork its workers from this process (nothing to start).
    """
    if backend != "local" or (workers or default_workers()) <= 1 or _fork_is_safe():
        return
    from multiprocessing import forkserver

    _context(fn)
    forkserver.ensure_running()


def run_ordered(
    fn: Callable[[T], R], items: Sequence[T], *, workers: int = 0, backend: Backend = "local",
    queued: Callable[[T], None] | None = None,
) -> Iterator[R]:
    """Yield ``fn(item)`` for each item, in item order, computing up to ``workers`` at once.

    ``queued(item)``, when given, runs in this process as each item is queued, a batch or two before a
    worker starts it (e.g. to have the OS read the item's input files ahead); on Ray, in the task itself just
    before ``fn(item)``, on the node that reads the files (a few files in, the rest are already on their way).
    At INFO level (``logpipe -v``) each result is logged with the seconds since the previous one.
    """
    results = _run_ordered(fn, items, workers=workers, backend=backend, queued=queued)
    if not logger.isEnabledFor(logging.INFO):
        yield from results
        return
    started = last = time.perf_counter()
    try:
        for i, result in enumerate(results, 1):
            now = time.perf_counter()
            logger.info("%s: %d/%d done, %.2f s after the previous (%.1f s in all)",
                        getattr(fn, "__name__", "work"), i, len(items), now - last, now - started)
            last = now
            yield result
    finally:
        results.close()  # a consumer that stops early ends the pool now, as without the logging


def _run_ordered(
    fn: Callable[[T], R], items: Sequence[T], *, workers: int, backend: Backend,
    queued: Callable[[T], None] | None,
) -> Generator[R]:
    """``run_ordered`` without the logging."""
    workers = workers or default_workers()
    if backend == "ray":
        yield from _run_ray(fn if queued is None else _announcing(fn, queued), items, workers)
        return
    announce = queued or (lambda item: None)
    if workers <= 1 or len(items) <= 1:
        if items:
            announce(items[0])
        for i, item in enumerate(items):
            if i + 1 < len(items):
                announce(items[i + 1])  # one item ahead, while this one runs
            yield fn(item)
        return
    context = _context(fn)
    try:
        yield from _pooled(fn, items, workers, context, announce)
    except BrokenProcessPool:
        # Killed (the OOM killer, a signal) or crashed in native code: one line instead of the pool's traceback.
        name = getattr(fn, "__name__", "work")
        raise LogpipeError(f"a worker process running {name} died (killed, out of memory, or crashed); what was "
                           "committed before is kept: rerun the same command to finish") from None


def _pooled(fn: Callable[[T], R], items: Sequence[T], workers: int, context: multiprocessing.context.BaseContext,
            announce: Callable[[T], None]) -> Generator[R]:
    """``_run_ordered`` on a pool of ``workers`` processes."""
    with ProcessPoolExecutor(max_workers=min(workers, len(items)), mp_context=context,
                             initializer=_init_worker, initargs=(os.getpid(),)) as pool:
        # Bounded look-ahead keeps memory at ~2 batches per worker however many items there are.
        pending = []
        iterator = iter(items)
        for item in iterator:
            announce(item)
            pending.append(pool.submit(fn, item))
            if len(pending) >= 2 * workers:
                break
        for item in iterator:
            announce(item)
            yield pending.pop(0).result()
            pending.append(pool.submit(fn, item))
        for future in pending:
            yield future.result()


def _announcing(fn: Callable[[T], R], queued: Callable[[T], None]) -> Callable[[T], R]:
    """``fn`` that first runs ``queued`` on its item (a plain function: ``ray.remote`` takes no partials). Cold
    inputs cost a Ray ingest task ~50 ms a 250-file batch without it (10k AV1 files, caches dropped)."""

    def announced(item: T) -> R:
        queued(item)
        return fn(item)

    announced.__name__ = getattr(fn, "__name__", "work")
    return announced


def _run_ray(fn: Callable[[T], R], items: Sequence[T], workers: int) -> Iterator[R]:
    try:
        import ray
    except ImportError as exc:
        raise LogpipeError("--backend ray needs Ray: pip install 'logpipe[ray]'") from exc
    if not ray.is_initialized():
        address = os.environ.get("RAY_ADDRESS")
        ray.init(address=address) if address else ray.init(num_cpus=workers, include_dashboard=False)
    remote: Any = ray.remote(fn)
    refs = [remote.remote(item) for item in items]
    for ref in refs:
        yield ray.get(ref)
