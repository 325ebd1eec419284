"""Committed artifact folders: one writer at a time, one atomic commit point, verification against it.

Every folder logpipe writes (a dataset, a raster run, a prediction run, a score report) follows one protocol:

1. ``ArtifactWriter`` takes an exclusive ``fcntl.flock`` on the folder for the whole write
   (``logpipe.storage.folder_lock``); a second writer fails at once with one line naming the holder's pid and command
   (``FOLDER/.logpipe.lock`` while held).
2. It removes what the committed manifest does not name, among the paths the artifact owns (``owned``):
   leftovers of a crashed writer. Files of other artifacts nested inside (a dataset's ``rasters/``) and
   anything the user put there are never touched.
3. New files are written whole (temp name + rename, ``logpipe.storage.io.atomic_path``) under names the committed
   manifest does not use, so the state a reader sees never changes under it.
4. ``commit`` flushes every new file to disk (one ``syncfs``, ``logpipe.storage.durability``), then replaces
   ``manifest.json`` by rename and syncs the folder: the single commit point. A crash before the rename
   leaves the old state, after it the new one; the next writer cleans the rest.
5. Files the new manifest no longer names are removed.

The manifest's ``files`` section lists every committed file (relative path → bytes, sha256, and rows for
Parquet tables): readers trust only these, ``verify`` recomputes them.

``logpipe.storage.durability.crash_point`` marks each step of the protocol (the crash-injection tests stop the process
there). Folders whose files are only valid together (checkpoints) are replaced whole by ``logpipe.storage.folder_swap``.
"""

from __future__ import annotations

import errno
import json
import os
import re
import shutil
from collections.abc import Iterable, Iterator, Sequence
from contextlib import contextmanager, suppress
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType
from typing import Any, Self, TypedDict

from logpipe.errors import DatasetError, LogpipeError, OutputError
from logpipe.storage import write_journal as jf
from logpipe.storage.durability import crash_point, fsync_dir, syncfs
from logpipe.storage.folder_lock import LOCK_FILE, FolderLock
from logpipe.storage.regular_files import parse_nested, read_regular_bytes
from logpipe.storage.safe_paths import check_manifest_files, refuse_linked_folders

MANIFEST = "manifest.json"
STAGING_PREFIX = ".staging-"
_RESERVED = (MANIFEST, LOCK_FILE, jf.JOURNAL)


class FileEntry(TypedDict, total=False):
    """A committed file in a manifest's ``files`` section."""

    bytes: int
    sha256: str
    rows: int


MAX_NAME_CHARS = 200
"""Longest id taken from data that may become a file name (``mcap/<log_id>.mcap``); most file systems refuse
names over 255 bytes."""


def unsafe_file_name(name: str) -> str | None:
    """Why ``name`` (an id taken from data) cannot be one file name inside an output folder, or None when it can:
    empty, ``.``/``..``, a ``/`` or ``\\``, NUL or control characters, or longer than ``MAX_NAME_CHARS``."""
    if not name or name in (".", "..") or "/" in name or "\\" in name:
        return "is not a single file name (empty, '.', '..' or has '/')"
    if any(ord(c) < 32 or ord(c) == 127 for c in name):
        return "holds NUL or control characters"
    if len(name) > MAX_NAME_CHARS:
        return f"is {len(name)} characters long (at most {MAX_NAME_CHARS})"
    return None


# ---- manifests -----------------------------------------------------------------------------------------


def read_manifest(root: Path, *, required: bool = True) -> dict[str, Any] | None:
    """The committed manifest of ``root`` (None when there is none and ``required`` is False).

    Raises:
        DatasetError: missing (when required) or not a JSON object.
    """
    path = root / MANIFEST
    try:
        text = read_regular_bytes(path)
    except FileNotFoundError:
        if required:
            raise DatasetError(f"{root}: no {MANIFEST} (not a logpipe output folder, or never committed)") from None
        return None
    except OSError as exc:
        raise DatasetError(f"{path}: cannot read: {exc.strerror}") from None
    try:
        manifest = parse_nested(json.loads, text.decode("utf-8"))
    except (ValueError, UnicodeDecodeError) as exc:
        raise DatasetError(f"{path}: damaged manifest ({exc}); `logpipe verify` lists what is wrong") from None
    if not isinstance(manifest, dict):
        raise DatasetError(f"{path}: damaged manifest (not a JSON object)")
    if "checksum" in manifest and manifest["checksum"] != manifest_checksum(manifest):
        raise DatasetError(f"{path}: damaged manifest (content differs from its checksum); "
                           "`logpipe verify` lists what is wrong")
    if isinstance(manifest.get("files"), dict):  # every reader, writer and verify joins these paths to root
        check_manifest_files(path, manifest["files"])
    return manifest


