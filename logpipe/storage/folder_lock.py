"""The write lock of an output folder: one logpipe writer at a time, and a clear error naming the holder."""

from __future__ import annotations

import fcntl
import json
import os
import shlex
import sys
from pathlib import Path

from logpipe.errors import ArtifactBusyError

LOCK_FILE = ".logpipe.lock"
"""Names the lock holder's pid and command while the lock is held."""



class FolderLock:
    """An exclusive, non-blocking ``flock`` on the folder itself, released when the process ends.

    Locking the directory (not a file in it) leaves a finished folder's contents independent of who wrote
    it. While held, ``.logpipe.lock`` names the holder's pid and command for the error a second writer gets;
    it is removed on release (a crashed holder's stale copy is overwritten by the next one). The kernel
    drops the lock with the process, so a crashed writer never blocks the next one.
    """

    def __init__(self, root: Path) -> None:
        self.root = root
        self._fd: int | None = None
        self.found_stale = False
        """Whether a holder's ``.logpipe.lock`` was there when this one took the lock: a writer was killed."""

    def acquire(self) -> None:
        fd = os.open(self.root, os.O_RDONLY | os.O_DIRECTORY | os.O_CLOEXEC)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            os.close(fd)
            try:
                holder = (self.root / LOCK_FILE).read_text(encoding="utf-8", errors="replace")
            except OSError:
                holder = ""
            raise ArtifactBusyError(f"{self.root}: another logpipe process is writing here "
                                    f"({_describe_holder(holder)}); wait for it to finish") from None
        except BaseException:
            os.close(fd)
            raise
        self._fd = fd
        self.found_stale = (self.root / LOCK_FILE).exists()
        try:
            info = json.dumps({"pid": os.getpid(), "command": shlex.join(sys.argv)})
            (self.root / LOCK_FILE).write_text(info + "\n", encoding="utf-8")
        except BaseException:
            self.release()
            raise

    def release(self) -> None:
        if self._fd is None:
            return
        try:
            (self.root / LOCK_FILE).unlink(missing_ok=True)
        finally:
            os.close(self._fd)  # closing the last descriptor drops the flock
            self._fd = None

    @property
    def held(self) -> bool:
        return self._fd is not None


def _describe_holder(text: str) -> str:
    try:
        info = json.loads(text)
        return f"pid {info['pid']}: {info['command']}"
    except (ValueError, KeyError, TypeError):
        return "holder unknown"
