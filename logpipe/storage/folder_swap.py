"""Replacing a whole folder in one step, for folders whose files are only valid together (a checkpoint: weights
and the metadata naming their sha256); ``logpipe.storage.artifact`` commits folders whose files are valid one by one."""

from __future__ import annotations

import ctypes
import errno
import os
import shutil
import sys
from pathlib import Path

from logpipe.storage.artifact import STAGING_PREFIX
from logpipe.storage.durability import crash_point, fsync_dir, syncfs

_RENAME_EXCHANGE = 2


def _exchange(a: Path, b: Path) -> bool:
    """Swap two paths in one step (``renameat2(RENAME_EXCHANGE)``); False where the kernel or file system
    cannot."""
    if sys.platform != "linux":
        return False
    libc = ctypes.CDLL(None, use_errno=True)
    renameat2 = getattr(libc, "renameat2", None)
    if renameat2 is None:
        return False
    at_fdcwd = -100
    if renameat2(at_fdcwd, os.fsencode(a), at_fdcwd, os.fsencode(b), _RENAME_EXCHANGE) == 0:
        return True
    err = ctypes.get_errno()
    if err in (errno.EINVAL, errno.ENOSYS, errno.ENOTSUP):
        return False
    raise OSError(err, os.strerror(err), str(b))


def staging_folder_for(target: Path) -> Path:
    """A fresh, empty folder beside ``target`` to build its replacement in (``replace_folder``)."""
    import uuid

    for stale in target.parent.glob(f"{STAGING_PREFIX}{target.name}-*"):  # a killed writer's
        shutil.rmtree(stale, ignore_errors=True)
    folder = target.parent / f"{STAGING_PREFIX}{target.name}-{uuid.uuid4().hex[:8]}"
    folder.mkdir(parents=True)
    return folder


def replace_folder(staging: Path, target: Path) -> None:
    """Make ``staging`` (a complete folder beside ``target``) the folder at ``target`` in one step, for
    folders whose files are only valid together (a checkpoint: weights and the metadata naming their sha256).

    The files are flushed first; the swap is one ``renameat2`` exchange, so a crash leaves either folder
    whole at ``target``. Where the file system cannot exchange, the old folder is renamed aside first and
    ``recover_folder`` puts it back if a crash came between the two renames.
    """
    syncfs(staging)
    crash_point(f"before swap {target.name}")
    if not target.exists():
        staging.rename(target)
    elif _exchange(staging, target):
        crash_point(f"after swap {target.name}")
        shutil.rmtree(staging)
    else:
        aside = target.parent / f".{target.name}.old"
        shutil.rmtree(aside, ignore_errors=True)
        target.rename(aside)
        staging.rename(target)
        shutil.rmtree(aside)
    fsync_dir(target.parent)


def recover_folder(target: Path) -> None:
    """Undo a ``replace_folder`` cut between its two renames (only on file systems without exchange)."""
    aside = target.parent / f".{target.name}.old"
    if not target.exists() and aside.is_dir():
        aside.rename(target)
