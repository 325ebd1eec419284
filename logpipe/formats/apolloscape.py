"""ApolloScape trajectory files: ``frame obj type x y z length width height heading``, space-separated, CRLF.

2 frames per second (``timestamp_ns = frame * 0.5 s``); x/y/z metres in a local frame per file; heading in
radians. Type codes: 1 small vehicle, 2 big vehicle, 3 pedestrian, 4 bicyclist (or motorcyclist, the
tracking release says), 5 others. Ids may disappear and reappear: the gap stays visible in the steps.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import ClassVar

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc

from logpipe.dataset.samples import steps_from_sorted_times
from logpipe.errors import SourceError
from logpipe.formats._text import (
    ID_LIMIT,
    NumericTextFormat,
    TextBatch,
    log_ids_column,
    parse_files,
)
from logpipe.formats.base import TIME_LIMIT_NS, ParsedLogs
from logpipe.formats.text_checks import check_finite, check_range, check_time_and_duplicates, row_error
from logpipe.storage.io import as_numpy
from logpipe.types import PROTOCOLS, LogMeta, ObjectType, Role, SampleProtocol, SourceFile

COLUMNS = ["frame_id", "object_id", "object_type", "x", "y", "z", "length", "width", "height", "heading"]
_TYPES = {name: pa.float64() for name in COLUMNS}
FRAME_PERIOD_NS = 500_000_000
TYPE_CODES: dict[int, str] = {
    1: ObjectType.VEHICLE.value,
    2: ObjectType.BUS_TRUCK.value,
    3: ObjectType.PEDESTRIAN.value,
    4: ObjectType.CYCLIST.value,
    5: ObjectType.UNKNOWN.value,
}


class ApolloScapeAdapter(NumericTextFormat):
    """Reads ApolloScape ``result_*_frame.txt`` files (10 space-separated numeric columns)."""

    name: ClassVar[str] = "apolloscape"
    default_protocol: ClassVar[SampleProtocol] = PROTOCOLS["apolloscape"]
    batch_files: ClassVar[int] = 64
    columns: ClassVar[list[str]] = COLUMNS
    delimiter: ClassVar[str] = " "

    def read(self, sources: Sequence[SourceFile], *, keep_going: bool) -> ParsedLogs:
        """Parse a batch of files; bad files raise (or, with ``keep_going``, are returned as failures)."""
        table, batch, good, failures = parse_files(
            sources, keep_going=keep_going, names=COLUMNS, types=_TYPES, delimiter=self.delimiter, header_lines=0,
            validate=_validate,
        )
        ts = (as_numpy(table.column("frame_id")).astype(np.int64)) * FRAME_PERIOD_NS
        codes = as_numpy(table.column("object_type")).astype(np.int64)
        lookup = np.array([""] + [TYPE_CODES[c] for c in sorted(TYPE_CODES)], dtype=object)
        tracks = pa.table(
            {
                "log_id": log_ids_column(batch, good),
                "timestamp_ns": ts,
                "step": steps_from_sorted_times(ts, batch.file_index).astype(np.int32),
                "track_id": pc.cast(pa.array(as_numpy(table.column("object_id")).astype(np.int64)), pa.string()),
                "object_type": pa.array(lookup[codes], pa.string()),
                "role": pa.array(np.full(len(ts), Role.OTHER.value)),
                "x": table.column("x"),
                "y": table.column("y"),
                "heading": table.column("heading"),
                "length": table.column("length"),
                "width": table.column("width"),
                "source_type": pc.cast(pa.array(codes), pa.string()),
            }
        )
        logs = [
            LogMeta(
                log_id=Path(s.relpath).stem,
                source_format=self.name,
                source_file=s.relpath,
                source_sha256=s.sha256,
                map_id=None,
                frame_rate_hz=2.0,
                memberships=s.memberships,
                attributes={},
            )
            for s in good
        ]
        return ParsedLogs(tracks=tracks, logs=logs, failures=failures)


def _validate(table: pa.Table, batch: TextBatch, sources: Sequence[SourceFile]) -> tuple[pa.Table, list[SourceError]]:
    return table, _errors(table, batch, sources)


def _errors(table: pa.Table, batch: TextBatch, sources: Sequence[SourceFile]) -> list[SourceError]:
    errors = check_finite(table, COLUMNS, batch, sources)
    if errors:
        return errors
    # Before any int64 conversion: frame x period must not wrap, ids must be exact integers in a float.
    errors = check_range(table, {"frame_id": TIME_LIMIT_NS / FRAME_PERIOD_NS, "object_id": ID_LIMIT}, batch, sources,
                         non_negative=("frame_id",))
    if errors:
        return errors
    for name in ("frame_id", "object_id", "object_type"):
        values = as_numpy(table.column(name))
        fractional = values != np.round(values)
        if fractional.any():
            row = int(np.flatnonzero(fractional)[0])
            errors.append(row_error(batch, sources, row, f"not a whole number: {values[row]!r}", name))
    codes = as_numpy(table.column("object_type"))
    unknown = ~np.isin(codes, list(TYPE_CODES))
    if unknown.any():
        row = int(np.flatnonzero(unknown)[0])
        errors.append(row_error(batch, sources, row, f"unknown type code {codes[row]!r} (1-5)", "object_type"))
    if errors:
        return errors
    ts = as_numpy(table.column("frame_id")).astype(np.int64) * FRAME_PERIOD_NS
    ids = as_numpy(table.column("object_id")).astype(np.int64)
    return check_time_and_duplicates(ts, ids - ids.min() if len(ids) else ids, batch, sources, "frame_id",
                                     "object_id")