def foreign_manifest(manifest: dict[str, Any] | None, legacy_keys: Sequence[str] = ()) -> bool:
    """Whether ``manifest`` (of a folder a writer or ``verify --repair`` would clean) is none of logpipe's: no
    artifact kind, and not the manifest of an older logpipe (which has every one of ``legacy_keys``)."""
    if manifest is None or isinstance(manifest.get("artifact"), str):
        return False
    return not (legacy_keys and all(k in manifest for k in legacy_keys))


def file_entry(path: Path, *, rows: int | None = None) -> FileEntry:
    """The ``files`` entry of a file just written (size, sha256, and rows for tables)."""
    from logpipe.storage.io import sha256_file

    entry: FileEntry = {"bytes": path.stat().st_size, "sha256": sha256_file(path)}
    if rows is not None:
        entry["rows"] = rows
    return entry


def check_files(root: Path, files: dict[str, Any]) -> None:
    """Cheap invariants a reader checks on open: every committed file exists with its committed size.

    Raises:
        DatasetError: the first file that is missing or has another size.
    """
    for rel, entry in files.items():
        try:
            size = (root / rel).stat().st_size
        except OSError:
            raise DatasetError(f"{root / rel}: missing (named by {root / MANIFEST}); "
                               "`logpipe verify` lists every problem") from None
        if size != entry["bytes"]:
            raise DatasetError(f"{root / rel}: {size} bytes, the manifest says {entry['bytes']} (truncated or "
                               "changed); `logpipe verify` lists every problem")


# ---- the writer ----------------------------------------------------------------------------------------


class Ownership:
    """Which paths of a folder are the artifact's own files: patterns over paths relative to the folder (POSIX).

    Patterns match the whole path with ``*`` / ``?`` not crossing ``/``; one ending in ``/`` owns everything
    under the folders it matches. Written into the manifest (``owns``), so ``verify`` and a
    later writer know, without code of the artifact's kind, which unnamed files are leftovers.
    """

    def __init__(self, patterns: Sequence[str]) -> None:
        self.patterns = tuple(patterns)

        def glob(p: str) -> str:
            return "".join("[^/]*" if c == "*" else "[^/]" if c == "?" else re.escape(c) for c in p)

        self._regex = re.compile("|".join(glob(p) + (".*" if p.endswith("/") else "") for p in self.patterns)
                                 or "(?!)")

    def __call__(self, rel: str) -> bool:
        return self._regex.fullmatch(rel) is not None

    @classmethod
    def of(cls, manifest: dict[str, Any] | None, default: Ownership) -> Ownership:
        """The ownership a committed manifest records (``default`` for manifests from before it did)."""
        owns = (manifest or {}).get("owns")
        return cls(owns) if isinstance(owns, list) and all(isinstance(p, str) for p in owns) else default


EVERYTHING = Ownership(["*", "*/"])
"""An artifact that owns its whole folder (nested artifacts aside)."""

OUTPUT_ERRNOS = frozenset({errno.ENOSPC, errno.EROFS, errno.EACCES, errno.EDQUOT, errno.EPERM})
"""OS errors on an output that are the user's to fix (disk full, read-only, permissions), not logpipe bugs."""


@contextmanager
def output_errors() -> Iterator[None]:
    """Turn ``OUTPUT_ERRNOS`` raised inside into one-line ``OutputError``s (the writer leaves the committed
    state as it was)."""
    try:
        yield
    except OSError as exc:
        if exc.errno in OUTPUT_ERRNOS:
            raise OutputError(os_error_message(exc)) from None
        raise


INDENTED_MANIFEST_MAX_BYTES = 16 * 1024
"""Manifests up to this size (compact) are written indented; larger ones on one line. json's indented encoder is
pure Python (~3 MB/s here): it took 0.55 s of a 5.3 s two-worker ingest of 10,000 AV1 logs (1.8 MB, every input
listed), serially after the workers, where the one-line C encoder takes a few ms; counting files instead missed that
manifest (42 files). At 16 KB a commit spends at most ~5 ms on it, also when predict commits once per shard."""


def manifest_checksum(manifest: dict[str, Any]) -> str:
    """sha256 of a manifest's content without its ``checksum`` key: a flipped byte in the manifest itself is
    found like one in any file it names."""
    import hashlib

    body = {k: v for k, v in manifest.items() if k != "checksum"}
    return hashlib.sha256(json.dumps(body, sort_keys=True, separators=(",", ":")).encode()).hexdigest()


