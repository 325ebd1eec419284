"""What logpipe wrote into an artifact folder: the proof a cleanup needs before it deletes anything.

A manifest names the files of a committed state; a file it does not name is a leftover only if logpipe wrote
it. A manifest cannot prove that (anyone can write ``{"artifact": "raster_run", "files": {}}`` beside their
own files), so every file ``atomic_path`` puts in place inside a locked artifact folder is recorded here, in
``FOLDER/.logpipe-written``, by its identity: inode, size and modification time in ns. A cleanup removes an
unnamed file only when a recorded identity is that very file, unchanged since logpipe renamed it into place
(renames keep the identity, so a file moved from staging stays proven; a file edited, replaced or copied in is
not). Each commit also records the files it names by content (path, bytes, sha256, as computed when written), and
the journal is pruned to those at the end of every write: a folder written twice alike has the same journal.
Temp files and staging folders are recognised by logpipe's own names for them (``TEMP_NAME``, ``STAGING_NAME``):
they hold no committed content and are never shown to readers.

Appends are single ``O_APPEND`` writes, so worker processes writing files at once never interleave; the journal
is rewritten (to the entries whose files are still there) only under the folder's lock, with no worker running.
"""

from __future__ import annotations

import json
import os
import re
from collections.abc import Iterable
from contextlib import suppress
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from logpipe.storage.folder_lock import LOCK_FILE

JOURNAL = ".logpipe-written"
TEMP_NAME = re.compile(r"\..+\.[a-z0-9_]{8}\.tmp")
"""``tempfile.mkstemp(prefix=".NAME.", suffix=".tmp")`` as ``atomic_path`` names its temp files."""
STAGING_NAME = re.compile(r"\.staging-[0-9a-f]{12}")
"""``ArtifactWriter.staging`` folders."""
_MAX_ANCESTORS = 8
"""How far above a written file its artifact folder may be (``DATASET/rasters/RUN/shards/x.npy`` is 3)."""

Identity = tuple[int, int, int]
_RESERVED = frozenset({JOURNAL, "manifest.json", LOCK_FILE})
"""Names a cleanup never removes anyway: not recorded (the manifest is rewritten at every commit)."""


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


def start_journal(root: Path) -> None:
    """Make ``root``'s journal if it has none (``ArtifactWriter`` on entering): only folders with one record
    writes, so a folder merely locked (a checkpoint being amended) never gets one."""
    os.close(os.open(root / JOURNAL, os.O_WRONLY | os.O_CREAT | os.O_NOFOLLOW | os.O_CLOEXEC, 0o644))


def _append(root: Path, lines: Iterable[str]) -> None:
    text = "".join(lines)
    if not text:
        return
    try:
        fd = os.open(root / JOURNAL, os.O_WRONLY | os.O_APPEND | os.O_NOFOLLOW | os.O_CLOEXEC)
    except FileNotFoundError:  # not an artifact folder's writer (``start_journal``)
        return
    try:
        os.write(fd, text.encode())
    finally:
        os.close(fd)


def record_written(path: Path) -> None:
    """Record ``path`` (just renamed into place) by its identity in the journal of the artifact folder being
    written around it; nothing when no logpipe writer holds a folder above it."""
    if path.name in _RESERVED:
        return
    root = _artifact_root(path)
    found = identity(path)
    if root is not None and found is not None:
        _append(root, [json.dumps([path.relative_to(root).as_posix(), *found]) + "\n"])


def record_written_files(paths: Iterable[Path]) -> None:
    """``record_written`` of many files at once: each folder's artifact root looked up once, one append per root
    (ingest writes a thousand small MCAPs per batch into one staging folder)."""
    roots: dict[Path, Path | None] = {}
    lines: dict[Path, list[str]] = {}
    for path in paths:
        if path.name in _RESERVED:
            continue
        if path.parent not in roots:
            roots[path.parent] = _artifact_root(path)
        root, found = roots[path.parent], identity(path)
        if root is not None and found is not None:
            lines.setdefault(root, []).append(json.dumps([path.relative_to(root).as_posix(), *found]) + "\n")
    for root, entries in lines.items():
        _append(root, entries)


