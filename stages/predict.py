"""``logpipe predict``: forecast every prediction sample of a dataset; write the predictions table and, per
log, an MCAP with the original recording plus prediction channels.

Reads top-down: open the dataset and the predictor (a checkpoint, the shipped one for the dataset kind, or a
baseline) → check that they fit (kind, obs/pred lengths, frame rate, agent types, rasters, originals, log ids that
are safe file names) before any work → take the output folder's lock → per dataset shard not yet committed: cut the
selected samples (``logpipe.dataset.sample_filter``, ``logpipe.prediction.model_inputs``), predict in batches (a
network in torch's inference mode), write the shard's Parquet and its logs' MCAPs on a writer thread
(``logpipe.prediction.output``, ``logpipe.prediction.mcap_logs``) → commit the shard by replacing the run manifest.
Each shard is one job of ``logpipe.prediction.sample_shards``. With ``--backend ray`` or local worker processes
(``--workers``), workers that each load the model (``logpipe.model.ray_predict``) run whole shard jobs, writing
their own files, when there are enough shards to share out; else they forecast the batches cut and written here.
Constant velocity to Parquet only takes ``logpipe.prediction.columnar``: a job per shard, ``--workers`` at a time.

Output folder (a committed artifact, ``logpipe.prediction.runs``): ``manifest.json``, ``predictions/part-NNNNN.parquet``
(one per dataset shard, NNNNN = its index) and ``mcap/part-NNNNN/<log_id>.mcap``. Positions are metres in the
log's world frame; times are ns on the log's clock; a sample's prediction time is its current (last observed)
step. Resuming: shards the committed manifest lists with the same settings are skipped; a shard interrupted
midway is redone from scratch, so the rerun of an interrupted run gives the same bytes as an uninterrupted one.
"""

from __future__ import annotations

import contextlib
import dataclasses
import time
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any, cast

from logpipe.dataset.reader import Dataset
from logpipe.dataset.sample_filter import SampleFilter, SelectedLogs, SelectedSamples, selected_samples
from logpipe.dataset.sample_filter import selected_logs as _selected_logs
from logpipe.errors import LogpipeError
from logpipe.executor import Backend, default_workers, run_ordered
from logpipe.model.ray_predict import ForecastJob, process_forecasts, ray_forecasts, shard_predictions
from logpipe.model.registry import check_fit, choose_predictor, load_net, resolve_inference, seen_in_training
from logpipe.model.residual.ood import OodCheck, ood_check_for
from logpipe.model.training.device import check_device_name, resolve_device
from logpipe.prediction.columnar import (
    ColumnarRun,
    TrackPredictor,
    predict_shard,
    track_predictor,
)
from logpipe.prediction.mcap_logs import PredictionMcaps, check_log_ids
from logpipe.prediction.model_inputs import SampleCutter, raster_problems
from logpipe.prediction.options import PredictOptions, PredictSummary, default_modes
from logpipe.prediction.output import fast_gil_switching
from logpipe.prediction.runs import PredictionMeta, PredictionRunWriter, RunSettings, RunShardEntry
from logpipe.prediction.sample_shards import SampleShardRun, predict_sample_shard
from logpipe.prediction.shard_jobs import ShardDone, logs_by_shard, shard_jobs
from logpipe.progress import report_total
from logpipe.raster.runs import find_raster_run
from logpipe.storage.artifact import MANIFEST, FileEntry, output_errors
from logpipe.storage.io import sha256_file


@dataclass
class _Run:
    """Everything fixed for one invocation (shared by the per-shard work): what every forecast needs (``job``, the
    same record the Ray actors get) and what the local writer adds."""

    job: ForecastJob
    logs: SelectedLogs
    samples: SelectedSamples
    meta: PredictionMeta
    mcaps: PredictionMcaps | None  # the per-log MCAP writer (None: --no-mcap)
    ood_check: OodCheck | None = None  # a residual checkpoint's out-of-distribution check


