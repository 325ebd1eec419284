"""The one interface every input format implements, and the registry that finds the right adapter.

An adapter turns input files into rows of the canonical track table (``schemas/tracks.json``) plus one
``LogMeta`` per log. It never writes anything: the ingest stage owns sharding, manifests and atomic writes.
Adding a format is one new module in ``logpipe/formats/`` registered in ``logpipe/formats/__init__.py``.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import ClassVar, Protocol

import pyarrow as pa

from logpipe.errors import SourceError
from logpipe.samples import TrackCodes
from logpipe.types import LogMeta, SampleProtocol, SourceFile


def read_head(path: Path, size: int) -> bytes | None:
    """The first ``size`` bytes of ``path`` (fewer if it is shorter), or None when it cannot be read: what
    ``sniff`` compares with a format's magic bytes."""
    try:
        with path.open("rb") as f:
            return f.read(size)
    except OSError:
        return None


def files_with_suffix(root: Path, suffixes: tuple[str, ...]) -> list[Path]:
    """Files under ``root`` (or ``root`` itself) whose lower-cased name ends in one of ``suffixes``, in path order.

    ``os.walk`` and string sorting: ``Path.rglob`` + ``Path`` comparisons cost ~0.1 ms a file, which is
    as much as parsing an Argoverse CSV.
    """
    if root.is_file():
        return [root]
    found = [
        os.path.join(folder, name)
        for folder, _, names in os.walk(root)
        for name in names
        if name.lower().endswith(suffixes)
    ]
    return [Path(p) for p in sorted(found)]


@dataclass
class ParsedLogs:
    """What an adapter returns for a batch of inputs.

    Attributes:
        tracks: rows in the canonical track-table schema (``logpipe.schemas.tracks_schema()``), any order.
        logs: one ``LogMeta`` per log present in ``tracks``.
        failures: inputs that could not be read, one ``SourceError`` each (only when the caller asked the
            adapter to keep going; otherwise the first error is raised).
        codes: integer codes of ``tracks``' log and track ids, when the adapter has them for free (parsed
            as dictionaries) and ``tracks`` is already in canonical order with ``step``; saves re-hashing.
    """

    tracks: pa.Table
    logs: list[LogMeta]
    failures: list[SourceError]
    codes: TrackCodes | None = None


ReadOne = Callable[[SourceFile], tuple[pa.Table, LogMeta, list[SourceError]]]
"""Reads one input: (rows, its LogMeta, problems kept when going on)."""


def read_each(sources: Sequence[SourceFile], read_one: ReadOne, *, keep_going: bool, empty: pa.Table) -> ParsedLogs:
    """``FormatAdapter.read`` for formats read one input at a time (bags, MCAP): a failing input raises, or with
    ``keep_going`` becomes a failure while the others are kept."""
    tables: list[pa.Table] = []
    logs: list[LogMeta] = []
    failures: list[SourceError] = []
    for source in sources:
        try:
            table, meta, problems = read_one(source)
        except SourceError as err:
            if not keep_going:
                raise
            failures.append(err)
            continue
        failures += problems
        tables.append(table)
        logs.append(meta)
    return ParsedLogs(tracks=pa.concat_tables(tables) if tables else empty, logs=logs, failures=failures)


class FormatAdapter(Protocol):
    """An input format.

    Attributes:
        name: short id used on the CLI (``--format``) and in ``logs.source_format``.
        default_protocol: the ``SampleProtocol`` preset this format's benchmark uses.
        batch_files: how many inputs to hand to ``read`` at once (large for many small files).
        hashes_while_reading: ``read`` fills in every ``PENDING_SHA256`` digest of the sources it logs, from
            its own read of each file (else the caller hashes them first, reading the files twice).
    """

    name: ClassVar[str]
    default_protocol: ClassVar[SampleProtocol]
    batch_files: ClassVar[int]
    hashes_while_reading: ClassVar[bool]

    def discover(self, root: Path) -> list[Path]:
        """Input paths under ``root`` (a file or folder) that this adapter reads, sorted; [] if none."""
        ...

    def sniff(self, path: Path) -> bool:
        """Cheap check whether ``path`` looks like this format (extension, header bytes)."""
        ...

    def read(self, sources: Sequence[SourceFile], *, keep_going: bool) -> ParsedLogs:
        """Parse ``sources`` into canonical rows.

        Raises:
            SourceError: the first bad input, naming file, line/record and field, when ``keep_going`` is False.
        """
        ...
