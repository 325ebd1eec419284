"""Checks every delimited-text format applies to its parsed columns, each error naming the file and line:
values in range and finite, time never going backwards inside a file, no (track, time) twice.

Vectorised over a whole batch of files (see ``TextBatch``); the error paths find the first offending line.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import pyarrow as pa

from logpipe.errors import SourceError
from logpipe.formats._text import TextBatch
from logpipe.storage.io import as_numpy
from logpipe.types import NDArrayBool, NDArrayInt, SourceFile


def check_range(
    table: pa.Table, limits: dict[str, float], batch: TextBatch, sources: Sequence[SourceFile],
    non_negative: Sequence[str] = (),
) -> list[SourceError]:
    """One error per file with a value of a column in ``limits`` whose magnitude is not below its limit (or, for
    ``non_negative`` columns such as frame numbers, below 0): checked on the floats, before they are converted to
    int64 (frames x period, ids) where they would wrap silently."""
    errors: dict[int, SourceError] = {}
    for name, limit in limits.items():
        values = as_numpy(table.column(name))
        floor = 0.0 if name in non_negative else -limit
        bad = ~((np.abs(values) < limit) & (values >= floor))
        for row in np.flatnonzero(bad)[:1000].tolist():
            f = int(batch.file_index[row])
            bound = f"must be in [0, {limit:.4g})" if name in non_negative else f"|value| must be below {limit:.4g}"
            errors.setdefault(f, row_error(batch, sources, row, f"{values[row]!r} is out of range ({bound})", name))
    return [errors[f] for f in sorted(errors)]


def first_true(mask: NDArrayBool) -> int:
    """Index of the first True in ``mask`` (caller knows there is one)."""
    return int(np.flatnonzero(mask)[0])


def check_finite(
    table: pa.Table, columns: Sequence[str], batch: TextBatch, sources: Sequence[SourceFile]
) -> list[SourceError]:
    """One error per file holding NaN or infinite values in ``columns``, naming the first such line."""
    errors: dict[int, SourceError] = {}
    files = batch.file_index
    starts = batch.row_starts
    for name in columns:
        values = as_numpy(table.column(name))
        bad = ~np.isfinite(values)
        if bad.any():
            for row in np.flatnonzero(bad):
                f = int(files[row])
                if f not in errors:
                    line = int(row - starts[f]) + batch.header_lines + 1
                    errors[f] = SourceError(
                        sources[f].relpath, f"not finite: {values[row]!r}", line=line, field=name
                    )
    return [errors[f] for f in sorted(errors)]


def check_time_and_duplicates(
    ts_ns: NDArrayInt,
    track_codes: NDArrayInt,
    batch: TextBatch,
    sources: Sequence[SourceFile],
    time_field: str,
    track_field: str,
) -> list[SourceError]:
    """Errors for files whose time goes backwards, or that repeat a (track, time) pair; first line named.

    Rows must come in file order. Vectorised over the whole batch: one diff and one sort of int64 keys.
    """
    errors: dict[int, SourceError] = {}
    files = batch.file_index
    starts = batch.row_starts
    n = len(ts_ns)
    if n == 0:
        return []

    def line_of(row: int) -> int:
        return int(row - starts[files[row]]) + batch.header_lines + 1

    same_file = files[1:] == files[:-1]
    backwards = np.flatnonzero(same_file & (ts_ns[1:] < ts_ns[:-1])) + 1
    for row in backwards.tolist():
        f = int(files[row])
        errors.setdefault(
            f,
            SourceError(
                sources[f].relpath,
                f"time goes backwards ({ts_ns[row - 1]} ns then {ts_ns[row]} ns)",
                line=line_of(int(row)),
                field=time_field,
            ),
        )
    # Duplicates: equal (file, time, track) keys. Ranks of time and track within the batch keep keys in int64.
    _, time_rank = np.unique(ts_ns, return_inverse=True)
    _, track_codes = np.unique(track_codes, return_inverse=True)
    key = (files * (int(time_rank.max()) + 1) + time_rank) * (int(track_codes.max()) + 1) + track_codes
    order = np.argsort(key, kind="stable")
    dup_sorted = np.flatnonzero(key[order][1:] == key[order][:-1]) + 1
    for pos in dup_sorted.tolist():
        dup_row = int(order[pos])
        f = int(files[dup_row])
        errors.setdefault(
            f,
            SourceError(
                sources[f].relpath,
                f"duplicated (track, time) row: first at line {line_of(int(order[pos - 1]))}",
                line=line_of(dup_row),
                field=track_field,
            ),
        )
    return [errors[f] for f in sorted(errors)]


def times_sorted_and_unique(ts_ns: NDArrayInt, track_codes: NDArrayInt, files: NDArrayInt) -> bool:
    """True when time never goes backwards inside a file and no (file, track, time) repeats.

    The cheap test run on every batch (one diff, one sort of int64 keys that are already ordered by time);
    ``check_time_and_duplicates`` then names the file and line for a batch that fails it.
    """
    if len(ts_ns) < 2:
        return True
    same_file = files[1:] == files[:-1]
    if (same_file & (ts_ns[1:] < ts_ns[:-1])).any():
        return False
    run = np.zeros(len(ts_ns), dtype=np.int64)  # run of equal (file, time): a duplicate must sit inside one
    np.cumsum(~same_file | (ts_ns[1:] != ts_ns[:-1]), out=run[1:])
    key = run * (int(track_codes.max()) + 1) + track_codes
    key.sort(kind="stable")  # nearly sorted already: timsort merges the runs cheaply
    return not bool((key[1:] == key[:-1]).any())


def row_error(
    batch: TextBatch, sources: Sequence[SourceFile], row: int, reason: str, field: str
) -> SourceError:
    """A ``SourceError`` for batch row ``row``, with the file and line it came from."""
    f = int(batch.file_index[row])
    line = int(row - batch.row_starts[f]) + batch.header_lines + 1
    return SourceError(sources[f].relpath, reason, line=line, field=field)
