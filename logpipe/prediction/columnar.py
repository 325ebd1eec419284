"""The columnar predict path, for predictors that forecast each target from its own observed track alone
(``TrackPredictor``: constant velocity): a shard's samples are cut (``logpipe.dataset.target_tracks``), forecast
and turned into predictions rows as whole arrays, a few thousand samples at a time, with no per-sample Python.
With MCAPs (no raster images: those stay on the per-sample path), each log's MCAP takes its samples' messages from
the same chunks, encoded per sample. A shard is one picklable job (``ShardJob`` → ``predict_shard``) that writes its
own uncommitted files, so shards run in parallel processes or as Ray tasks and the stage commits them in order.

It writes the files the per-sample path writes (tested byte for byte): samples in the order given, targets in window
order, targets unobserved at the current step left out and counted, an MCAP for every selected log.

Positions are metres in the log's world frame; times are ns on the log's clock.
"""

from __future__ import annotations

import time
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass
from functools import partial
from pathlib import Path
from typing import Protocol, cast

import numpy as np
import pyarrow as pa

from logpipe.dataset.shards import log_slices
from logpipe.dataset.target_tracks import ShardTracks, TargetTracks
from logpipe.errors import DatasetError
from logpipe.mcap.forecast_scene import TargetForecasts
from logpipe.mcap.merge import NewMessage
from logpipe.prediction.mcap_logs import PredictionMcaps
from logpipe.prediction.options import PredictSummary
from logpipe.prediction.output import ShardWriter, counted_shard_writer
from logpipe.prediction.runs import PredictionMeta
from logpipe.prediction.shard_jobs import ShardDone, ShardJob
from logpipe.prediction.table import Targets, targets_table
from logpipe.types import OBJECT_TYPES, NDArrayBool, NDArrayFloat, NDArrayInt

CHUNK_SAMPLES = 4096
"""Samples cut and tabulated at a time (bounds memory: ETH/UCY scenes have ~10 targets a sample)."""
SCENE_SAMPLES = 64
"""Samples whose scene messages are built at a time (~50 kB each with K = 20)."""


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
    drawn: ChunkForecasts | None = None


@dataclass(frozen=True)
class SampleDrawn:
    """What a sample's MCAP messages are made of (``PredictionMcaps.sample_messages``' arguments).

    Attributes:
        log_id: its log; ``now_ns``: its prediction time; ``step_ns``: (T_pred,) its future steps' times;
        forecasts: its targets and forecasts; ``scene``: its serialized scene update.
    """

    log_id: str
    now_ns: int
    step_ns: NDArrayInt
    forecasts: TargetForecasts
    scene: bytes


@dataclass(frozen=True)
class ChunkForecasts:
    """A chunk's samples and their kept targets' tracks and forecasts, for the MCAP messages of each sample.

    Attributes:
        samples: the chunk's sample-index rows; ``cut``: their targets (with ``truth``); ``kept``: the targets
            forecast (observed at the current step); ``futures``: (N_kept, K, T_pred, 2) their forecasts;
            ``scores``: (N_kept, K) their mode scores (the rows' own).
    """

    samples: pa.Table
    cut: TargetTracks
    kept: NDArrayBool | slice
    futures: NDArrayFloat
    scores: NDArrayFloat

    def of_samples(self, mcaps: PredictionMcaps) -> Iterator[SampleDrawn]:
        """Each sample with a target in its window, in order, as the per-sample path hands it to its MCAP writer;
        scene messages are built ``SCENE_SAMPLES`` samples at a time."""
        cut, kept = self.cut, self.kept
        drawn = np.flatnonzero(cut.per_sample > 0)
        rows = self.samples.take(drawn)
        log_ids = rows.column("log_id").to_pylist()
        sample_ids = rows.column("sample_id").to_pylist()
        now_ns = rows.column("current_ns").to_pylist()
        sample_of = cut.sample_of[kept]
        bounds = np.searchsorted(sample_of, np.append(drawn, self.samples.num_rows)).tolist()
        forecasts = TargetForecasts(
            [str(i) for i in sample_ids], bounds, cut.track_ids[kept].tolist(),
            [OBJECT_TYPES[c] for c in cut.object_types[kept].tolist()], cut.observed[kept],
            cast(NDArrayFloat, cut.truth)[kept], self.futures, self.scores).with_columns()
        for first in range(0, len(drawn), SCENE_SAMPLES):
            stop = min(first + SCENE_SAMPLES, len(drawn))
            part = forecasts.part(first, stop)
            scenes = mcaps.scene_updates(log_ids[first:stop], now_ns[first:stop], part)
            for i, scene in enumerate(scenes):
                s = first + i
                yield SampleDrawn(log_ids[s], now_ns[s], cut.step_ns[drawn[s]], part.part(i, i + 1), scene)


