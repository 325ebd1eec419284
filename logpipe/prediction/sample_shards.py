"""The per-sample predict path, one dataset shard at a time: cut each selected sample (``model_inputs``), forecast
it in batches, hand the results to the shard's writer (``output``). The predictor comes in as a forecast function,
so this core module runs a network without importing it: the stage passes its own model's (or its workers'
results), and worker processes or Ray actors that load the model once pass theirs (``logpipe.model.ray_predict``).

A shard is one picklable job (``shard_jobs.ShardJob`` of a ``SampleShardRun`` → ``predict_sample_shard``) that writes
its own uncommitted files, as the columnar path's do: wherever it runs, the same job writes the same bytes.
Positions are metres in the log's world frame; times are ns on the log's clock.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pyarrow as pa

from logpipe.dataset.sample_filter import SelectedSamples
from logpipe.prediction.model_inputs import SampleCutter, log_windows
from logpipe.prediction.options import PredictSummary
from logpipe.prediction.output import LogOutput, SamplePrediction, ShardWriter, counted_shard_writer
from logpipe.prediction.runs import PredictionMeta
from logpipe.prediction.shard_jobs import ShardDone, ShardJob
from logpipe.prediction.table import OodRows
from logpipe.types import SampleProtocol, SceneSample

Forecast = Callable[[list[SceneSample]], Sequence[Any]]
OodCheck = Callable[[list[SceneSample], Sequence[Any]], tuple[Sequence[Any], list[OodRows]]]
"""(samples, their forecasts) → (the forecasts to write, each sample's out-of-distribution rows)."""
"""A batch of samples → one forecast per sample (an array of its targets' K futures), in order."""


@dataclass(frozen=True)
class SampleShardRun:
    """What every shard job of a run shares (picklable).

    Attributes:
        cutter: cuts samples from track windows; ``protocol``: the dataset's; ``modes``: K;
        batch_size: samples per forecast batch; ``meta``: the table metadata; ``out_dir``: the run folder.
        cut_rasters: whether samples are cut with their rasters (the forecast or the MCAPs use them).
        ood_check: scores each batch's targets against the predictor's training data and applies
            ``--out-of-distribution`` to the forecasts (``model.residual.ood.OodCheck``); None: no check.
    """

    cutter: SampleCutter
    protocol: SampleProtocol
    modes: int
    batch_size: int
    meta: PredictionMeta
    out_dir: Path
    cut_rasters: bool
    ood_check: OodCheck | None = None


def predict_sample_shard(job: ShardJob[SampleShardRun], forecast: Forecast,
                         progress: Callable[[int], None] | None = None) -> ShardDone:
    """Predict one shard into its own uncommitted files (the Parquet rows and, with ``job.mcaps``, its logs'
    MCAPs) with ``forecast``; ``progress`` is called with the samples each batch finished."""
    summary = job.summary
    entry, tracks = job.start()
    if tracks is None:
        return ShardDone(entry, {}, summary)
    write_mcap = job.mcaps.write if job.mcaps is not None else None
    with counted_shard_writer(job.run.meta, job.run.batch_size, job.run.out_dir, job.index, entry, write_mcap,
                              summary) as sink:
        _predict_logs(job, tracks, forecast, summary, progress, sink)
    return ShardDone(entry, sink.files, summary)


def _predict_logs(job: ShardJob[SampleShardRun], tracks: pa.Table, forecast: Forecast, summary: PredictSummary,
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


def run_batch(job: ShardJob[SampleShardRun], batch: list[tuple[LogOutput, dict[str, Any], SceneSample]],
              forecast: Forecast, summary: PredictSummary, progress: Callable[[int], None] | None,
              sink: ShardWriter) -> None:
    """Forecast one batch and hand each sample's result to its log (public: the seam ``benchmarks/bench_predict``
    wraps to see every batch the stage forecasts)."""
    samples = [s for _, _, s in batch]
    t0 = time.perf_counter()
    # Each sample's noise comes from (--seed, sample id) and a network's arithmetic from batch-shape invariant
    # kernels (logpipe.model.training.row_blocks): batching and resuming change no bit of a forecast.
    futures = forecast(samples)
    summary.model_seconds += time.perf_counter() - t0
    oods: list[OodRows | None] = [None] * len(samples)
    if job.run.ood_check is not None:
        futures, checked = job.run.ood_check(samples, futures)
        oods = list(checked)
        summary.targets_out_of_distribution += sum(int(o[1].sum()) for o in checked)
        summary.targets_fallback += sum(int(o[2].sum()) for o in checked)
    by_log: dict[str, tuple[LogOutput, list[SamplePrediction]]] = {}
    for (out, row, sample), future, ood in zip(batch, futures, oods, strict=True):
        prediction, unobserved = SamplePrediction.of(row, sample, future, job.run.protocol, job.run.modes,
                                                     job.dt_ns[out.log_id], ood)
        by_log.setdefault(out.log_id, (out, []))[1].append(prediction)
        out.finished += 1
        summary.targets_unobserved += unobserved
        summary.targets += len(prediction.targets)
    for out, predictions in by_log.values():  # batch order is log order
        sink.add(out, predictions)
    summary.samples += len(batch)
    if progress:
        progress(len(batch))