def record_committed(root: Path, files: dict[str, Any]) -> None:
    """Record files a commit of ``root`` just named, by content (``{rel: {"bytes", "sha256"}}``, as logpipe itself
    computed them when writing): these entries are the same on every run that writes the same files."""
    _append(root, [json.dumps([rel, entry["bytes"], entry["sha256"]]) + "\n" for rel, entry in sorted(files.items())])


@dataclass
class Journal:
    """What a folder's journal records: identities of files put in place, and (rel, bytes, sha256) of files
    committed."""

    identities: set[Identity] = field(default_factory=set)
    contents: dict[str, tuple[int, str]] = field(default_factory=dict)

    def proves(self, root: Path, path: Path) -> bool:
        """Whether ``path`` is, unchanged, a file logpipe wrote: the very file it put in place, or a file at a
        committed path with the committed size and sha256."""
        found = identity(path)
        if found is None:
            return False
        if found in self.identities:
            return True
        committed = self.contents.get(path.relative_to(root).as_posix())
        if committed is None or committed[0] != found[1]:
            return False
        from logpipe.storage.io import sha256_file

        return sha256_file(path) == committed[1]


def read_journal(root: Path) -> Journal:
    """The journal of ``root`` (empty when missing, a link or unreadable; a damaged line proves nothing)."""
    from logpipe.storage.regular_files import open_regular

    journal = Journal()
    path = root / JOURNAL
    if os.path.islink(path):
        return journal
    try:
        with open_regular(path, "r", encoding="utf-8", errors="replace") as fh:
            lines = fh.read().splitlines()
    except OSError:
        return journal
    for line in lines:
        try:
            entry = json.loads(line)
        except ValueError:
            continue
        if not isinstance(entry, list) or not entry or not isinstance(entry[0], str):
            continue
        if len(entry) == 4 and all(type(v) is int for v in entry[1:]):
            journal.identities.add((entry[1], entry[2], entry[3]))
        elif len(entry) == 3 and type(entry[1]) is int and isinstance(entry[2], str):
            journal.contents[entry[0]] = (entry[1], entry[2])
    return journal


def logpipe_scratch(name: str) -> bool:
    """Whether ``name`` is one of logpipe's temp-file or staging-folder names."""
    return TEMP_NAME.fullmatch(name) is not None or STAGING_NAME.fullmatch(name) is not None


def prune_journal(root: Path, present: Iterable[Path], *, keep_empty: bool = False) -> None:
    """Rewrite the journal to what still proves something (called under the folder's lock, with no worker
    writing): committed entries of files still there with their size, then identities of files still there that
    no committed entry covers, each in path order. After a clean run only committed entries remain, so two runs
    that write the same files leave the same journal. ``keep_empty``: a writer going on keeps an empty journal
    (the file's presence is what makes writes be recorded); one leaving removes it."""
    path = root / JOURNAL
    journal = read_journal(root)
    if not journal.identities and not journal.contents:
        if not keep_empty:
            path.unlink(missing_ok=True)
        return
    lines: list[str] = []
    loose: list[str] = []
    for file in sorted(present):
        found = identity(file)
        if found is None:
            continue
        rel = file.relative_to(root).as_posix()
        committed = journal.contents.get(rel)
        if committed is not None and committed[0] == found[1]:
            lines.append(json.dumps([rel, *committed]) + "\n")
        elif found in journal.identities:
            loose.append(json.dumps([rel, *found]) + "\n")
    if not lines and not loose:  # a failed run into a folder that held nothing of logpipe's leaves no trace
        if keep_empty:
            path.write_bytes(b"")
        else:
            path.unlink(missing_ok=True)
        return
    text = "".join(lines + loose)
    with suppress(OSError):
        if path.read_text(encoding="utf-8") == text:  # a run that changed nothing leaves the journal untouched
            return
    tmp = root / f"{JOURNAL}.new"
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC | os.O_NOFOLLOW | os.O_CLOEXEC, 0o644)
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as fh:
            fh.write(text)
        os.replace(tmp, path)
    except BaseException:  # a failed rewrite leaves the old journal and no temp beside it
        tmp.unlink(missing_ok=True)
        raise
