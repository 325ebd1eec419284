"""ETH/UCY pedestrian files as distributed by Social-GAN: ``frame_id  ped_id  x  y``, tab-separated.

frame_id is a video frame number (written as ``780`` or ``780.0``); annotations are 10 frames apart,
0.4 s at the nominal 25 fps, so ``timestamp_ns = frame_id * 40 ms``. x/y are metres in a plane specific to
each scene. The folder layout ``<scene>/<train|val|test>/<file>.txt`` gives each file its memberships
(``eth/test``, ``univ/train``, ...); identical files under several scenes are one log with several
memberships, so leave-one-scene-out selects logs by membership instead of copying data.
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

COLUMNS = ["frame_id", "ped_id", "x", "y"]
_TYPES = {name: pa.float64() for name in COLUMNS}
FRAME_PERIOD_NS = 40_000_000  # 25 fps video; annotations every 10 frames = 0.4 s (2.5 Hz)


class EthUcyAdapter(NumericTextFormat):
    """Reads ETH/UCY ``*.txt`` files (4 tab-separated numeric columns, no header)."""

    name: ClassVar[str] = "ethucy"
    default_protocol: ClassVar[SampleProtocol] = PROTOCOLS["ethucy"]
    batch_files: ClassVar[int] = 64
    columns: ClassVar[list[str]] = COLUMNS
    delimiter: ClassVar[str] = "\t"

    def read(self, sources: Sequence[SourceFile], *, keep_going: bool) -> ParsedLogs:
        """Parse a batch of files; bad files raise (or, with ``keep_going``, are returned as failures)."""
        table, batch, good, failures = parse_files(
            sources, keep_going=keep_going, names=COLUMNS, types=_TYPES, delimiter=self.delimiter, header_lines=0,
            validate=_validate,
        )
        frames = as_numpy(table.column("frame_id"))
        ts = np.rint(frames * FRAME_PERIOD_NS).astype(np.int64)
        peds = as_numpy(table.column("ped_id"))
        tracks = pa.table(
            {
                "log_id": log_ids_column(batch, good),
                "timestamp_ns": ts,
                "step": steps_from_sorted_times(ts, batch.file_index).astype(np.int32),
                "track_id": pc.cast(pa.array(peds.astype(np.int64)), pa.string()),
                "object_type": pa.array(np.full(len(ts), ObjectType.PEDESTRIAN.value)),
                "role": pa.array(np.full(len(ts), Role.OTHER.value)),
                "x": table.column("x"),
                "y": table.column("y"),
                "source_type": pa.array(np.full(len(ts), "pedestrian")),
            }
        )
        logs = [
            LogMeta(
                log_id=Path(s.relpath).stem,
                source_format=self.name,
                source_file=s.relpath,
                source_sha256=s.sha256,
                map_id=None,
                frame_rate_hz=2.5,
                memberships=s.memberships,
                attributes={"recording": Path(s.relpath).stem.removesuffix("_train").removesuffix("_val")},
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
    errors = check_range(table, {"frame_id": TIME_LIMIT_NS / FRAME_PERIOD_NS, "ped_id": ID_LIMIT}, batch, sources,
                         non_negative=("frame_id",))
    if errors:
        return errors
    for name in ("frame_id", "ped_id"):
        values = as_numpy(table.column(name))
        fractional = values != np.round(values)
        if fractional.any():
            row = int(np.flatnonzero(fractional)[0])
            errors.append(row_error(batch, sources, row, f"not a whole number: {values[row]!r}", name))
    if errors:
        return errors
    ts = np.rint(as_numpy(table.column("frame_id")) * FRAME_PERIOD_NS).astype(np.int64)
    peds = as_numpy(table.column("ped_id")).astype(np.int64)
    return check_time_and_duplicates(ts, peds - peds.min() if len(peds) else peds, batch, sources, "frame_id",
                                     "ped_id")