def chunk_rows(shard: ShardTracks, samples: pa.Table, dt_ns: NDArrayInt, predictor: TrackPredictor,
               meta: PredictionMeta, object_types: tuple[str, ...] = (), drawn: bool = False) -> Iterator[ChunkRows]:
    """The rows of ``samples`` (sample-index rows of the shard's logs, in output order), ``CHUNK_SAMPLES`` at a
    time; ``dt_ns``: (S,) each sample's log median step (ns); ``drawn``: also give each chunk's
    ``ChunkForecasts`` (for MCAPs)."""
    k, obs_len, pred_len = meta.num_modes, meta.obs_len, meta.pred_len
    for lo in range(0, samples.num_rows, CHUNK_SAMPLES):
        part = samples.slice(lo, CHUNK_SAMPLES)
        cut = shard.targets(part, obs_len, pred_len, dt_ns[lo : lo + CHUNK_SAMPLES], object_types, drawn)
        t0 = time.perf_counter()
        futures = np.asarray(predictor.predict_tracks(cut.observed, k), np.float64)[:, :k, :pred_len]
        model_seconds = time.perf_counter() - t0
        ok = np.asarray(np.isfinite(futures).all(axis=(1, 2, 3)), bool)
        # A slice keeps views (a predictor's broadcast modes) uncopied.
        kept: NDArrayBool | slice = slice(None) if ok.all() else ok
        sample_of = cut.sample_of[kept]
        targets = Targets(part.column("log_id").combine_chunks().cast(pa.string()),
                          part.column("sample_id").combine_chunks().cast(pa.string()), sample_of,
                          pa.array(cut.track_ids[kept], pa.string()), cut.object_types[kept])
        forecast, scores = futures[kept], np.full((len(sample_of), k), 1.0 / k)
        table = targets_table(meta, targets, forecast, scores, cut.step_ns[sample_of])
        forecasts = ChunkForecasts(part, cut, kept, forecast, scores) if drawn else None
        yield ChunkRows(table, part.num_rows, int((cut.per_sample > 0).sum()), len(sample_of),
                        int((~ok).sum()), model_seconds, forecasts)


def track_predictor(model: object) -> TrackPredictor | None:
    """``model`` as a ``TrackPredictor`` when it is one (has ``predict_tracks``), else None."""
    return cast(TrackPredictor, model) if hasattr(model, "predict_tracks") else None


def handed_chunks(chunks: Iterable[ChunkRows], sink: ShardWriter, summary: PredictSummary) -> Iterator[ChunkRows]:
    """Hand each chunk's rows to ``sink`` and count them in ``summary`` as the per-sample path counts; yields
    each chunk once handed over."""
    for chunk in chunks:
        sink.add_rows(chunk.table, chunk.with_targets)
        summary.model_seconds += chunk.model_seconds
        summary.samples += chunk.with_targets
        summary.samples_without_targets += chunk.samples - chunk.with_targets
        summary.targets += chunk.targets
        summary.targets_unobserved += chunk.unobserved
        yield chunk


def write_mcaps(chunks: Iterator[ChunkRows], sink: ShardWriter, mcaps: PredictionMcaps,
                log_ids: Sequence[str]) -> None:
    """Write the MCAP of each of ``log_ids`` (the shard's logs, in the order of the chunks' samples; a log
    without samples still gets its original copied), its samples' messages drawn from ``chunks`` as the MCAP
    writer takes them, so a chunk's rows and messages are made once and the logs stream."""
    pending = (sample for chunk in chunks for sample in cast(ChunkForecasts, chunk.drawn).of_samples(mcaps))
    producing = 0.0  # time in ``pending`` (cutting, forecasting, rows, scene messages): not the MCAP writer's

    def advance() -> SampleDrawn | None:
        nonlocal producing
        t0 = time.perf_counter()
        sample = next(pending, None)
        producing += time.perf_counter() - t0
        return sample

    head = advance()
    for log_id in log_ids:

        def messages(log_id: str = log_id) -> Iterator[NewMessage]:
            nonlocal head
            while head is not None and head.log_id == log_id:
                yield from mcaps.sample_messages(head.log_id, head.now_ns, head.step_ns, head.forecasts, head.scene)
                head = advance()

        sink.write_log_now(log_id, partial(mcaps.write_messages, log_id, messages()))
    sink.inline_seconds -= producing
    if head is not None:
        raise DatasetError(f"a sample of log {head.log_id!r} follows the logs of its shard (sample-index out of order)")


@dataclass(frozen=True)
class ColumnarRun:
    """What every shard job of a run shares: the predictor, the run folder, the table metadata and the target
    classes kept (empty: all)."""

    predictor: TrackPredictor
    out_dir: Path
    meta: PredictionMeta
    object_types: tuple[str, ...]


def predict_shard(job: ShardJob[ColumnarRun]) -> ShardDone:
    """Predict one shard into its own uncommitted files (``prediction.output.shard_writer``): the Parquet rows
    and, with ``job.mcaps``, each log's MCAP."""
    summary = job.summary
    entry, tracks = job.start(ShardTracks.COLUMNS)
    if tracks is None:
        return ShardDone(entry, {}, summary)
    with counted_shard_writer(job.run.meta, CHUNK_SAMPLES, job.run.out_dir, job.index, entry, None, summary) as sink:
        chunks = handed_chunks(chunk_rows(ShardTracks(tracks), job.samples, _sample_dt_ns(job), job.run.predictor,
                                          job.run.meta, job.run.object_types, drawn=job.mcaps is not None),
                               sink, summary)
        if job.mcaps is not None:
            write_mcaps(chunks, sink, job.mcaps, job.log_ids)
        for _ in chunks:  # the rest (all of them without MCAPs)
            pass
    return ShardDone(entry, sink.files, summary)


def _sample_dt_ns(job: ShardJob[ColumnarRun]) -> NDArrayInt:
    """(S,) each of the job's samples' log median step (ns); its samples come log after log."""
    slices = log_slices(job.samples)
    return np.repeat(np.array([job.dt_ns[i] for i in slices], np.int64), [hi - lo for lo, hi in slices.values()])
