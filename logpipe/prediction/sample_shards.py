"""The per-sample predict path, one dataset shard at a time: cut each selected sample (``model_inputs``), forecast
it in batches, hand the results to the shard's writer (``output``). The predictor comes in as a forecast function,
so this core module runs a network without importing it: the stage passes its own model's (or its workers'
results), and worker processes or Ray actors that load the model once pass theirs (``logpipe.model.ray_predict``).

A shard is one picklable job (``SampleShardJob`` → ``predict_sample_shard``) that writes its own uncommitted files,
as the columnar path's (``logpipe.prediction.columnar``) do: wherever it runs, the same job writes the same bytes.
Positions are metres in the log's world frame; times are ns on the log's clock.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pyarrow as pa

from logpipe.dataset.sample_filter import SelectedLogs, SelectedSamples
from logpipe.prediction.columnar import ShardDone, logs_by_shard
from logpipe.prediction.mcap_logs import PredictionMcaps
from logpipe.prediction.model_inputs import SampleCutter, log_windows
from logpipe.prediction.options import PredictSummary
from logpipe.prediction.output import LogOutput, SamplePrediction, ShardWriter, counted_shard_writer
from logpipe.prediction.runs import PredictionMeta, RunShardEntry
from logpipe.storage.io import read_table
from logpipe.types import SampleProtocol, SceneSample

Forecast = Callable[[list[SceneSample]], Sequence[Any]]
"""A batch of samples → one forecast per sample (an array of its targets' K futures), in order."""


@dataclass(frozen=True)
class SampleShardRun:
    """What every shard job of a run shares (picklable).

    Attributes:
        cutter: cuts samples from track windows; ``protocol``: the dataset's; ``modes``: K;
        batch_size: samples per forecast batch; ``meta``: the table metadata; ``out_dir``: the run folder.
        cut_rasters: whether samples are cut with their rasters (the forecast or the MCAPs use them).
    """

    cutter: SampleCutter
    protocol: SampleProtocol
    modes: int
    batch_size: int
    meta: PredictionMeta
    out_dir: Path
    cut_rasters: bool


@dataclass(frozen=True)
class SampleShardJob:
    """One dataset shard's work on the per-sample path (picklable: a worker process or a Ray actor runs it).

    Attributes:
        run: what the run's jobs share; ``path``: the shard file; ``key``: its name in the run manifest;
            ``index``: its number (``part-NNNNN``).
        log_ids: the selected logs it holds, in logs-table order; ``samples``: their selected sample-index rows;
        dt_ns: each of its logs' median step (ns); ``summary``: a zeroed run summary, filled with its counts.
        mcaps: how to write its logs' MCAPs (None: Parquet only).
    """

    run: SampleShardRun
    path: Path
    key: str
    index: int
    log_ids: tuple[str, ...]
    samples: pa.Table
    dt_ns: dict[str, int]
    summary: PredictSummary
    mcaps: PredictionMcaps | None = None


def sample_shard_jobs(run: SampleShardRun, root: Path, pending: Sequence[tuple[int, Path]], logs: SelectedLogs,
                      samples: SelectedSamples, summary: PredictSummary,
                      mcaps: PredictionMcaps | None) -> list[SampleShardJob]:
    """The jobs of the ``pending`` (index, path) shards of the dataset at ``root``, each carrying only its own
    logs' sample rows, steps and MCAP writer."""
    by_shard = logs_by_shard(logs)
    log_dt_ns = logs.column("median_dt_ns")
    jobs = []
    for index, path in pending:
        mine = by_shard.get(path.name, [])
        jobs.append(SampleShardJob(run, path, path.relative_to(root).as_posix(), index, tuple(mine),
                                   samples.table(mine).combine_chunks(), {i: int(log_dt_ns[i]) for i in mine},
                                   summary.zeroed(), mcaps.of_logs(mine) if mcaps is not None else None))
    return jobs


def predict_sample_shard(job: SampleShardJob, forecast: Forecast,
                         progress: Callable[[int], None] | None = None) -> ShardDone:
    """Predict one shard into its own uncommitted files (the Parquet rows and, with ``job.mcaps``, its logs'
    MCAPs) with ``forecast``; ``progress`` is called with the samples each batch finished."""
    summary = job.summary
    entry: RunShardEntry = {"shard": job.key, "logs": len(job.log_ids), "samples": 0, "rows": 0, "file": None}
    if not job.log_ids:
        return ShardDone(entry, {}, summary)
    t0 = time.perf_counter()
    tracks = read_table(job.path)  # a damaged shard is a one-line DatasetError
    summary.io_seconds += time.perf_counter() - t0
    write_mcap = job.mcaps.write if job.mcaps is not None else None
    with counted_shard_writer(job.run.meta, job.run.batch_size, job.run.out_dir, job.index, entry, write_mcap,
                              summary) as sink:
        _predict_logs(job, tracks, forecast, summary, progress, sink)
    return ShardDone(entry, sink.files, summary)


def _predict_logs(job: SampleShardJob, tracks: pa.Table, forecast: Forecast, summary: PredictSummary,
                  progress: Callable[[int], None] | None, sink: ShardWriter) -> None:
    """Predict every selected sample of the shard's logs, handing results to ``sink`` batch by batch and ending
    each log once all its samples are predicted. Batches span logs (Argoverse has one sample per log), so a log is
    finished when a batch has gone past it."""
    pending: list[LogOutput] = []
    batch: list[tuple[LogOutput, dict[str, Any], SceneSample]] = []
    rows = SelectedSamples(job.samples).rows_by_log(job.log_ids)
    for log_id, windows in log_windows(tracks, list(job.log_ids)):
        out = LogOutput(log_id)
        pending.append(out)
        for row in rows[log_id]:
            sample = job.run.cutter.cut(windows, row, job.run.cut_rasters)
            if sample is None:
                summary.samples_without_targets += 1
                if progress:
                    progress(1)
                continue
            out.expected += 1
            batch.append((out, row, sample))
            if len(batch) >= job.run.batch_size:
                run_batch(job, batch, forecast, summary, progress, sink)
                batch = []
                sink.end_finished(pending, out)
                sink.throttle()
        sink.end_finished(pending, out)
    if batch:
        run_batch(job, batch, forecast, summary, progress, sink)
    for out in pending:
        sink.end(out)


def run_batch(job: SampleShardJob, batch: list[tuple[LogOutput, dict[str, Any], SceneSample]], forecast: Forecast,
              summary: PredictSummary, progress: Callable[[int], None] | None, sink: ShardWriter) -> None:
    """Forecast one batch and hand each sample's result to its log (public: the seam ``benchmarks/bench_predict``
    wraps to see every batch the stage forecasts)."""
    import torch

    samples = [s for _, _, s in batch]
    t0 = time.perf_counter()
    with torch.inference_mode():
        # Each sample's noise comes from (--seed, sample id) and a network's arithmetic from batch-shape invariant
        # kernels (logpipe.model.row_blocks): batching and resuming change no bit of a forecast.
        futures = forecast(samples)
    summary.model_seconds += time.perf_counter() - t0
    by_log: dict[str, tuple[LogOutput, list[SamplePrediction]]] = {}
    for (out, row, sample), future in zip(batch, futures, strict=True):
        prediction, unobserved = SamplePrediction.of(row, sample, future, job.run.protocol, job.run.modes,
                                                     job.dt_ns[out.log_id])
        by_log.setdefault(out.log_id, (out, []))[1].append(prediction)
        out.finished += 1
        summary.targets_unobserved += unobserved
        summary.targets += len(prediction.targets)
    for out, predictions in by_log.values():  # batch order is log order
        sink.add(out, predictions)
    summary.samples += len(batch)
    if progress:
        progress(len(batch))
