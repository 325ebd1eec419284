"""The one interface every input format implements, and the registry that finds the right adapter.

An adapter turns input files into rows of the canonical track table (``schemas/tracks.json``) plus one
``LogMeta`` per log. It never writes anything: the ingest stage owns sharding, manifests and atomic writes.
Adding a format is one new module in ``logpipe/formats/`` registered in ``logpipe/formats/__init__.py``.
"""

from __future__ import annotations

import hashlib
import math
import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING, ClassVar, Protocol

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc

from logpipe.dataset.samples import TrackCodes
from logpipe.errors import LogpipeError, SourceError
from logpipe.formats.motion_checks import impossible_motion
from logpipe.storage.artifact import unsafe_file_name
from logpipe.storage.regular_files import irregular_kind
from logpipe.types import LogMeta, SampleProtocol, SourceFile

if TYPE_CHECKING:  # annotations only: the text formats' pool workers need not import the map store
    from logpipe.maps.store import MapStore


def read_head(path: Path, size: int) -> bytes | None:
    """The first ``size`` bytes of ``path`` (fewer if it is shorter), or None when it cannot be read: what
    ``sniff`` compares with a format's magic bytes."""
    if not path.is_file():  # opening a FIFO would block, a device would never end
        return None
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


TIME_LIMIT_NS = 1 << 62
"""Largest |timestamp| accepted, in ns (~146 years): leaves int64 headroom for differences and grid steps, so a
value near the int64 limit (a damaged or absurd time) is refused before any conversion could wrap it."""


def require_regular(path: str | Path, relpath: str, *, folder_ok: bool = False) -> None:
    """Refuse anything but a regular file (or a folder when ``folder_ok``) before it is opened.

    Why: a FIFO blocks ``open`` forever, ``/dev/zero`` never ends, a dangling symlink fails deep in a reader.

    Raises:
        SourceError: missing / dangling link / FIFO / device / socket.
    """
    try:
        kind = irregular_kind(path)
    except FileNotFoundError:
        what = "a dangling symbolic link" if os.path.islink(path) else "missing (removed since it was listed?)"
        raise SourceError(relpath, f"not readable: {what}") from None
    except OSError as err:
        raise SourceError(relpath, f"not readable: {err.strerror or err}") from None
    if kind is None or (folder_ok and kind == "a folder"):
        return
    raise SourceError(relpath, f"not a regular file: {kind}; only regular files are read")


def require_regular_tree(folder: str | Path, relpath: str) -> None:
    """``require_regular`` on everything inside an input folder (a bag folder, an AV2 sensor log), each entry
    checked: readers open the files they find there, and one FIFO among them would block forever."""
    for here, dirs, names in os.walk(folder):
        for name in [*names, *(d for d in dirs if os.path.islink(os.path.join(here, d)))]:
            path = os.path.join(here, name)
            require_regular(path, f"{relpath}/{os.path.relpath(path, folder)}", folder_ok=True)


def check_log_id(log_id: object, relpath: str, field: str = "log_id") -> str:
    """``log_id`` when it is safe as one path component (ids become file names), else a ``SourceError``
    (the rule: ``logpipe.storage.artifact.unsafe_file_name``)."""
    if not isinstance(log_id, str):
        raise SourceError(relpath, f"log id {log_id!r} is not text; log ids become file names", field=field)
    reason = unsafe_file_name(log_id)
    if reason:
        raise SourceError(relpath, f"log id {log_id[:80]!r} {reason}; log ids become file names", field=field)
    return log_id


def as_source_error(err: BaseException, relpath: str) -> SourceError:
    """Any failure while parsing one input, as that input's ``SourceError`` (a ``LogpipeError`` about a setting
    keeps its words; anything else says what Python raised: a damaged file can make any library fail)."""
    if isinstance(err, SourceError):
        return err
    text = str(err).strip()
    first = text.splitlines()[0][:300] if text else ""
    if isinstance(err, LogpipeError):
        return SourceError(relpath, first or type(err).__name__)
    if isinstance(err, MemoryError):
        return SourceError(relpath, "damaged: a record claims more memory than is available (MemoryError)")
    return SourceError(relpath, f"unreadable or damaged: {type(err).__name__}: {first}" if first
                       else f"unreadable or damaged: {type(err).__name__}")


