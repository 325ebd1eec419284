"""Paths in an output folder that logpipe may trust: committed file names that stay inside the folder, and
folders it writes into that are real folders, not links to somewhere else.

A folder logpipe writes may be shared or prepared by someone else: a manifest may name ``../../x``, an owned
subfolder (``mcap/``) may be a symlink to another user's home. Both would let a write or a cleanup reach
outside ``--out``; both are refused here with one line naming the path.
"""

from __future__ import annotations

import os
import stat
from collections.abc import Callable, Mapping
from pathlib import Path

from logpipe.errors import DatasetError, OutputError

MAX_MANIFEST_PATH_CHARS = 1024


def unsafe_relative_path(rel: object) -> str | None:
    """Why ``rel`` (a path a manifest names) is not a plain relative path inside its folder, or None."""
    if not isinstance(rel, str) or not rel:
        return "is not a non-empty string"
    if len(rel) > MAX_MANIFEST_PATH_CHARS:
        return f"is longer than {MAX_MANIFEST_PATH_CHARS} characters"
    if rel.startswith("/") or "\\" in rel:
        return "is not a relative POSIX path"
    if any(part in ("", ".", "..") for part in rel.split("/")):
        return "has an empty, '.' or '..' part (would leave its folder)"
    if any(ord(c) < 32 or ord(c) == 127 for c in rel):
        return "holds NUL or control characters"
    return None


def manifest_files_problem(files: Mapping[object, object]) -> str | None:
    """The first thing wrong with a manifest's ``files`` section (a path leaving the folder, an entry that is
    not ``{bytes, sha256}``), or None: a foreign or edited manifest must never steer a read or a removal."""
    for rel, entry in files.items():
        why = unsafe_relative_path(rel)
        if why is not None:
            return f"file {str(rel)[:80]!r} {why}"
        if not isinstance(entry, dict):
            return f"file {rel!r}: entry is not an object"
        size, digest, rows = entry.get("bytes"), entry.get("sha256"), entry.get("rows", 0)
        if type(size) is not int or size < 0 or not isinstance(digest, str) or type(rows) is not int:
            return f"file {rel!r}: entry needs integer 'bytes' (and 'rows') and a string 'sha256'"
    return None


def _linked(path: Path) -> int | None:
    """``path``'s mode when it is a symlink or special file (anything but a plain file or folder), else None."""
    try:
        mode = os.lstat(path).st_mode
    except FileNotFoundError:
        return None
    return None if stat.S_ISDIR(mode) or stat.S_ISREG(mode) else mode


def _describe(mode: int) -> str:
    return "a symbolic link" if stat.S_ISLNK(mode) else "a special file (FIFO, socket or device)"


def refuse_linked_folders(root: Path, owns_under: Callable[[str], bool]) -> None:
    """Refuse a folder whose owned subfolders (those ``owns_under(rel + "/")`` accepts) include a symlink or
    special file: writing into one would put files outside ``root``. Walks without following links.

    Raises:
        OutputError: naming the first such path.
    """
    for folder, dirs, _names in os.walk(root):
        here = Path(folder)
        rel_folder = here.relative_to(root).as_posix()
        prefix = "" if rel_folder == "." else rel_folder + "/"
        for name in dirs:  # links to folders are listed here; a link to a file is replaced, never followed
            mode = _linked(here / name)
            if mode is not None and owns_under(prefix + name + "/"):
                raise OutputError(f"{here / name}: is {_describe(mode)} where logpipe writes its own folder; "
                                  "logpipe never writes through links: remove it or choose another folder")
        dirs[:] = [d for d in dirs if owns_under(prefix + d + "/")]


def real_folder(root: Path, rel: str) -> Path:
    """``root / rel`` as a folder, created where missing, each part checked to be a real folder (not a link).

    Raises:
        OutputError: a part is a symlink, special file or plain file.
    """
    path = root
    for part in rel.split("/"):
        path = path / part
        try:
            os.mkdir(path)
        except FileExistsError:
            mode = os.lstat(path).st_mode
            if not stat.S_ISDIR(mode):
                what = _describe(mode) if not stat.S_ISREG(mode) else "a file"
                raise OutputError(f"{path}: is {what} where logpipe writes a folder; logpipe never writes "
                                  "through links: remove it or choose another folder") from None
    return path


def check_manifest_files(path: Path, files: Mapping[object, object]) -> None:
    """Raise ``DatasetError`` naming ``path`` when ``manifest_files_problem`` finds something."""
    problem = manifest_files_problem(files)
    if problem is not None:
        raise DatasetError(f"{path}: damaged or foreign manifest ({problem}); `logpipe verify` lists what is wrong")