class ArtifactWriter:
    """Writes one artifact folder under the protocol of this module.

    Use as a context manager: entering takes the lock and cleans leftovers; ``commit`` is the one commit point;
    leaving releases the lock (a writer that leaves without committing changes nothing a reader sees).

    Attributes:
        root: the folder (created when missing).
        manifest: the committed manifest when entering (None for a new folder).
    """

    def __init__(self, root: Path, owned: Ownership, kind: str, legacy_keys: Sequence[str] = ()) -> None:
        self.root = Path(root)
        self.owned = owned
        self.kind = kind
        self.legacy_keys = tuple(legacy_keys)
        self.manifest: dict[str, Any] | None = None
        self._lock = FolderLock(self.root)
        self._created = False
        self._recorded: dict[str, Any] = {}

    def __enter__(self) -> ArtifactWriter:
        if self.root.is_symlink():  # before the first write: every file would land in the link's target
            raise OutputError(f"{self.root}: is a symbolic link; logpipe never writes through links: give the "
                              "folder it points to, or another folder")
        if self.root.exists() and not self.root.is_dir():
            raise DatasetError(f"{self.root}: exists and is not a folder")
        self.root.parent.mkdir(parents=True, exist_ok=True)
        try:  # one atomic step decides who created the folder (two runs may both find it missing)
            self.root.mkdir()
            self._created = True
        except FileExistsError:
            self._created = False
        self._lock.acquire()
        try:
            self.manifest = read_manifest(self.root, required=False)
            if foreign_manifest(self.manifest, self.legacy_keys):
                raise DatasetError(f"{self.root}: holds a {MANIFEST} that logpipe did not write (no artifact kind); "
                                   "choose another folder")
            found = (self.manifest or {}).get("artifact", self.kind)
            if found != self.kind:
                raise DatasetError(f"{self.root}: holds a {str(found).replace('_', ' ')}, not a "
                                   f"{self.kind.replace('_', ' ')}; choose another folder")
            refuse_linked_folders(self.root, self.owned)
            jf.start_journal(self.root)
            self.clean()
        except BaseException:
            self._lock.release(remove_folder=self._created)
            raise
        return self

    def __exit__(self, kind: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None) -> None:
        failed_first_run = self._created and self.manifest is None
        try:
            if failed_first_run:
                # Leave no trace, and only under the lock: released first, another writer could take the folder
                # and commit into it before it is gone. Only owned files this run wrote can be here.
                self.clean(everything_owned=True)
            else:  # still under the lock: the journal keeps only what the folder holds (best effort)
                with suppress(OSError):
                    jf.prune_journal(self.root, (path for _rel, path in _walk(self.root)))
        finally:
            self._lock.release(remove_folder=failed_first_run)

    def staging(self) -> Path:
        """A fresh staging folder inside the artifact (removed by ``clean`` if never committed)."""
        import uuid

        folder = self.root / f"{STAGING_PREFIX}{uuid.uuid4().hex[:12]}"
        folder.mkdir()
        return folder

    def committed_files(self) -> set[str]:
        return set((self.manifest or {}).get("files", {}))

    def clean(self, *, everything_owned: bool = False) -> list[str]:
        """Remove owned paths the committed manifest does not name (and any staging or temp file).

        In a folder without a manifest, owned paths are removed only when a killed writer left its lock file
        there, or (``everything_owned``) this writer created the folder: otherwise they may be the user's own
        files (``--out`` pointed at a folder with PNGs in it).
        """
        keep = self.committed_files()
        ours = self.manifest is not None or self._lock.found_stale or everything_owned
        journal = jf.read_journal(self.root)
        removed, present = [], []
        for rel, path in _walk(self.root):
            if rel in keep or rel in _RESERVED:
                present.append(path)
                continue
            # A file no commit names is removed only when logpipe can prove it wrote it (its journal), never on
            # a manifest's word: a spoofed manifest beside the user's files must not turn them into leftovers.
            proven = everything_owned or (self.owned(rel) and journal.proves(self.root, path))
            scratch = jf.logpipe_scratch(path.name)
            if (scratch and ("/" not in rel or self.owned(rel))) or (ours and self.owned(rel) and proven):
                crash_point(f"clean {rel}")
                if path.is_dir() and not path.is_symlink():
                    shutil.rmtree(path)
                else:
                    path.unlink()
                removed.append(rel)
            else:
                present.append(path)
        _remove_empty_owned_dirs(self.root, self.owned)
        jf.prune_journal(self.root, present, keep_empty=not everything_owned)
        return removed

    def stamped(self, manifest: dict[str, Any]) -> dict[str, Any]:
        """``manifest`` as ``commit`` writes it: with the artifact's kind, ownership and checksum."""
        manifest = {**manifest, "artifact": self.kind, "owns": list(self.owned.patterns)}
        manifest["checksum"] = manifest_checksum(manifest)
        return manifest

    def is_committed(self, manifest: dict[str, Any]) -> bool:
        """Whether committing ``manifest`` would change nothing."""
        return bool(self.manifest == json.loads(json.dumps(self.stamped(manifest))))

    def commit(self, manifest: dict[str, Any]) -> None:
        """Make ``manifest`` (whose ``files`` name every file of the new state) the folder's state."""
        from logpipe.storage.io import atomic_path

        files = manifest.get("files")
        if not isinstance(files, dict):
            raise LogpipeError("internal: a manifest must list its files")
        manifest = self.stamped(manifest)
        # Only what this commit adds: the committed files were checked by their own commit, and a run committing
        # once per shard would otherwise stat every earlier file again on each commit.
        committed = self.committed_files()
        missing = [rel for rel in files if rel not in committed and not (self.root / rel).is_file()]
        if missing:
            raise LogpipeError(f"internal: {self.root}: commit names files that are not there: {missing[:3]}")
        crash_point("before sync")
        syncfs(self.root)
        text = json.dumps(manifest, sort_keys=True, separators=(",", ":")) + "\n"
        if len(text) <= INDENTED_MANIFEST_MAX_BYTES:  # indented for people where that costs little
            text = json.dumps(manifest, indent=2, sort_keys=True) + "\n"
        with atomic_path(self.root / MANIFEST, durable=True) as tmp:
            tmp.write_text(text, encoding="utf-8")
        crash_point("after manifest")
        fsync_dir(self.root)
        jf.record_committed(self.root, {rel: e for rel, e in files.items() if self._recorded.get(rel) != e})
        self._recorded.update((rel, dict(e)) for rel, e in files.items())
        superseded = sorted(self.committed_files() - set(files))
        self.manifest = manifest
        # Only what the previous state named: workers may be writing the next commit's files right now, so
        # only the folders these files leave empty go, never a sweep (it would take a worker's new folder).
        journal = jf.read_journal(self.root)
        for rel in superseded:
            crash_point(f"remove {rel}")
            if journal.proves(self.root, self.root / rel):  # an edited or foreign manifest names no file to delete
                (self.root / rel).unlink()
        _remove_emptied_dirs(self.root, self.owned, superseded)


