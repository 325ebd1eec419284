"""Argoverse 1 motion-forecasting CSVs: one file per 5 s sequence, one row per (timestamp, track).

Header ``TIMESTAMP,TRACK_ID,OBJECT_TYPE,X,Y,CITY_NAME``; TIMESTAMP is decimal seconds, X/Y are metres in
the city frame of CITY_NAME (MIA or PIT). OBJECT_TYPE says why a track is there, not what it is: ``AV`` is
the recording vehicle (role ego), ``AGENT`` the vehicle the sequence was mined for (role focal), ``OTHERS``
everything else tracked, whose class the CSV does not give (object type ``unknown``).

Speed: the devkit reads one file per ``pandas.read_csv`` call; here a batch of files is joined and parsed
in one pyarrow call, then mapped back to files by their line counts.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import ClassVar

import numpy as np
import pyarrow as pa

from logpipe.dataset.samples import TrackCodes, steps_from_sorted_times
from logpipe.errors import SourceError
from logpipe.formats._text import (
    TextBatch,
    decimal_seconds_to_ns,
    dictionary_column,
    log_ids_column,
    parse_files,
    relabel,
    stem,
)
from logpipe.formats.base import ParsedLogs, files_with_suffix
from logpipe.formats.text_checks import (
    check_finite,
    check_time_and_duplicates,
    first_true,
    row_error,
    times_sorted_and_unique,
)
from logpipe.storage.io import as_numpy
from logpipe.types import PROTOCOLS, LogMeta, ObjectType, Role, SampleProtocol, SourceFile

COLUMNS = ["TIMESTAMP", "TRACK_ID", "OBJECT_TYPE", "X", "Y", "CITY_NAME"]
HEADER = ",".join(COLUMNS).encode()
# Dictionary-encoded while parsing: ~50 distinct timestamps and tracks per file, and every later step
# (exact time conversion, duplicate check, track codes) wants the codes anyway.
_TYPES = {
    "TIMESTAMP": pa.dictionary(pa.int32(), pa.string()),
    "TRACK_ID": pa.dictionary(pa.int32(), pa.string()),
    "OBJECT_TYPE": pa.dictionary(pa.int32(), pa.string()),
    "X": pa.float64(),
    "Y": pa.float64(),
    "CITY_NAME": pa.dictionary(pa.int32(), pa.string()),
}
_ROLE = {"AV": Role.EGO.value, "AGENT": Role.FOCAL.value, "OTHERS": Role.OTHER.value}
_OBJECT_TYPE = {"AV": ObjectType.VEHICLE.value, "AGENT": ObjectType.VEHICLE.value, "OTHERS": ObjectType.UNKNOWN.value}


class Argoverse1Adapter:
    """Reads Argoverse 1 forecasting CSVs (``*.csv`` with the header above)."""

    name: ClassVar[str] = "argoverse1"
    default_protocol: ClassVar[SampleProtocol] = PROTOCOLS["argoverse"]
    batch_files: ClassVar[int] = 250  # ~220k rows per shard; enough batches to keep every core busy
    hashes_while_reading: ClassVar[bool] = True  # parse_files hashes each blob it reads

    def discover(self, root: Path) -> list[Path]:
        """CSV files under ``root`` (or ``root`` itself)."""
        return files_with_suffix(root, (".csv",))

    def sniff(self, path: Path) -> bool:
        """True for a CSV whose first line is the Argoverse 1 header."""
        if path.suffix.lower() != ".csv" or not path.is_file():
            return False
        with path.open("rb") as fh:
            return fh.readline().strip() == HEADER

    def read(self, sources: Sequence[SourceFile], *, keep_going: bool) -> ParsedLogs:
        """Parse a batch of CSVs; bad files raise (or, with ``keep_going``, are returned as failures)."""
        table, batch, good, failures = parse_files(
            sources, keep_going=keep_going, names=COLUMNS, types=_TYPES, delimiter=",", header_lines=1,
            validate=_validate, check_header=_check_header,
        )
        tracks, logs, codes = _to_canonical(table, batch, good)
        return ParsedLogs(tracks=tracks, logs=logs, failures=failures, codes=codes if tracks.num_rows else None)


def _check_header(source: SourceFile, header: bytes, has_rows: bool) -> SourceError | None:
    first = header.strip()
    if not first and not has_rows:
        return SourceError(source.relpath, "empty file (no header, no rows)", line=1)
    if first != HEADER:
        found = first.decode("utf-8", "replace").split(",")
        missing = [c for c in COLUMNS if c not in found]
        extra = [c for c in found if c not in COLUMNS]
        detail = []
        if missing:
            detail.append(f"missing columns {missing}")
        if extra:
            detail.append(f"unexpected columns {extra}")
        if not detail:
            detail.append(f"columns in order {found}, expected {COLUMNS}")
        return SourceError(source.relpath, "bad header: " + "; ".join(detail), line=1)
    if not has_rows:
        return SourceError(source.relpath, "no data rows after the header", line=2)
    return None


def _validate(table: pa.Table, batch: TextBatch, sources: Sequence[SourceFile]) -> tuple[pa.Table, list[SourceError]]:
    """Checks, plus the exact nanosecond timestamps (column ``_ns``) that the checks need anyway.

    Every check is one vectorised pass over the batch; line-level detail is worked out only for a batch
    that fails one.
    """
    errors = check_finite(table, ["X", "Y"], batch, sources)
    files = batch.file_index
    stamps = dictionary_column(table.column("TIMESTAMP"))
    ns, valid = decimal_seconds_to_ns(stamps)
    valid_np = as_numpy(valid)
    if not valid_np.all():
        row = first_true(~valid_np)
        value = stamps[row].as_py()
        errors.append(row_error(batch, sources, row, f"not a decimal number of seconds: {value!r}", "TIMESTAMP"))
    kinds = dictionary_column(table.column("OBJECT_TYPE"))
    unknown = [i for i, v in enumerate(kinds.dictionary.to_pylist()) if v not in _ROLE]
    if unknown:
        row = first_true(np.isin(as_numpy(kinds.indices), unknown))
        reason = f"unknown OBJECT_TYPE {kinds[row].as_py()!r} (AV, AGENT, OTHERS)"
        errors.append(row_error(batch, sources, row, reason, "OBJECT_TYPE"))
    city = as_numpy(dictionary_column(table.column("CITY_NAME")).indices)
    changes = np.flatnonzero((city[1:] != city[:-1]) & (files[1:] == files[:-1])) + 1
    if len(changes):
        errors.append(row_error(batch, sources, int(changes[0]), "CITY_NAME changes inside the file", "CITY_NAME"))
    tracks = dictionary_column(table.column("TRACK_ID"))
    ns_np = as_numpy(ns)
    if not errors:
        track_codes = as_numpy(tracks.indices).astype(np.int64)
        if not times_sorted_and_unique(ns_np, track_codes, files):  # then find which file and line
            errors.extend(
                check_time_and_duplicates(ns_np, track_codes, batch, sources, "TIMESTAMP", "TRACK_ID")
            )
    combined = {"TRACK_ID": tracks, "OBJECT_TYPE": kinds}
    columns = [combined.get(n, table.column(n)) for n in table.column_names]
    return pa.table([*columns, ns], names=[*table.column_names, "_ns"]), errors


def _to_canonical(
    table: pa.Table, batch: TextBatch, sources: Sequence[SourceFile]
) -> tuple[pa.Table, list[LogMeta], TrackCodes]:
    files = batch.file_index
    ns_np = as_numpy(table.column("_ns"))
    kinds = dictionary_column(table.column("OBJECT_TYPE"))
    tracks = dictionary_column(table.column("TRACK_ID"))
    stems = [stem(s.relpath) for s in sources]
    # String columns stay dictionary-encoded (the track-table contract allows it; readers see strings).
    table_out = pa.table(
        {
            "log_id": log_ids_column(batch, sources),
            "timestamp_ns": table.column("_ns"),
            "step": pa.array(steps_from_sorted_times(ns_np, files).astype(np.int32)),
            "track_id": tracks,
            "object_type": relabel(kinds, _OBJECT_TYPE),
            "role": relabel(kinds, _ROLE),
            "x": table.column("X"),
            "y": table.column("Y"),
            "source_type": kinds,
        }
    )
    # Rows are in file order and every file has rows, so the file index is the log code (first-seen order).
    codes = TrackCodes(log_code=files, log_names=stems, track_code=as_numpy(tracks.indices).astype(np.int64),
                       track_names=np.array(tracks.dictionary.to_pylist(), dtype=object))
    cities = dictionary_column(table.column("CITY_NAME"))
    city_names = cities.dictionary.to_pylist()
    city_codes = as_numpy(cities.indices)
    starts = batch.row_starts
    logs = []
    for i, source in enumerate(sources):
        city = city_names[city_codes[starts[i]]] if batch.rows_per_file[i] else None
        logs.append(
            LogMeta(
                log_id=stems[i],
                source_format=Argoverse1Adapter.name,
                source_file=source.relpath,
                source_sha256=source.sha256,
                map_id=city,
                frame_rate_hz=10.0,
                memberships=source.memberships,
                attributes={"sequence_id": stems[i]},
            )
        )
    return table_out, logs, codes