def predict_dataset(dataset_dir: Path, out_dir: Path, options: PredictOptions | None = None, *,
                    progress: Callable[[int], None] | None = None, **fields: Any) -> dict[str, Any]:
    """Predict every selected sample of ``dataset_dir`` into ``out_dir`` (rerunning with the same settings
    resumes); returns the run summary (``PredictSummary.to_dict()``, the ``--json`` output).

    ``options`` (or ``PredictOptions``' fields given by keyword, which override it) says what to predict and how;
    ``progress`` is called with the number of samples each batch finished.

    Raises:
        LogpipeError: a bad option, a checkpoint that does not fit the dataset, missing rasters or originals;
            all raised before any output is written.
    """
    opts = dataclasses.replace(options or PredictOptions(), **fields)
    started = time.perf_counter()
    run, settings, summary, torch_device = _prepare(dataset_dir, out_dir, opts)
    threads = opts.threads if torch_device is not None else None  # None: a baseline, torch never loaded
    with (_torch_threads(threads), output_errors(), PredictionRunWriter(out_dir) as writer,
          fast_gil_switching()):
        shards, files = writer.committed(settings)
        done, root, paths = {s["shard"] for s in shards}, run.job.dataset.root, run.job.dataset.shard_paths
        pending = [(i, p) for i, p in enumerate(paths) if p.relative_to(root).as_posix() not in done]
        summary.shards_skipped_done = len(paths) - len(pending)
        by_shard = logs_by_shard(run.logs)  # progress counts the samples of the shards left to do
        report_total(progress, sum(run.samples.count(i) for _, p in pending for i in by_shard.get(p.name, [])))
        # Constant velocity without raster images: whole arrays, a job per shard (parallel), the same bytes.
        columnar = track_predictor(run.job.chosen.model) if not (run.mcaps and run.mcaps.raster_channels) else None
        processes = opts.forecast_processes(len(run.samples), on_cpu=str(torch_device) == "cpu",
                                            environment_net=run.job.chosen.needs_raster)
        outputs = (_columnar_shards(run, columnar, pending, out_dir, summary, opts, progress) if columnar
                   else _sample_shards(run, pending, out_dir, summary, opts, progress, processes,
                                       torch_device or "cpu"))
        uncommitted = writer.manifest is None
        for entry, new_files in outputs:
            shards.append(entry)
            files.update(new_files)
            uncommitted = not new_files  # one commit per shard with outputs; empty ones ride with the next
            if new_files:
                writer.commit(settings, run.meta, shards, files)
        if uncommitted:
            writer.commit(settings, run.meta, shards, files)
    if summary.targets_out_of_distribution:
        summary.warnings.append(f"{summary.targets_out_of_distribution} of {summary.targets} targets are outside the "
                                f"checkpoint's training data (column ood_flag; --out-of-distribution "
                                f"{opts.out_of_distribution}: {summary.targets_fallback} got the best kinematic "
                                "baseline of its training as mode 0, the model's own modes after it)")
    summary.shards = len(shards)
    summary.rows_total = sum(int(s["rows"]) for s in shards)
    summary.samples_total = sum(int(s["samples"]) for s in shards)
    summary.targets_total = summary.rows_total // run.job.modes
    summary.already_done = not pending
    summary.seconds = time.perf_counter() - started
    return summary.to_dict()


@contextlib.contextmanager
def _torch_threads(threads: int | None) -> Iterator[None]:
    """torch's intra-op threads while a network predicts (``threads``, 0: one per core), restored after; None: a
    baseline, which runs numpy, so torch is not even imported (~1 s of a small run)."""
    if threads is None:
        yield
        return
    import torch

    previous = torch.get_num_threads()
    torch.set_num_threads(threads or default_workers())
    try:
        yield
    finally:
        torch.set_num_threads(previous)


