"""Building the predictions table (``logpipe.prediction.runs``: its layout and metadata) from forecasts, column-wise.

Positions are metres in the log's world frame; times are ns on the log's clock.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import pyarrow as pa

from logpipe.prediction.runs import PredictionMeta, PredictionsError
from logpipe.types import OBJECT_TYPES, NDArrayFloat, NDArrayInt, SceneSample

_IDS = ("log_id", "sample_id", "track_id")
_DICT = pa.dictionary(pa.int32(), pa.string())


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
    """

    log_id: str
    sample_id: str
    track_ids: Sequence[str]
    object_types: Sequence[str]
    futures: NDArrayFloat
    scores: NDArrayFloat | None
    step_ns: NDArrayInt


def build_table(meta: PredictionMeta, forecasts: Sequence[SampleForecast]) -> pa.Table:
    """The predictions rows of ``forecasts`` in the table's order, built column-wise (no per-row Python).

    The id columns get one dictionary per sample (the sample's own targets): a writer that cuts row groups at
    fixed row counts then writes the same file however the forecasts were batched into tables.

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
    n_targets = [len(f.track_ids) for f in done]
    futures = np.concatenate([np.asarray(f.futures, np.float64) for f in done])  # (agents, K, T, 2)
    step_ns = np.concatenate([np.broadcast_to(np.asarray(f.step_ns, np.int64), (n * k, t))
                              for f, n in zip(done, n_targets, strict=True)])
    uniform = np.full(k, 1.0 / k)
    scores = np.concatenate([(np.broadcast_to(uniform, (n, k)) if f.scores is None else np.asarray(f.scores))
                             .reshape(-1) for f, n in zip(done, n_targets, strict=True)])
    type_code = {name: i for i, name in enumerate(OBJECT_TYPES)}
    try:
        type_codes = np.repeat(np.array([type_code[str(c)] for f in done for c in f.object_types], np.int32), k)
    except KeyError as exc:
        raise PredictionsError(f"object type {exc.args[0]!r} is not one of {list(OBJECT_TYPES)}") from None
    ids = _sample_dictionaries(done, n_targets, k)
    columns = {
        **ids,
        "object_type": pa.DictionaryArray.from_arrays(pa.array(type_codes), pa.array(OBJECT_TYPES, pa.string())),
        "mode": pa.array(np.tile(np.arange(k, dtype=np.int16), len(type_codes) // k)),
        "score": pa.array(scores.astype(np.float32)),
        "timestamp_ns": pa.FixedSizeListArray.from_arrays(pa.array(step_ns.reshape(-1)), t),
        "x": pa.FixedSizeListArray.from_arrays(pa.array(np.ascontiguousarray(futures[..., 0]).reshape(-1)), t),
        "y": pa.FixedSizeListArray.from_arrays(pa.array(np.ascontiguousarray(futures[..., 1]).reshape(-1)), t),
    }
    return pa.Table.from_arrays([columns[f.name] for f in schema], schema=schema)


def _sample_dictionaries(done: Sequence[SampleForecast], n_targets: Sequence[int],
                         k: int) -> dict[str, pa.ChunkedArray]:
    """``log_id``, ``sample_id``, ``track_id`` as one dictionary-encoded chunk per sample: the sample's log, its
    id, its targets in order. Chunks cut anywhere keep these dictionaries, so what a Parquet writer stores does
    not depend on which forecasts shared a table (it writes a chunk's dictionary as given)."""
    logs = pa.array([f.log_id for f in done], pa.string())
    samples = pa.array([f.sample_id for f in done], pa.string())
    tracks = pa.array([str(n) for f in done for n in f.track_ids], pa.string())
    starts = np.concatenate([[0], np.cumsum(n_targets)]).tolist()
    longest = max(n_targets)
    zeros = pa.array(np.zeros(longest * k, np.int32))
    local = pa.array(np.repeat(np.arange(longest, dtype=np.int32), k))
    out: dict[str, list[pa.Array]] = {name: [] for name in _IDS}
    for i, n in enumerate(n_targets):
        same = zeros.slice(0, n * k)
        out["log_id"].append(pa.DictionaryArray.from_arrays(same, logs.slice(i, 1)))
        out["sample_id"].append(pa.DictionaryArray.from_arrays(same, samples.slice(i, 1)))
        out["track_id"].append(pa.DictionaryArray.from_arrays(local.slice(0, n * k), tracks.slice(starts[i], n)))
    return {name: pa.chunked_array(chunks, _DICT) for name, chunks in out.items()}


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
