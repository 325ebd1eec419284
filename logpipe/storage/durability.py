"""Crash safety of writes: flushing new files and renames to disk, and the crash points that test it.

``crash_point`` marks each step of a commit (``logpipe.storage.artifact``) where a crash must leave a consistent
folder; ``LOGPIPE_CRASH_AT=N`` makes the process kill itself (SIGKILL) at the N-th one it reaches and
``LOGPIPE_CRASH_TRACE=FILE`` lists them (the crash-injection tests).
"""

from __future__ import annotations

import ctypes
import os
import signal
from dataclasses import dataclass
from pathlib import Path


@dataclass
class _CrashPlan:
    at: int
    trace: str | None
    pid: int
    reached: int = 0


def _crash_plan() -> _CrashPlan | None:
    at, trace = os.environ.get("LOGPIPE_CRASH_AT"), os.environ.get("LOGPIPE_CRASH_TRACE")
    if at is None and trace is None:
        return None
    return _CrashPlan(int(at) if at else 0, trace, os.getpid())


_PLAN = _crash_plan()


def crash_point(label: str) -> None:
    """A step of a commit where a crash must leave a consistent folder; a no-op unless a test asked for a crash.

    Counts only in the process that read the environment (worker processes write only staging files, which
    the random-time kills of the tests cover).
    """
    if _PLAN is None or os.getpid() != _PLAN.pid:
        return
    _PLAN.reached += 1
    if _PLAN.trace:
        with open(_PLAN.trace, "a", encoding="utf-8") as fh:
            fh.write(f"{_PLAN.reached}\t{label}\n")
    if _PLAN.reached == _PLAN.at:
        os.kill(os.getpid(), signal.SIGKILL)


def syncfs(folder: Path) -> None:
    """Flush every dirty page of ``folder``'s file system: one call instead of an fsync per new file."""
    fd = os.open(folder, os.O_RDONLY)
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        if getattr(libc, "syncfs", None) is None or libc.syncfs(fd) != 0:
            os.sync()
    finally:
        os.close(fd)


def fsync_dir(folder: Path) -> None:
    """Make renames inside ``folder`` durable."""
    fd = os.open(folder, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)
