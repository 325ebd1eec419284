"""The logs table's rows of one batch of track rows: a pure transform of a canonical track table.

``canonical_order`` puts an adapter's rows in the track-table order (log, time, track; ``step`` filled in);
``log_rows`` then gives one logs-table row per log (``schemas/logs.json``): the adapter's ``LogMeta`` plus
statistics of the log's rows (``log_stats``), every one a slice boundary or a reduction over the contiguous
run of the log's rows, so no hashing group-by. Times are nanoseconds (``timestamp_ns``), steps are indices.
"""

from __future__ import annotations

import json
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc

from logpipe.contracts import arrow_schema, conform, tracks_schema
from logpipe.dataset.samples import TrackCodes, steps_from_sorted_times
from logpipe.dataset.shards import log_runs
from logpipe.storage.io import as_numpy
from logpipe.types import LogMeta, NDArrayBool, NDArrayInt, Role

STAT_KEYS = ("num_rows", "num_tracks", "num_steps", "start_ns", "end_ns", "median_dt_ns", "has_ego")
"""The logs-table columns ``log_stats`` computes from the rows (the rest come from the adapter's ``LogMeta``)."""


def canonical_order(tracks: pa.Table) -> pa.Table:
    """Rows sorted by log, time, track with ``step`` filled in, in the track-table schema.

    Adapters that return ``step`` promise this order already (the text adapters keep file order, which is
    by time), which saves a sort of millions of rows.
    """
    if "step" not in tracks.column_names:
        tracks = tracks.sort_by([("log_id", "ascending"), ("timestamp_ns", "ascending"),
                                 ("track_id", "ascending")])
        log_ids = as_numpy(pc.dictionary_encode(tracks.column("log_id")).combine_chunks().indices)

        steps = steps_from_sorted_times(as_numpy(tracks.column("timestamp_ns")), log_ids.astype(np.int64))
        tracks = tracks.append_column("step", pa.array(steps.astype(np.int32)))
    return conform(tracks, tracks_schema(), keep_dictionaries=True)


def log_rows(
    tracks: pa.Table, metas: list[LogMeta], shard: str, codes: TrackCodes | None
) -> tuple[pa.Table, list[LogMeta]]:
    """The logs-table rows for ``metas`` (stats from ``tracks``), and the metas that have no rows.

    ``tracks`` is in canonical order (logs contiguous, time ascending), so every statistic is a slice
    boundary or a reduction over contiguous runs: no hashing group-by.
    """
    stats = log_stats(tracks, codes) if codes is not None else {}
    kept = [m for m in metas if m.log_id in stats]
    empty = [m for m in metas if m.log_id not in stats]
    rows = [stats[m.log_id] for m in kept]
    # Column by column (one comprehension each): a per-log loop of appends costs as much as the statistics.
    columns: dict[str, list[Any]] = {
        "log_id": [m.log_id for m in kept],
        "source_format": [m.source_format for m in kept],
        "source_file": [m.source_file for m in kept],
        "source_sha256": [m.source_sha256 for m in kept],
        "map_id": [m.map_id for m in kept],
        "frame_rate_hz": [m.frame_rate_hz for m in kept],
        "memberships": [list(m.memberships) for m in kept],
        "attributes": [json.dumps(m.attributes, sort_keys=True) for m in kept],
        "shard": [shard] * len(kept),
    }
    for key in STAT_KEYS:
        columns[key] = [row[key] for row in rows]
    return conform(pa.table({name: columns[name] for name in arrow_schema("logs").names}), arrow_schema("logs")), \
        empty


def log_metas(logs: pa.Table) -> list[LogMeta]:
    """The ``LogMeta`` of each logs-table row, as far as building the sample index needs it (memberships and
    attributes left at their defaults)."""
    return [
        LogMeta(log_id=r["log_id"], source_format=r["source_format"], source_file=r["source_file"],
                source_sha256=r["source_sha256"], map_id=r["map_id"], frame_rate_hz=r["frame_rate_hz"])
        for r in logs.select(["log_id", "source_format", "source_file", "source_sha256", "map_id",
                              "frame_rate_hz"]).to_pylist()
    ]


def log_stats(tracks: pa.Table, codes: TrackCodes) -> dict[str, dict[str, Any]]:
    """Per-log row count, distinct tracks and steps, time span, median step and whether an ego exists."""
    logs, names, tracks_code = codes.log_code, codes.log_names, codes.track_code
    steps = as_numpy(tracks.column("step"))
    ts = as_numpy(tracks.column("timestamp_ns"))
    ego = column_equals(tracks.column("role"), Role.EGO.value)
    starts, ends = log_runs(logs)
    distinct = distinct_per_group(logs, tracks_code, len(names))
    egos = np.zeros(len(names), dtype=bool)
    egos[logs[ego]] = True
    first_of_step = np.flatnonzero(np.concatenate([[True], (steps[1:] != steps[:-1]) | (logs[1:] != logs[:-1])]))
    median_dt = median_step(logs[first_of_step], ts[first_of_step], len(names))
    stats = {}
    for i, lo, hi in zip(logs[starts].tolist(), starts.tolist(), ends.tolist(), strict=True):
        stats[names[i]] = {
            "num_rows": hi - lo,
            "num_tracks": int(distinct[i]),
            "num_steps": int(steps[hi - 1]) + 1,
            "start_ns": int(ts[lo]),
            "end_ns": int(ts[hi - 1]),
            "median_dt_ns": int(median_dt[i]),
            "has_ego": bool(egos[i]),
        }
    return stats


def column_equals(column: pa.ChunkedArray, value: str) -> NDArrayBool:
    """``column == value`` as numpy; for a dictionary column by its codes (no string compare per row)."""
    if pa.types.is_dictionary(column.type) and column.num_chunks == 1:
        encoded = column.chunk(0)
        matches = np.flatnonzero(as_numpy(pc.equal(encoded.dictionary, value)))
        found: NDArrayBool = np.isin(as_numpy(encoded.indices), matches)
        return found
    plain: NDArrayBool = as_numpy(pc.equal(column, value)).astype(bool)
    return plain


def distinct_per_group(groups: NDArrayInt, codes: NDArrayInt, n_groups: int) -> NDArrayInt:
    """Number of distinct ``codes`` in each group: a presence table when it is small, else a sort."""
    n_codes = int(codes.max()) + 1 if len(codes) else 1
    if n_groups * n_codes <= 1 << 24:  # 16 MB of booleans: a scatter beats sorting every row
        seen = np.zeros((n_groups, n_codes), dtype=bool)
        seen[groups, codes] = True
        counts: NDArrayInt = seen.sum(axis=1)
        return counts
    pairs = np.unique(groups * n_codes + codes)
    return np.bincount(pairs // n_codes, minlength=n_groups)


def median_step(step_logs: NDArrayInt, step_ts: NDArrayInt, n_logs: int) -> NDArrayInt:
    """Median gap (ns) between consecutive step timestamps of each log (0 for a one-step log), vectorised."""
    same = step_logs[1:] == step_logs[:-1]
    gaps, owners = np.diff(step_ts)[same], step_logs[1:][same]
    order = np.lexsort((gaps, owners))
    gaps, owners = gaps[order], owners[order]
    counts = np.bincount(owners, minlength=n_logs)
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    result = np.zeros(n_logs, dtype=np.int64)
    has = counts > 0
    lower = gaps[starts[has] + (counts[has] - 1) // 2]
    upper = gaps[starts[has] + counts[has] // 2]
    result[has] = (lower + upper) // 2  # the mean of the middle two for an even count, as np.median
    return result
