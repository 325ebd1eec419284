"""What logpipe wrote into an artifact folder: the proof a cleanup needs before it deletes anything.

A manifest names the files of a committed state; a file it does not name is a leftover only if logpipe wrote
it. A manifest cannot prove that (anyone can write ``{"artifact": "raster_run", "files": {}}`` beside their
own files), so every file ``atomic_path`` puts in place inside a locked artifact folder is recorded here, in
``FOLDER/.logpipe-written``, by its identity: inode, size and modification time in ns. A cleanup removes an
unnamed file only when a recorded identity is that very file, unchanged since logpipe renamed it into place
(renames keep the identity, so a file moved from staging stays proven; a file edited, replaced or copied in is
not). Temp files and staging folders are recognised by logpipe's own names for them (``TEMP_NAME``,
``STAGING_NAME``): they hold no committed content and are never shown to readers.

Appends are single ``O_APPEND`` writes of one short line, so worker processes writing files at once never
interleave; the journal is rewritten (to the entries whose files are still there) only under the folder's
lock, before any worker starts.
"""

from __future__ import annotations

import json
import os
import re
from collections.abc import Iterable
from pathlib import Path

from logpipe.storage.folder_lock import LOCK_FILE

JOURNAL = ".logpipe-written"
TEMP_NAME = re.compile(r"\..+\.[a-z0-9_]{8}\.tmp")
"""``tempfile.mkstemp(prefix=".NAME.", suffix=".tmp")`` as ``atomic_path`` names its temp files."""
STAGING_NAME = re.compile(r"\.staging-[0-9a-f]{12}")
"""``ArtifactWriter.staging`` folders."""
_MAX_ANCESTORS = 8
"""How far above a written file its artifact folder may be (``DATASET/rasters/RUN/shards/x.npy`` is 3)."""

Identity = tuple[int, int, int]


def identity(path: Path) -> Identity | None:
    """(inode, size, mtime ns) of a regular file (links not followed), None for anything else or nothing."""
    try:
        st = os.lstat(path)
    except OSError:
        return None
    return (st.st_ino, st.st_size, st.st_mtime_ns) if os.path.isfile(path) and not os.path.islink(path) else None


def _artifact_root(path: Path) -> Path | None:
    """The nearest folder above ``path`` whose writer holds its lock (its ``LOCK_FILE`` is there)."""
    folder = path.parent
    for _ in range(_MAX_ANCESTORS):
        if os.path.isfile(folder / LOCK_FILE):
            return folder
        if folder.parent == folder:
            return None
        folder = folder.parent
    return None


def record_written(path: Path) -> None:
    """Record ``path`` (just renamed into place) in the journal of the artifact folder being written around it;
    nothing when no logpipe writer holds a folder above it."""
    if path.name == JOURNAL:
        return
    root = _artifact_root(path)
    found = identity(path)
    if root is None or found is None:
        return
    line = json.dumps([path.relative_to(root).as_posix(), *found]) + "\n"
    fd = os.open(root / JOURNAL, os.O_WRONLY | os.O_APPEND | os.O_CREAT | os.O_NOFOLLOW | os.O_CLOEXEC, 0o644)
    try:
        os.write(fd, line.encode())
    finally:
        os.close(fd)


def written_identities(root: Path) -> set[Identity]:
    """Every identity the journal of ``root`` records (none when it is missing, a link or unreadable; a
    damaged line is skipped: it proves nothing)."""
    from logpipe.storage.regular_files import open_regular

    path = root / JOURNAL
    if os.path.islink(path):
        return set()
    try:
        with open_regular(path, "r", encoding="utf-8", errors="replace") as fh:
            lines = fh.read().splitlines()
    except OSError:
        return set()
    found: set[Identity] = set()
    for line in lines:
        try:
            entry = json.loads(line)
        except ValueError:
            continue
        if isinstance(entry, list) and len(entry) == 4 and all(type(v) is int for v in entry[1:]):
            found.add((entry[1], entry[2], entry[3]))
    return found


def proven_written(path: Path, written: set[Identity]) -> bool:
    """Whether ``path`` is, unchanged, a file logpipe recorded writing (``written``: ``written_identities``)."""
    found = identity(path)
    return found is not None and found in written


def logpipe_scratch(name: str) -> bool:
    """Whether ``name`` is one of logpipe's temp-file or staging-folder names."""
    return TEMP_NAME.fullmatch(name) is not None or STAGING_NAME.fullmatch(name) is not None


def prune_journal(root: Path, present: Iterable[Path]) -> None:
    """Rewrite the journal to the entries of files still ``present`` (called under the folder's lock, with no
    worker writing): it grows only with the files a folder holds."""
    path = root / JOURNAL
    written = written_identities(root)
    if not written:
        return
    keep = [(p, found) for p in present if (found := identity(p)) is not None and found in written]
    if not keep:  # a failed run into a folder that held nothing of logpipe's leaves no trace
        path.unlink(missing_ok=True)
        return
    tmp = root / f"{JOURNAL}.new"
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC | os.O_NOFOLLOW | os.O_CLOEXEC, 0o644)
    with os.fdopen(fd, "w", encoding="utf-8") as fh:
        fh.writelines(json.dumps([p.relative_to(root).as_posix(), *found]) + "\n" for p, found in keep)
    os.replace(tmp, path)