_VALUE_COLUMNS = ("x", "y", "heading", "vx", "vy", "length", "width")


def check_tracks(table: pa.Table, relpath: str) -> None:
    """Checks on one input's canonical rows that the binary formats need as much as the text ones: every
    value finite (a NaN quaternion or position must not land silently), times inside ``TIME_LIMIT_NS``, and no
    (log, track, time) twice.

    Raises:
        SourceError: naming the field and the first offending row (1-based, in the adapter's row order).
    """
    if table.num_rows == 0:
        return
    for name in _VALUE_COLUMNS:
        if name not in table.column_names:
            continue
        column = table.column(name)
        values = column.to_numpy(zero_copy_only=False).astype(np.float64, copy=False)
        valid = ~np.asarray(column.is_null().to_numpy(zero_copy_only=False), dtype=bool)
        bad = valid & ~np.isfinite(values)
        if bad.any():
            row = int(np.flatnonzero(bad)[0])
            raise SourceError(relpath, f"{int(bad.sum())} of {len(values)} rows are not finite "
                              f"(first: {values[row]!r}, track {table.column('track_id')[row].as_py()!r})",
                              line=row + 1, field=name)
    ts = np.asarray(table.column("timestamp_ns").to_numpy(zero_copy_only=False), dtype=np.int64)
    outside = np.abs(ts) >= TIME_LIMIT_NS
    if outside.any():
        row = int(np.flatnonzero(outside)[0])
        raise SourceError(relpath, f"timestamp {int(ts[row])} ns is outside +-2^62 ns", line=row + 1,
                          field="timestamp_ns")
    keys = pa.table({"log": pc.cast(table.column("log_id"), pa.string()),
                     "track": pc.cast(table.column("track_id"), pa.string()), "t": table.column("timestamp_ns")})
    counts = keys.group_by(["log", "track", "t"]).aggregate([]).num_rows
    if counts < keys.num_rows:  # the error path only: find the first repeat in Python
        seen: dict[tuple[object, object, int], int] = {}
        for row, key in enumerate(zip(keys.column("log").to_pylist(), keys.column("track").to_pylist(),
                                      ts.tolist(), strict=True)):
            if key in seen:
                raise SourceError(relpath, f"duplicated (track, time) row: track {key[1]!r} at {key[2]} ns "
                                  f"(rows {seen[key] + 1} and {row + 1})", line=row + 1, field="track_id")
            seen[key] = row


