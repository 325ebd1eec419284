"""The one check logpipe makes before it opens a file it reads: the path leads to a regular file.

Why: opening a FIFO blocks until a writer comes (forever), ``/dev/zero`` never ends, a socket cannot be opened.
Every reader of a file a user names (maps, mapping files, checkpoint ``meta.json``, manifests) goes through
``open_regular`` or ``irregular_kind`` first. Opening with ``O_NONBLOCK`` and checking the open descriptor
leaves no gap between the check and the read (a path swapped for a FIFO after a ``stat`` would still block).

Also here: JSON/TOML/YAML parsed under ``parse_nested``, so ``'[' * 100000`` is one error naming the file, not
a ``RecursionError`` traceback from the parser.
"""

from __future__ import annotations

import errno
import fcntl
import json
import os
import stat
from collections.abc import Callable
from pathlib import Path
from typing import IO, Any, TypeVar

T = TypeVar("T")


def describe_mode(mode: int) -> str:
    """What a non-regular file is, in words."""
    return ("a folder" if stat.S_ISDIR(mode) else "a FIFO (named pipe)" if stat.S_ISFIFO(mode)
            else "a device" if stat.S_ISCHR(mode) or stat.S_ISBLK(mode)
            else "a socket" if stat.S_ISSOCK(mode) else "not a regular file")


class IrregularFileError(OSError):
    """A path logpipe was to read is not a regular file. An ``OSError`` so that every reader's existing
    ``except OSError`` turns it into its own one-line error."""

    def __init__(self, path: str | Path, kind: str) -> None:
        super().__init__(errno.EINVAL, f"not a regular file: {kind}; only regular files are read", str(path))
        self.kind = kind

    def __str__(self) -> str:  # readers put the path before it themselves
        return str(self.strerror)


def irregular_kind(path: str | Path) -> str | None:
    """None when ``path`` (links followed) is a regular file, else what it is ("a FIFO (named pipe)", ...).

    Raises:
        OSError: it cannot be stat'ed (missing, dangling link, permissions).
    """
    mode = os.stat(path).st_mode
    return None if stat.S_ISREG(mode) else describe_mode(mode)


def open_regular(path: str | Path, mode: str = "rb", encoding: str | None = None,
                 errors: str | None = None) -> IO[Any]:
    """``open(path, mode)`` for reading, refusing anything but a regular file without blocking on a FIFO.

    Raises:
        IrregularFileError: a FIFO, device, socket or folder.
        OSError: missing or unreadable.
    """
    fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | os.O_CLOEXEC)
    try:
        st_mode = os.fstat(fd).st_mode
        if not stat.S_ISREG(st_mode):
            raise IrregularFileError(path, describe_mode(st_mode))
        fcntl.fcntl(fd, fcntl.F_SETFL, fcntl.fcntl(fd, fcntl.F_GETFL) & ~os.O_NONBLOCK)
        return open(fd, mode, encoding=encoding, errors=errors, closefd=True)
    except BaseException:
        os.close(fd)
        raise


def read_regular_bytes(path: str | Path) -> bytes:
    """The bytes of a regular file (``IrregularFileError`` for anything else)."""
    with open_regular(path) as fh:
        data: bytes = fh.read()
    return data


def read_regular_text(path: str | Path) -> str:
    """The UTF-8 text of a regular file (``IrregularFileError`` for anything else, ``ValueError`` if not UTF-8)."""
    return read_regular_bytes(path).decode("utf-8")


class NestingError(ValueError):
    """A document nested deeper than its parser can follow (``'[' * 100000``)."""


MAX_BRACKET_DEPTH = 1000
"""Deepest ``[``/``{`` nesting ``parse_nested`` hands to a parser (no real manifest, meta.json or mapping nests
more than ~10): the pure-Python YAML parser spends minutes on ``'[' * 100000`` before it recurses too deep."""


def _bracket_depth(text: str) -> int:
    """Deepest nesting of brackets in ``text`` (brackets inside strings counted too: an upper bound)."""
    import numpy as np

    codes = np.frombuffer(text.encode("utf-8", "replace"), dtype=np.uint8)
    step = np.isin(codes, (ord("["), ord("{"))).astype(np.int32) - np.isin(codes, (ord("]"), ord("}")))
    return int(np.cumsum(step).max()) if len(step) else 0


def parse_nested(parse: Callable[[str], T], text: str) -> T:
    """``parse(text)`` with too deep a nesting (over ``MAX_BRACKET_DEPTH`` brackets, or a parser's
    ``RecursionError``) as a ``NestingError`` (a ``ValueError``: readers already report those, after the file's
    name, as a damaged document)."""
    try:
        if _bracket_depth(text) > MAX_BRACKET_DEPTH:
            raise RecursionError
        return parse(text)
    except RecursionError:
        raise NestingError("nested too deeply to parse (lists or tables inside each other thousands of levels "
                           "deep: damaged or hostile)") from None


def read_json_file(path: str | Path) -> Any:
    """Parsed JSON of a regular file.

    Raises:
        OSError: missing, unreadable, or not a regular file (``IrregularFileError``).
        ValueError: not UTF-8, not JSON, or nested too deeply (``NestingError``).
    """
    return parse_nested(json.loads, read_regular_text(path))
