"""Where each log's rows are in a table of track rows grouped by log.

Track shards (and the batches ingest builds them from) keep a log's rows together (sorted by log id, then time),
so a log is one contiguous run of rows: finding the runs once is much cheaper than filtering the table per log.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import numpy.typing as npt
import pyarrow as pa
import pyarrow.compute as pc

from logpipe.types import NDArrayInt


def log_runs(log_keys: npt.NDArray[Any]) -> tuple[NDArrayInt, NDArrayInt]:
    """Each log's [start, end) rows, in row order.

    Args:
        log_keys: one key per row, the log id or an integer code of it; each log's rows must be contiguous (a
            log whose rows are not would be reported once per run).

    Returns:
        ``(starts, ends)``: int64 row numbers, one pair per log; both empty when there are no rows.
    """
    n = len(log_keys)
    if n == 0:
        return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
    starts = np.flatnonzero(np.concatenate([[True], log_keys[1:] != log_keys[:-1]])).astype(np.int64)
    return starts, np.append(starts[1:], np.int64(n))


def log_slices(tracks: pa.Table) -> dict[str, tuple[int, int]]:
    """``{log_id: (start, end)}``: each log's [start, end) rows in ``tracks`` (rows grouped by log), in row order."""
    # Runs of dictionary codes: no Python string per row.
    ids = tracks.column("log_id")
    if pa.types.is_dictionary(ids.type):  # a file's dictionary may repeat a value
        ids = ids.cast(ids.type.value_type)
    encoded = pc.dictionary_encode(ids).combine_chunks()
    names = encoded.dictionary.to_pylist()
    codes = encoded.indices.to_numpy()
    starts, ends = log_runs(codes)
    return {str(names[codes[lo]]): (lo, hi) for lo, hi in zip(starts.tolist(), ends.tolist(), strict=True)}