def _walk(root: Path) -> Iterable[tuple[str, Path]]:
    """(relative POSIX path, path) of every file and staging folder under ``root``, not into staging folders
    or other artifacts' folders (those that hold their own manifest)."""
    for folder, dirs, names in os.walk(root):
        here = Path(folder)
        rel_folder = here.relative_to(root).as_posix()
        prefix = "" if rel_folder == "." else rel_folder + "/"
        keep_dirs = []
        for d in sorted(dirs):
            if d.startswith(STAGING_PREFIX):
                yield prefix + d, here / d
            elif not ((here / d / MANIFEST).exists() or (here / d / LOCK_FILE).exists()):
                keep_dirs.append(d)  # another artifact's folder is its own writer's business
        dirs[:] = keep_dirs
        for name in sorted(names):
            yield prefix + name, here / name


def _remove_emptied_dirs(root: Path, owned: Ownership, removed: Iterable[str]) -> None:
    """Remove the owned folders (and their owned parents) that removing the files ``removed`` left empty."""
    for rel in removed:
        parts = rel.split("/")[:-1]
        while parts and owned("/".join(parts) + "/"):
            try:
                (root / "/".join(parts)).rmdir()
            except OSError:  # not empty (or gone): its other files, or a worker's new ones
                break
            parts.pop()


def _remove_empty_owned_dirs(root: Path, owned: Ownership) -> None:
    for folder, dirs, names in os.walk(root, topdown=False):  # children before their parents
        here = Path(folder)
        if here == root or dirs or names:
            continue
        rel = here.relative_to(root).as_posix()
        if owned(rel + "/"):
            here.rmdir()


# ---- verification --------------------------------------------------------------------------------------