def finite_or_error(value: float, relpath: str, field: str, *, line: int | None = None) -> float:
    """``value`` when finite, else a ``SourceError`` naming ``field``."""
    if not math.isfinite(value):
        raise SourceError(relpath, f"not finite: {value!r}", line=line, field=field)
    return value


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
        maps: the map of each log, by log id, for formats whose inputs carry their own map (CommonRoad); ingest
            writes them into the dataset (``maps/``), where ``rasterise`` finds them without ``--maps``.
    """

    tracks: pa.Table
    logs: list[LogMeta]
    failures: list[SourceError]
    codes: TrackCodes | None = None
    maps: dict[str, MapStore] = field(default_factory=dict)


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
            _refuse_escaping_link(source)
            require_regular(source.path, source.relpath, folder_ok=True)
            table, meta, problems = read_one(source)
            check_log_id(meta.log_id, source.relpath)
            check_tracks(table, source.relpath)
        except Exception as exc:  # whatever a damaged input makes a library raise is that input's failure
            err = as_source_error(exc, source.relpath)
            if not keep_going:
                raise err from None
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


def irregular_digest(path: str | Path) -> str:
    """The digest recorded for an input that is not a regular file (its bytes cannot be read): from its path."""
    return hashlib.sha256(f"not a regular file: {path}".encode()).hexdigest()


def _empty_tracks() -> pa.Table:
    from logpipe.contracts import tracks_schema  # here: contracts is not needed by the adapters' fast paths

    return tracks_schema().empty_table()


def adapter_schema() -> pa.Schema:
    """The canonical track schema without ``step`` (the ingest stage computes it): what the log adapters return."""
    from logpipe.contracts import tracks_schema  # here: as in _empty_tracks

    schema = tracks_schema()
    return pa.schema([f for f in schema if f.name != "step"], metadata=schema.metadata)


def conform_tracks(table: pa.Table) -> pa.Table:
    """``table`` cast to ``adapter_schema()``."""
    from logpipe.contracts import conform

    return conform(table, adapter_schema())


def empty_tracks() -> pa.Table:
    """A table with no rows in ``adapter_schema()``."""
    return adapter_schema().empty_table()


def regular_sources(
    sources: list[SourceFile], keep_going: bool
) -> tuple[list[SourceFile], list[tuple[SourceFile, SourceError]]]:
    """``sources`` that are regular files (or folders: bags, AV2 sensor logs), and a failure for each other one,
    with a digest that names the path (its contents cannot be read: a FIFO blocks, a device never ends)."""
    good: list[SourceFile] = []
    refused: list[tuple[SourceFile, SourceError]] = []
    for source in sources:
        try:
            _refuse_escaping_link(source)
            require_regular(source.path, source.relpath, folder_ok=True)
        except SourceError as err:
            if not keep_going:
                raise
            refused.append((replace(source, sha256=irregular_digest(source.path), size=0), err))
            continue
        good.append(source)
    return good, refused


def _refuse_escaping_link(source: SourceFile) -> None:
    """Refuse an input that is a symbolic link to a file outside its input folder: in skip mode its parse
    error (which quotes the offending line) would copy another file's first line into the manifest."""
    path = str(source.path)
    if not os.path.islink(path):
        return
    base = path[: -len(source.relpath)] if path.endswith(source.relpath) else os.path.dirname(path)
    inside = os.path.realpath(base or ".")
    if os.path.commonpath([os.path.realpath(path), inside]) != inside:
        raise SourceError(source.relpath, "a symbolic link to a file outside its input folder; not read "
                          "(pass the file itself)")


def read_isolating(adapter: FormatAdapter, sources: list[SourceFile], keep_going: bool) -> ParsedLogs:
    """``adapter.read``, with the guarantee that a failure is the failure of exactly one input, whatever the
    adapter raised: a batch that raises anything but a ``SourceError`` it was asked to raise is read again one
    input at a time, and an input that still raises becomes that input's ``SourceError``."""
    try:
        return adapter.read(sources, keep_going=keep_going)
    except Exception as err:
        if (isinstance(err, SourceError) and not keep_going) or (
                isinstance(err, LogpipeError) and not isinstance(err, SourceError)):
            raise  # the error the caller asked for, or a setting (mapping, option) rather than an input
        if len(sources) == 1:
            error = as_source_error(err, sources[0].relpath)
            if not keep_going:
                raise error from None
            return ParsedLogs(tracks=_empty_tracks(), logs=[], failures=[error])
    parts = [read_isolating(adapter, [source], keep_going) for source in sources]
    kept = [p.tracks for p in parts if p.logs]
    tracks = pa.concat_tables(kept, promote_options="permissive") if kept else _empty_tracks()
    return ParsedLogs(tracks=tracks, logs=[m for p in parts for m in p.logs],
                      failures=[e for p in parts for e in p.failures],
                      maps={k: v for p in parts for k, v in p.maps.items()})