def _prepare(dataset_dir: Path, out_dir: Path, opts: PredictOptions) -> tuple[_Run, RunSettings, PredictSummary, Any]:
    """Open and check everything before any output: the run, its settings, the summary to fill, the torch device
    (None for baselines: numpy, so the value is checked but no device used)."""
    dataset = Dataset.open(dataset_dir)
    sample_filter = opts.sample_filter or SampleFilter()
    chosen = choose_predictor(dataset, opts.checkpoint, opts.predictor, split=sample_filter.split)
    check_device_name(opts.device)
    torch_device = resolve_device(opts.device) if chosen.checkpoint is not None else None
    stored = None if opts.as_trained else chosen.stored_settings
    modes = opts.modes or (stored.num_modes if stored is not None else default_modes(dataset.protocol.name))
    opts.check(modes)
    inference = resolve_inference(chosen, num_modes=modes, noise_scale=opts.noise_scale,
                                  constant_velocity_modes=opts.constant_velocity_modes,
                                  context_max_neighbours=opts.context_max_neighbours, as_trained=opts.as_trained)
    logs_table = _selected_logs(dataset, sample_filter)
    problems = check_fit(dataset, chosen, logs_table)
    warnings = seen_in_training(chosen, logs_table)
    samples = selected_samples(dataset, logs_table, sample_filter)
    # Looked up when used or named: several runs are an error only where the choice matters; a missing named one always.
    rasters = (find_raster_run(dataset_dir, opts.raster_run, chosen.raster_channels if chosen.needs_raster else None)
               if chosen.needs_raster or opts.raster_images or opts.raster_run is not None else None)
    if chosen.needs_raster:
        problems += raster_problems(dataset_dir, rasters, samples, opts.allow_blank_rasters)
    if problems:
        raise LogpipeError(f"{chosen.checkpoint or 'predictor'} does not fit {dataset_dir}: " + "; ".join(problems))
    logs = SelectedLogs(logs_table)
    check_log_ids(dataset.root, logs)
    # Where bags/MCAP inputs are: --inputs, else the roots ingest recorded (manifest "input_roots", if it does).
    roots = list(opts.inputs) or [Path(p) for p in dataset.manifest.get("input_roots", [])]
    manifest_sha = sha256_file(dataset.root / MANIFEST)
    raster_images = rasters is not None and opts.raster_images
    mcaps = PredictionMcaps.of_run(dataset, logs, roots, chosen.name, chosen.checkpoint_id, modes, opts.seed,
                                   rasters.spec.channels if raster_images and rasters is not None else None
                                   ) if opts.write_mcap else None
    settings: RunSettings = {
        "dataset_manifest_sha256": manifest_sha, "predictor": chosen.name, "checkpoint_id": chosen.checkpoint_id,
        "num_modes": modes, "seed": opts.seed, "batch_size": opts.batch_size, "filter": sample_filter.to_dict(),
        "protocol": dataset.protocol.to_dict(), "write_mcap": opts.write_mcap,
        "raster_run": rasters.run_dir.name if rasters is not None and raster_images else None,
    }
    ood_check = (ood_check_for(chosen.checkpoint, opts.out_of_distribution, modes, logs_table)
                 if chosen.name == "residual" and chosen.checkpoint is not None else None)
    if ood_check is not None:
        settings["out_of_distribution"] = opts.out_of_distribution
    protocol = dataset.protocol
    meta = PredictionMeta(
        predictor=chosen.name, checkpoint_id=chosen.checkpoint_id, protocol=protocol.name, obs_len=protocol.obs_len,
        pred_len=protocol.pred_len, num_modes=modes, checkpoint_sha256=chosen.weights_sha256, seed=opts.seed,
        dataset_manifest_sha256=manifest_sha, noise_scale=inference.noise_scale,
        constant_velocity_modes=inference.constant_velocity_modes,
        context_max_neighbours=inference.context_max_neighbours,
        out_of_distribution=opts.out_of_distribution if ood_check is not None else None,
    )
    PredictionRunWriter.refuse_other_folders(out_dir)
    summary = PredictSummary(
        dataset=str(dataset_dir), out=str(out_dir), predictor=chosen.name, checkpoint_id=chosen.checkpoint_id,
        num_modes=modes, seed=opts.seed, checkpoint=str(chosen.checkpoint) if chosen.checkpoint is not None else None,
        raster_run=rasters.run_dir.name if rasters is not None else None,
        inference=inference.summary() if chosen.checkpoint is not None else None, warnings=warnings,
        protocol=protocol.to_dict(), logs_selected=len(logs), samples_selected=len(samples),
        device=None if torch_device is None else str(torch_device), backend=opts.backend,
        predictor_reason=chosen.why,
    )
    raster_ids = frozenset(rasters.index.column("sample_id").to_pylist()) if rasters is not None else frozenset()
    cutter = SampleCutter(protocol.obs_len, sample_filter.object_types, rasters, raster_ids)
    # The job's dataset without the input list (most of a large corpus's manifest): found originals were its use.
    run = _Run(ForecastJob(dataset.without_inputs(), chosen, modes, opts.seed, opts.batch_size, cutter,
                           ranked=ood_check is not None), logs,
               samples, meta, mcaps, ood_check)
    return run, settings, summary, torch_device


