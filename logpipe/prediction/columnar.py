"""The columnar predict path, for predictors that forecast each target from its own observed track alone
(``TrackPredictor``: constant velocity): a shard's samples are cut (``logpipe.dataset.target_tracks``), forecast
and turned into predictions rows as whole arrays, a few thousand samples at a time, with no per-sample Python.
A shard is one picklable job (``ShardJob`` → ``predict_shard``) that writes its own uncommitted files, so shards run
in parallel processes or as Ray tasks and the stage commits them in order.

It writes the rows the per-sample path writes, in the same order (tested byte for byte): samples in the order
given, targets in window order, targets unobserved at the current step left out and counted.

Positions are metres in the log's world frame; times are ns on the log's clock.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol, cast

import numpy as np
import pyarrow as pa

from logpipe.dataset.sample_filter import SelectedSamples
from logpipe.dataset.target_tracks import ShardTracks
from logpipe.prediction.options import PredictSummary
from logpipe.prediction.output import ShardWriter, counted_shard_writer
from logpipe.prediction.runs import PredictionMeta, RunShardEntry
from logpipe.prediction.table import Targets, targets_table
from logpipe.storage.artifact import FileEntry
from logpipe.storage.io import read_table
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


@dataclass(frozen=True)
class ColumnarRun:
    """What every shard job of a run shares: the predictor, the run folder, the table metadata and the target
    classes kept (empty: all)."""

    predictor: TrackPredictor
    out_dir: Path
    meta: PredictionMeta
    object_types: tuple[str, ...]


@dataclass(frozen=True)
class ShardJob:
    """One dataset shard's work on the columnar path (picklable: a process-pool or Ray task).

    Attributes:
        run: what the run's jobs share; ``path``: the shard file; ``key``: its name in the run manifest;
            ``index``: its number (``part-NNNNN``).
        logs: how many selected logs it holds; ``samples``: their selected sample-index rows, in output order;
            ``dt_ns``: (S,) each sample's log median step (ns).
        summary: a zeroed run summary, filled with this shard's counts.
    """

    run: ColumnarRun
    path: Path
    key: str
    index: int
    logs: int
    samples: pa.Table
    dt_ns: NDArrayInt
    summary: PredictSummary


def shard_jobs(run: ColumnarRun, root: Path, pending: Sequence[tuple[int, Path]],
               logs: Mapping[str, Mapping[str, Any]], samples: SelectedSamples,
               summary: PredictSummary) -> list[ShardJob]:
    """The jobs of the ``pending`` (index, path) shards of the dataset at ``root``, from the selected ``logs``
    (logs-table rows by id, in table order) and ``samples``."""
    by_shard = logs_by_shard(logs)
    jobs = []
    for index, path in pending:
        mine = by_shard.get(path.name, [])
        dt_ns = np.repeat(np.array([int(logs[i]["median_dt_ns"]) for i in mine], np.int64),
                          [samples.count(i) for i in mine])
        # combine_chunks: a job pickles its own rows, not the buffers of the whole selection.
        jobs.append(ShardJob(run, path, path.relative_to(root).as_posix(), index, len(mine),
                             samples.table(mine).combine_chunks(), dt_ns, summary.zeroed()))
    return jobs


def logs_by_shard(logs: Mapping[str, Mapping[str, Any]]) -> dict[str, list[str]]:
    """The ids of ``logs`` (logs-table rows by id) by the file name of their shard, in the rows' order."""
    by_shard: dict[str, list[str]] = {}
    for log_id, row in logs.items():
        by_shard.setdefault(str(row["shard"]).rsplit("/", 1)[-1], []).append(log_id)  # a POSIX path; no Path per log
    return by_shard


@dataclass(frozen=True)
class ShardDone:
    """A predicted shard: its manifest entry, the files to commit with it and its counts."""

    entry: RunShardEntry
    files: dict[str, FileEntry]
    summary: PredictSummary


def predict_shard(job: ShardJob) -> ShardDone:
    """Predict one shard into its own uncommitted files (``prediction.output.shard_writer``; Parquet only)."""
    summary = job.summary
    entry: RunShardEntry = {"shard": job.key, "logs": job.logs, "samples": 0, "rows": 0, "file": None}
    if not job.logs:
        return ShardDone(entry, {}, summary)
    t0 = time.perf_counter()
    tracks = read_table(job.path)  # a damaged shard is a one-line DatasetError
    summary.io_seconds += time.perf_counter() - t0
    with counted_shard_writer(job.run.meta, CHUNK_SAMPLES, job.run.out_dir, job.index, entry, None, summary) as sink:
        chunks = chunk_rows(ShardTracks(tracks), job.samples, job.dt_ns, job.run.predictor, job.run.meta,
                            job.run.object_types)
        write_chunks(chunks, sink, summary, None)
    return ShardDone(entry, sink.files, summary)