@dataclass
class Problem:
    """One thing ``verify`` found wrong: the file and what."""

    path: str
    what: str

    def line(self) -> str:
        return f"{self.path}: {self.what}"


def verify_folder(root: Path, owned: Ownership | None = None, *,
                  deep: bool = True) -> tuple[list[Problem], list[str]]:
    """Check a committed folder against its manifest.

    Returns:
        (problems, leftovers): every committed file missing, of another size, sha256 or row count; and the
        uncommitted files (staging, temp, owned but unnamed) a crashed writer left.
    """
    from logpipe.storage.io import sha256_file

    root = Path(root)
    try:
        manifest = read_manifest(root)
    except DatasetError as exc:
        return [Problem(str(root / MANIFEST), str(exc).split(": ", 1)[-1])], []
    assert manifest is not None
    if "checksum" in manifest and manifest["checksum"] != manifest_checksum(manifest):
        return [Problem(str(root / MANIFEST), "content differs from its checksum (edited or damaged)")], []
    owned = owned or Ownership.of(manifest, EVERYTHING)
    files = manifest.get("files")
    if not isinstance(files, dict):
        return [Problem(str(root / MANIFEST), "lists no files (written by logpipe < 0.2; re-create the folder)")], []
    problems = []
    for rel, entry in sorted(files.items()):
        path = root / rel
        try:
            size = path.stat().st_size
        except OSError:
            problems.append(Problem(str(path), "missing"))
            continue
        if size != entry.get("bytes"):
            problems.append(Problem(str(path), f"{size} bytes, manifest says {entry.get('bytes')}"))
            continue
        if deep and sha256_file(path) != entry.get("sha256"):
            problems.append(Problem(str(path), "sha256 differs from the manifest (content changed)"))
            continue
        if deep and "rows" in entry:
            rows = _parquet_rows(path)
            if rows != entry["rows"]:
                problems.append(Problem(str(path), f"{rows} rows, manifest says {entry['rows']}"))
    leftovers = []
    journal = jf.read_journal(root)
    for rel, path in _walk(root):
        if rel in files or rel in _RESERVED:
            continue
        mine = owned(rel)
        if (jf.logpipe_scratch(path.name) and ("/" not in rel or mine)) or (mine and journal.proves(root, path)):
            leftovers.append(rel)
    return problems, leftovers


def _parquet_rows(path: Path) -> int | str:
    import pyarrow.parquet as pq

    try:
        return int(pq.ParquetFile(path).metadata.num_rows)
    except Exception as exc:
        return f"unreadable ({type(exc).__name__})"


def owned_by(prefixes: Sequence[str], names: Sequence[str] = ()) -> Ownership:
    """An ``Ownership`` of the folders ``prefixes`` (each ending in ``/``) and the files ``names``."""
    return Ownership([*prefixes, *names])


def os_error_message(exc: OSError) -> str:
    """One line for an OS error on an output (disk full, read-only, permissions): the file, the error in words
    and its errno name, and what the folder holds now (true whether or not earlier commits of the run landed)."""
    where = str(exc.filename) if exc.filename else "a file the operating system did not name"
    if exc.filename2:
        where += f" -> {exc.filename2}"
    hints = {errno.ENOSPC: "disk full", errno.EROFS: "read-only file system", errno.EACCES: "permission denied",
             errno.EDQUOT: "disk quota exceeded", errno.EPERM: "operation not permitted"}
    what = hints.get(exc.errno or 0, exc.strerror or type(exc).__name__)
    code = errno.errorcode.get(exc.errno or -1)
    return (f"{where}: {what}{f' ({code})' if code else ''}; the folder holds its previous state (its last "
            "commit), this run's uncommitted work was discarded")


# ---- the base of the typed writers ---------------------------------------------------------------------


class FolderWriter:
    """Base of each artifact's typed writer (``DatasetWriter``, ``RasterRunWriter``, ``PredictionRunWriter``):
    a context manager over an ``ArtifactWriter`` of the subclass's ``ownership`` and ``kind``.

    Attributes:
        root: the folder.
    """

    ownership: Ownership
    kind: str
    legacy_keys: tuple[str, ...] = ()
    """Keys every manifest of this kind written before manifests named their kind has (none: no such ones)."""

    def __init__(self, root: Path) -> None:
        self.root = Path(root)
        self._writer = ArtifactWriter(self.root, self.ownership, self.kind, self.legacy_keys)

    def __enter__(self) -> Self:
        self._writer.__enter__()
        return self

    def __exit__(self, kind: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None) -> None:
        self._writer.__exit__(kind, exc, tb)
