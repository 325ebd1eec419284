"""Building the predictions table (``logpipe.prediction.runs``: its layout and metadata) from forecasts, column-wise.

Positions are metres in the log's world frame; times are ns on the log's clock.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
import pyarrow.parquet as pq

from logpipe.prediction.runs import PredictionMeta, PredictionsError
from logpipe.types import OBJECT_TYPES, NDArrayBool, NDArrayFloat, NDArrayInt, SceneSample

_IDS = ("log_id", "sample_id", "track_id")


@dataclass(frozen=True)
class SampleForecast:
    """One sample's forecasts, the unit tables are built from.

    Attributes:
        log_id: the sample's log.
        sample_id: the sample-index id.
        track_ids: (N,) predicted targets.
        object_types: (N,) their normalised classes.
        futures: (N, K, T, 2) metres, world frame.
        scores: (N, K) mode scores, or None for uniform ones (predictors without scores).
        step_ns: (T,) times of the future steps.
        ood: (scores (N,), flags (N,), fallback (N,)) of a predictor that scores targets against its training
            data (``PredictionMeta.out_of_distribution``), else None.
    """

    log_id: str
    sample_id: str
    track_ids: Sequence[str]
    object_types: Sequence[str]
    futures: NDArrayFloat
    scores: NDArrayFloat | None
    step_ns: NDArrayInt
    ood: OodRows | None = None


OodRows = tuple[NDArrayFloat, NDArrayBool, NDArrayBool]
"""Per target: out-of-distribution score, flag, and whether the Kalman fallback replaced the forecast."""


def build_table(meta: PredictionMeta, forecasts: Sequence[SampleForecast]) -> pa.Table:
    """The predictions rows of ``forecasts`` in the table's order, built column-wise (no per-row Python).

    Id columns are plain strings (``schemas/predictions.json``); ``RowGroupWriter`` writes whole row groups, so a
    file does not depend on how its forecasts were batched into tables.

    Raises:
        PredictionsError: a forecast whose shape is not (N, K, T, 2) with the metadata's K and T, step times
            that are not (T,), or an object type outside ``logpipe.types.OBJECT_TYPES``.
    """
    schema = meta.schema()
    k, t = meta.num_modes, meta.pred_len
    done = [f for f in forecasts if len(f.track_ids)]
    for f in done:
        if f.futures.shape != (len(f.track_ids), k, t, 2):
            raise PredictionsError(f"{f.sample_id}: forecasts of shape {f.futures.shape}, expected "
                                   f"({len(f.track_ids)}, {k}, {t}, 2) (targets, K, T, xy)")
        if np.shape(f.step_ns) != (t,):
            raise PredictionsError(f"{f.sample_id}: {np.shape(f.step_ns)} step times, expected ({t},)")
    if not done:
        return schema.empty_table()
    n_targets = np.array([len(f.track_ids) for f in done], np.int64)
    uniform = np.full(k, 1.0 / k)
    type_code = {name: i for i, name in enumerate(OBJECT_TYPES)}
    try:
        type_codes = np.array([type_code[str(c)] for f in done for c in f.object_types], np.int64)
    except KeyError as exc:
        raise PredictionsError(f"object type {exc.args[0]!r} is not one of {list(OBJECT_TYPES)}") from None
    targets = Targets(pa.array([f.log_id for f in done], pa.string()),
                      pa.array([f.sample_id for f in done], pa.string()), np.repeat(np.arange(len(done)), n_targets),
                      pa.array([str(n) for f in done for n in f.track_ids], pa.string()), type_codes)
    table = targets_table(
        meta, targets, np.concatenate([np.asarray(f.futures, np.float64) for f in done]),
        np.concatenate([np.broadcast_to(uniform, (n, k)) if f.scores is None else np.asarray(f.scores)
                        for f, n in zip(done, n_targets, strict=True)]),
        np.concatenate([np.broadcast_to(np.asarray(f.step_ns, np.int64), (n, t))
                        for f, n in zip(done, n_targets, strict=True)]))
    if meta.out_of_distribution is None:
        return table
    return _with_ood(table, schema, done, k)


def _with_ood(table: pa.Table, schema: pa.Schema, done: Sequence[SampleForecast], k: int) -> pa.Table:
    """``table`` with the out-of-distribution columns, each target's values on its K rows (zeros and False for a
    forecast without them)."""
    parts = [f.ood if f.ood is not None else (np.zeros(len(f.track_ids)), np.zeros(len(f.track_ids), bool),
                                              np.zeros(len(f.track_ids), bool)) for f in done]
    columns = {"ood_score": pa.array(np.repeat(np.concatenate([p[0] for p in parts]).astype(np.float32), k)),
               "ood_flag": pa.array(np.repeat(np.concatenate([p[1] for p in parts]).astype(bool), k)),
               "fallback": pa.array(np.repeat(np.concatenate([p[2] for p in parts]).astype(bool), k))}
    arrays = [table.column(f.name) if f.name in table.column_names else columns[f.name] for f in schema]
    return pa.Table.from_arrays(arrays, schema=schema)


@dataclass(frozen=True)
class Targets:
    """Who N forecasts of S samples are for.

    Attributes:
        log_ids, sample_ids: (S,) strings, per sample; ``sample_of``: (N,) each target's sample.
        track_ids: (N,) strings; ``type_codes``: (N,) codes into ``OBJECT_TYPES``.
    """

    log_ids: pa.Array
    sample_ids: pa.Array
    sample_of: NDArrayInt
    track_ids: pa.Array
    type_codes: NDArrayInt


def targets_table(meta: PredictionMeta, targets: Targets, futures: NDArrayFloat, scores: NDArrayFloat,
                  step_ns: NDArrayInt) -> pa.Table:
    """The predictions rows of N ``targets``, K rows per target (no per-row or per-sample Python).

    Args:
        futures: (N, K, T, 2) world metres; ``scores``: (N, K); ``step_ns``: (N, T) ns.
    """
    # the contract's columns (``build_table`` adds the out-of-distribution ones of a run that has them)
    schema = meta.schema() if meta.out_of_distribution is None else replace(meta, out_of_distribution=None).schema()
    k, t = meta.num_modes, meta.pred_len
    per_row = np.repeat(np.asarray(targets.sample_of, np.int32), k)
    n = len(targets.type_codes)
    # Ids as plain strings, the other tables' type: an engine joins them with the tracks without a cast.
    columns = {
        "log_id": _strings(targets.log_ids, per_row),
        "sample_id": _strings(targets.sample_ids, per_row),
        "track_id": _strings(targets.track_ids, np.repeat(np.arange(n, dtype=np.int32), k)),
        "object_type": _strings(pa.array(OBJECT_TYPES, pa.string()),
                                np.repeat(np.asarray(targets.type_codes, np.int32), k)),
        "mode": pa.array(np.tile(np.arange(k, dtype=np.int16), n)),
        "score": pa.array(np.asarray(scores, np.float32).reshape(-1)),
        "timestamp_ns": pa.FixedSizeListArray.from_arrays(
            pa.array(np.repeat(np.asarray(step_ns, np.int64), k, axis=0).reshape(-1)), t),
        "x": pa.FixedSizeListArray.from_arrays(pa.array(np.ascontiguousarray(futures[..., 0]).reshape(-1)), t),
        "y": pa.FixedSizeListArray.from_arrays(pa.array(np.ascontiguousarray(futures[..., 1]).reshape(-1)), t),
    }
    return pa.Table.from_arrays([columns[f.name] for f in schema], schema=schema)


def _strings(values: pa.Array, codes: np.ndarray) -> pa.Array:
    """``values[codes]`` as a plain string array."""
    return values.cast(pa.string()).take(pa.array(codes))


def samples_table(meta: PredictionMeta, samples: Sequence[SceneSample], forecasts: Sequence[NDArrayFloat], *,
                  sample_log: dict[str, str] | None = None) -> pa.Table:
    """The predictions table for ``Predictor.predict`` outputs on ``samples`` (uniform scores).

    ``logpipe predict`` is the normal producer; this serves tests and the reproduction scripts. Step times are
    the window's own; ``sample_log`` maps sample id to log id (default: the id before its last ``:``).

    Raises:
        PredictionsError: a forecast array that does not match its sample's targets, K or T.
    """
    out = []
    for s, f in zip(samples, forecasts, strict=True):
        idx = np.flatnonzero(s.target_mask)
        futures = np.asarray(f, np.float64)
        if futures.shape[0] != len(idx):
            raise PredictionsError(f"{s.sample_id}: {futures.shape[0]} forecasts for {len(idx)} targets")
        log = sample_log[s.sample_id] if sample_log else s.sample_id.rsplit(":", 1)[0]
        out.append(SampleForecast(
            log_id=log, sample_id=s.sample_id, track_ids=[s.track_ids[a] for a in idx],
            object_types=[OBJECT_TYPES[int(s.object_types[a])] for a in idx], futures=futures, scores=None,
            step_ns=np.asarray(s.timestamps_ns[s.obs_len : s.obs_len + meta.pred_len], np.int64)))
    return build_table(meta, out)


def row_group_table(table: pa.Table) -> pa.Table:
    """``table`` (one row group's rows) with its id columns dictionary-encoded over exactly these rows (distinct
    values numbered in order of first appearance, as ``pyarrow.compute.dictionary_encode`` numbers them): what a
    Parquet writer stores then depends on the rows alone, not on the tables they arrived in."""
    # One chunk per column too: the writer cuts pages at chunk boundaries. String ids need nothing more: the
    # Parquet writer's dictionary pages then depend on the row group's values only.
    columns = [_by_first_appearance(table.column(f.name)).cast(f.type)
               if f.name in _IDS and pa.types.is_dictionary(f.type) else table.column(f.name).combine_chunks()
               for f in table.schema]
    return pa.Table.from_arrays(columns, schema=table.schema)


def _by_first_appearance(column: pa.ChunkedArray) -> pa.DictionaryArray:
    """``column``'s strings as one dictionary array numbered by first appearance; works on the chunks'
    dictionaries and integer codes (no string per row is made)."""
    chunks = [c if pa.types.is_dictionary(c.type) else pc.dictionary_encode(c) for c in column.chunks]
    if not chunks:
        return pc.dictionary_encode(pa.array([], pa.string()))
    offsets = np.cumsum([0] + [len(c.dictionary) for c in chunks])
    distinct = pc.dictionary_encode(pa.concat_arrays([c.dictionary.cast(pa.string()) for c in chunks]))
    merged = distinct.indices.to_numpy()
    codes = np.concatenate([merged[c.indices.to_numpy().astype(np.int64) + off]
                            for c, off in zip(chunks, offsets, strict=False)])
    order = pc.unique(pa.array(codes)).to_numpy()  # distinct codes in order of first appearance
    renumber = np.zeros(len(distinct.dictionary), np.int32)
    renumber[order] = np.arange(len(order), dtype=np.int32)
    return pa.DictionaryArray.from_arrays(renumber[codes], distinct.dictionary.take(pa.array(order)))


class RowGroupWriter:
    """Writes tables of predictions rows into ``parquet`` as row groups of exactly ``rows_per_group`` rows (the
    last one shorter), each normalised by ``row_group_table``: the file depends on the rows alone, however they
    were cut into tables."""

    def __init__(self, parquet: pq.ParquetWriter, rows_per_group: int) -> None:
        self._parquet, self._rows_per_group = parquet, rows_per_group
        self._buffered: list[pa.Table] = []
        self._buffered_rows = 0

    def add(self, table: pa.Table) -> None:
        """Buffer ``table``'s rows; write every row group they complete."""
        if not table.num_rows:
            return
        self._buffered.append(table)
        self._buffered_rows += table.num_rows
        if self._buffered_rows >= self._rows_per_group:
            whole = pa.concat_tables(self._buffered)
            cut = whole.num_rows // self._rows_per_group * self._rows_per_group
            self._write(whole.slice(0, cut))
            rest = whole.slice(cut)
            self._buffered = [rest] if rest.num_rows else []
            self._buffered_rows = rest.num_rows

    def flush(self) -> None:
        """Write the buffered rows as the last (shorter) row group."""
        if self._buffered:
            self._write(pa.concat_tables(self._buffered))
            self._buffered, self._buffered_rows = [], 0

    def _write(self, table: pa.Table) -> None:
        for start in range(0, table.num_rows, self._rows_per_group):
            group = row_group_table(table.slice(start, self._rows_per_group))
            self._parquet.write_table(group, row_group_size=self._rows_per_group)
