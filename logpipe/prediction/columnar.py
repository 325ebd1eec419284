"""The columnar predict path, for predictors that forecast each target from its own observed track alone
(``TrackPredictor``: constant velocity): a shard's samples are cut (``logpipe.dataset.target_tracks``), forecast
and turned into predictions rows as whole arrays, a few thousand samples at a time, with no per-sample Python.

It writes the rows the per-sample path writes, in the same order (tested byte for byte): samples in the order
given, targets in window order, targets unobserved at the current step left out and counted.

Positions are metres in the log's world frame; times are ns on the log's clock.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from typing import Protocol, cast

import numpy as np
import pyarrow as pa

from logpipe.dataset.target_tracks import ShardTracks
from logpipe.prediction.options import PredictSummary
from logpipe.prediction.output import ShardWriter
from logpipe.prediction.runs import PredictionMeta
from logpipe.prediction.table import Targets, targets_table
from logpipe.types import NDArrayFloat, NDArrayInt

CHUNK_SAMPLES = 4096
"""Samples cut and tabulated at a time (bounds memory: ETH/UCY scenes have ~10 targets a sample)."""


class TrackPredictor(Protocol):
    """A predictor whose forecast of a target depends on that target's observed track only."""

    def predict_tracks(self, observed: NDArrayFloat, num_modes: int) -> NDArrayFloat:
        """(N, K, T_pred, 2) forecasts from (N, T_obs, 2) observed tracks (world metres, NaN where unobserved)."""
        ...


@dataclass
class ChunkRows:
    """The predictions rows of one chunk of samples and what it counted.

    Attributes:
        table: the rows (``logpipe.prediction.runs`` layout).
        samples: samples cut; ``with_targets``: of them, those with a target (predicted, even if every target
            was unobserved at the current step); ``targets``: targets predicted; ``unobserved``: targets left
            out, unobserved at the current step; ``model_seconds``: time in the predictor.
    """

    table: pa.Table
    samples: int
    with_targets: int
    targets: int
    unobserved: int
    model_seconds: float


def chunk_rows(shard: ShardTracks, samples: pa.Table, dt_ns: NDArrayInt, predictor: TrackPredictor,
               meta: PredictionMeta, object_types: tuple[str, ...] = ()) -> Iterator[ChunkRows]:
    """The rows of ``samples`` (sample-index rows of the shard's logs, in output order), ``CHUNK_SAMPLES`` at a
    time; ``dt_ns``: (S,) each sample's log median step (ns)."""
    k, obs_len, pred_len = meta.num_modes, meta.obs_len, meta.pred_len
    for lo in range(0, samples.num_rows, CHUNK_SAMPLES):
        part = samples.slice(lo, CHUNK_SAMPLES)
        cut = shard.targets(part, obs_len, pred_len, dt_ns[lo : lo + CHUNK_SAMPLES], object_types)
        t0 = time.perf_counter()
        futures = np.asarray(predictor.predict_tracks(cut.observed, k), np.float64)[:, :k, :pred_len]
        model_seconds = time.perf_counter() - t0
        ok = np.isfinite(futures).all(axis=(1, 2, 3))
        kept = slice(None) if ok.all() else ok  # a slice keeps views (a predictor's broadcast modes) uncopied
        sample_of = cut.sample_of[kept]
        targets = Targets(part.column("log_id").combine_chunks().cast(pa.string()),
                          part.column("sample_id").combine_chunks().cast(pa.string()), sample_of,
                          pa.array(cut.track_ids[kept], pa.string()), cut.object_types[kept])
        table = targets_table(meta, targets, futures[kept], np.full((len(sample_of), k), 1.0 / k),
                              cut.step_ns[sample_of])
        yield ChunkRows(table, part.num_rows, int((cut.per_sample > 0).sum()), len(sample_of),
                        int((~ok).sum()), model_seconds)


def track_predictor(model: object) -> TrackPredictor | None:
    """``model`` as a ``TrackPredictor`` when it is one (has ``predict_tracks``), else None."""
    return cast(TrackPredictor, model) if hasattr(model, "predict_tracks") else None


def write_chunks(chunks: Iterable[ChunkRows], sink: ShardWriter, summary: PredictSummary,
                 progress: Callable[[int], None] | None) -> None:
    """Hand each chunk's rows to ``sink`` and count them in ``summary`` as the per-sample path counts."""
    for chunk in chunks:
        sink.add_rows(chunk.table, chunk.with_targets)
        summary.model_seconds += chunk.model_seconds
        summary.samples += chunk.with_targets
        summary.samples_without_targets += chunk.samples - chunk.with_targets
        summary.targets += chunk.targets
        summary.targets_unobserved += chunk.unobserved
        if progress:
            progress(chunk.samples)
