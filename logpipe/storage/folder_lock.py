"""The write lock of an output folder: one logpipe writer at a time, and a clear error naming the holder."""

from __future__ import annotations

import errno
import fcntl
import json
import os
import shlex
import stat
import sys
from pathlib import Path

from logpipe.errors import ArtifactBusyError, DatasetError, OutputError

LOCK_FILE = ".logpipe.lock"
"""Names the lock holder's pid and command while the lock is held."""

_HOLDER_MAX_BYTES = 4096
_ATTEMPTS = 5


class FolderLock:
    """An exclusive, non-blocking ``flock`` on the folder itself, released when the process ends.

    Locking the directory (not a file in it) leaves a finished folder's contents independent of who wrote
    it. While held, ``.logpipe.lock`` names the holder's pid and command for the error a second writer gets;
    it is removed on release (a crashed holder's stale copy is replaced by the next one). The kernel
    drops the lock with the process, so a crashed writer never blocks the next one.

    The lock file is never written through a link: a symlink or special file of that name is refused, a
    stale regular one is unlinked and a new one created with ``O_EXCL | O_NOFOLLOW`` relative to the locked
    folder's descriptor (so a hard link to someone's file is never written either).
    """

    def __init__(self, root: Path) -> None:
        self.root = root
        self._fd: int | None = None
        self._inode: tuple[int, int] | None = None
        self.found_stale = False
        """Whether a holder's ``.logpipe.lock`` was there when this one took the lock: a writer was killed."""

    def acquire(self) -> None:
        for _ in range(_ATTEMPTS):
            fd = self._lock_folder()
            # A writer cleaning up its failed first run removes its (empty) folder while it holds the lock: a
            # descriptor opened before that names a deleted folder, so the lock is only ours if the path still
            # leads to the folder we locked.
            try:
                here, there = os.fstat(fd), os.stat(self.root)
            except OSError:
                os.close(fd)
                continue
            if (here.st_dev, here.st_ino) == (there.st_dev, there.st_ino):
                break
            os.close(fd)
        else:
            raise DatasetError(f"{self.root}: the folder was removed or replaced while taking its lock; run again")
        self._fd = fd
        try:
            self._write_holder(fd)
        except BaseException:
            self.release()
            raise

    def _lock_folder(self) -> int:
        fd = os.open(self.root, os.O_RDONLY | os.O_DIRECTORY | os.O_CLOEXEC)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = _read_holder(fd)
            os.close(fd)
            raise ArtifactBusyError(f"{self.root}: another logpipe process is writing here "
                                    f"({_describe_holder(holder)}); wait for it to finish") from None
        except BaseException:
            os.close(fd)
            raise
        return fd

    def _write_holder(self, fd: int) -> None:
        path = self.root / LOCK_FILE
        try:
            found = os.stat(LOCK_FILE, dir_fd=fd, follow_symlinks=False)
        except FileNotFoundError:
            found = None
        if found is not None and not stat.S_ISREG(found.st_mode):
            raise OutputError(_not_ours(path, found.st_mode))
        self.found_stale = found is not None
        if found is not None:  # a killed holder's file, or a hard link: never write into it, replace it
            os.unlink(LOCK_FILE, dir_fd=fd)
        info = json.dumps({"pid": os.getpid(), "command": shlex.join(sys.argv)}) + "\n"
        flags = os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW | os.O_CLOEXEC
        try:
            out = os.open(LOCK_FILE, flags, 0o644, dir_fd=fd)
        except FileExistsError:  # a link made in the instant since the unlink
            raise OutputError(f"{path}: appeared while taking the lock (not logpipe's); remove it") from None
        try:
            os.write(out, info.encode())
            mine = os.fstat(out)
            self._inode = (mine.st_dev, mine.st_ino)
        finally:
            os.close(out)

    def release(self, *, remove_folder: bool = False) -> None:
        """Drop the lock; ``remove_folder``: first remove the folder when it is empty but for the lock file (a
        failed first run), while still holding the lock so no other writer's files can be in it."""
        if self._fd is None:
            return
        try:
            self._unlink_own_holder()
            if remove_folder:
                try:
                    os.rmdir(self.root)
                except OSError as exc:
                    if exc.errno not in (errno.ENOTEMPTY, errno.EEXIST, errno.ENOENT, errno.EBUSY):
                        raise
        finally:
            os.close(self._fd)  # closing the last descriptor drops the flock
            self._fd = None

    def _unlink_own_holder(self) -> None:
        assert self._fd is not None
        try:
            found = os.stat(LOCK_FILE, dir_fd=self._fd, follow_symlinks=False)
        except FileNotFoundError:
            return
        if (found.st_dev, found.st_ino) == self._inode:  # only the file this lock wrote, never a link found here
            os.unlink(LOCK_FILE, dir_fd=self._fd)

    @property
    def held(self) -> bool:
        return self._fd is not None


def _not_ours(path: Path, mode: int) -> str:
    what = "a symbolic link" if stat.S_ISLNK(mode) else "a folder" if stat.S_ISDIR(mode) else "a special file"
    return (f"{path}: is {what}, not logpipe's lock file; logpipe never writes through links or into special "
            "files: remove it")


def _read_holder(fd: int) -> str:
    """The holder's lock file text, read without following a link or blocking on a FIFO."""
    try:
        held = os.open(LOCK_FILE, os.O_RDONLY | os.O_NOFOLLOW | os.O_NONBLOCK | os.O_CLOEXEC, dir_fd=fd)
    except OSError:
        return ""
    try:
        if not stat.S_ISREG(os.fstat(held).st_mode):
            return ""
        return os.read(held, _HOLDER_MAX_BYTES).decode("utf-8", errors="replace")
    finally:
        os.close(held)


def _describe_holder(text: str) -> str:
    try:
        info = json.loads(text)
        return f"pid {info['pid']}: {info['command']}"
    except (ValueError, KeyError, TypeError):
        return "holder unknown"