def refuse_unsafe_log_ids(parsed: ParsedLogs, keep_going: bool) -> ParsedLogs:
    """``parsed`` without the logs whose id is not one safe file name (ids become ``mcap/<log_id>.mcap`` and
    prediction files): ``../../x`` from a data column must not write outside the dataset; nor those with a
    negative time (no MCAP can hold it)."""
    bad: dict[str, SourceError] = {}
    early = _earliest_times(parsed.tracks)
    implausible = implausible_rows(parsed.tracks)
    for meta in parsed.logs:
        try:
            check_log_id(meta.log_id, meta.source_file)
            # MCAP log times are unsigned: a negative frame or time (ETH/UCY frame -400) is this input's error,
            # quarantined in skip mode, never a crash of the whole batch in the MCAP writer.
            if early.get(meta.log_id, 0) < 0:
                raise SourceError(meta.source_file, f"time {early[meta.log_id]} ns is negative (a negative frame "
                                  "number or time stamp; log times start at 0)", field="timestamp_ns")
            if meta.log_id in implausible:
                field, reason = implausible[meta.log_id]
                raise SourceError(meta.source_file, reason, field=field)
        except SourceError as err:
            if not keep_going:
                raise
            bad[meta.log_id] = err
    if not bad:
        return parsed
    tracks = parsed.tracks.filter(pc.invert(pc.is_in(pc.cast(parsed.tracks.column("log_id"), pa.string()),
                                                     pa.array(list(bad), pa.string()))))
    return ParsedLogs(tracks=tracks, logs=[m for m in parsed.logs if m.log_id not in bad],
                      failures=[*parsed.failures, *bad.values()],  # codes dropped: rows were removed
                      maps={k: v for k, v in parsed.maps.items() if k not in bad})


COORD_LIMIT_M = 1e7
"""Largest |x| or |y| accepted, in metres (10,000 km): above any UTM northing or city frame; 1e12 m is damage."""


def implausible_rows(tracks: pa.Table) -> dict[str, tuple[str, str]]:
    """(field, reason) for each log of ``tracks`` holding a physically implausible row: a coordinate beyond
    ``COORD_LIMIT_M``, a track id with NUL or control characters (ids reach file names, MCAP and terminals), or
    motion no agent is capable of (``logpipe.formats.motion_checks``).
    One vectorised pass, the same for every format."""
    if tracks.num_rows == 0:
        return {}
    logs = pc.cast(tracks.column("log_id"), pa.string())
    found: dict[str, tuple[str, str]] = {}
    for name in ("x", "y"):
        far = pc.fill_null(pc.greater_equal(pc.abs(tracks.column(name)), COORD_LIMIT_M), False)
        for log, value in zip(pc.filter(logs, far).to_pylist(), pc.filter(tracks.column(name), far).to_pylist(),
                              strict=True):
            found.setdefault(log, (name, f"{value!r} m is beyond the plausible {COORD_LIMIT_M:.0e} m"))
    ids = pc.cast(tracks.column("track_id"), pa.string())
    control = pc.fill_null(pc.match_substring_regex(ids, r"[\x00-\x1f\x7f]"), False)
    for log, value in zip(pc.filter(logs, control).to_pylist(), pc.filter(ids, control).to_pylist(), strict=True):
        found.setdefault(log, ("track_id", f"track id {value[:40]!r} holds NUL or control characters"))
    for log, why in impossible_motion(tracks).items():  # jumps and velocities beyond any agent's
        found.setdefault(log, why)
    return found


def _earliest_times(tracks: pa.Table) -> dict[str, int]:
    """The earliest ``timestamp_ns`` of each log of ``tracks``."""
    if tracks.num_rows == 0:
        return {}
    table = pa.table({"log": pc.cast(tracks.column("log_id"), pa.string()), "t": tracks.column("timestamp_ns")})
    earliest = table.group_by("log").aggregate([("t", "min")])
    return dict(zip(earliest.column("log").to_pylist(), earliest.column("t_min").to_pylist(), strict=True))


def source_of(file: str, by_path: dict[str, SourceFile]) -> SourceFile:
    """The input an error names: its relpath, or the input folder holding the file it names (an AV2 sensor
    log's ``<log>/annotations.feather``)."""
    if file in by_path:
        return by_path[file]
    owners = [rel for rel in by_path if file.startswith(rel.rstrip("/") + "/")]
    if owners:
        return by_path[max(owners, key=len)]
    return SourceFile(file, file, irregular_digest(file), 0)