# ---------------------------------------------------------------------------------------------------------
# One shard: samples → model → Parquet + MCAPs.


def _columnar_shards(run: _Run, predictor: TrackPredictor, pending: list[tuple[int, Path]], out_dir: Path,
                     summary: PredictSummary, opts: PredictOptions,
                     progress: Callable[[int], None] | None) -> Iterator[tuple[RunShardEntry, dict[str, FileEntry]]]:
    """Predict the ``pending`` shards on the columnar path, ``--workers`` at a time (processes; Ray tasks with
    ``--backend ray``), each into its own uncommitted files; yields entries and files in shard order."""
    shared = ColumnarRun(predictor, out_dir, run.meta, run.job.cutter.object_types)
    jobs = shard_jobs(shared, run.job.dataset.root, pending, run.logs, run.samples, summary, run.mcaps)
    yield from _counted(run_ordered(predict_shard, jobs, workers=opts.workers, backend=cast(Backend, opts.backend)),
                        summary, progress)


def _sample_shards(run: _Run, pending: list[tuple[int, Path]], out_dir: Path, summary: PredictSummary,
                   opts: PredictOptions, progress: Callable[[int], None] | None, processes: int,
                   device: Any) -> Iterator[tuple[RunShardEntry, dict[str, FileEntry]]]:
    """Predict the ``pending`` shards on the per-sample path: here (on ``device``), or by workers (``processes``
    local ones, else with ``--backend ray`` actors) that predict whole shards when there are enough of them, else
    forecast the batches cut here; yields entries and files in shard order."""
    job = run.job
    remote_forecast = processes > 0 or opts.backend == "ray"
    shard_run = SampleShardRun(job.cutter, job.dataset.protocol, job.modes, job.batch_size, run.meta, out_dir,
                               cut_rasters=not remote_forecast or bool(run.mcaps and run.mcaps.raster_channels),
                               ood_check=run.ood_check)
    jobs = shard_jobs(shard_run, job.dataset.root, pending, run.logs, run.samples, summary, run.mcaps)
    if remote_forecast:
        done_remotely = shard_predictions(job, jobs, processes or opts.workers, opts.threads, opts.device,
                                          ray=opts.backend == "ray")
        if done_remotely is not None:
            summary.device = None  # chosen on each actor / process
            yield from _counted(done_remotely, summary, progress)
            return
        # Too few shards to share out: the workers forecast the batches cut here (each loads the model).
        forecast = (process_forecasts if processes else ray_forecasts)(
            job, list(run.logs), run.samples, [j.path for j in jobs if j.log_ids], processes or opts.workers,
            opts.threads, opts.device)
        summary.device = None
    else:
        load_net(job.chosen, job.dataset, job.batch_size, device)
        forecast = job.forecast()
    for shard in jobs:
        done = predict_sample_shard(shard, forecast, progress)
        summary.add(done.summary)
        yield done.entry, done.files


def _counted(done: Iterable[ShardDone], summary: PredictSummary,
             progress: Callable[[int], None] | None) -> Iterator[tuple[RunShardEntry, dict[str, FileEntry]]]:
    """Shards predicted elsewhere (a worker, a Ray task or actor), in order: their counts added to ``summary`` and
    ``progress``; yields each one's entry and files."""
    for shard in done:
        summary.add(shard.summary)
        if progress:
            progress(shard.summary.samples + shard.summary.samples_without_targets)
        yield shard.entry, shard.files
