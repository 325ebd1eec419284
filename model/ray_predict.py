"""Forecasts on a Ray cluster for ``logpipe predict --backend ray``: Ray Data ``map_batches`` over work items
with a pool of actors, each loading the model once (a GPU per actor where the cluster has GPUs).

``ray_forecasts`` gives the stage a forecast function that returns, batch after batch, the actors' forecasts of
exactly the batches the stage's local loop cuts: the actors cut their samples with the run's ``SampleCutter``
(``logpipe.prediction.model_inputs``) from the same batch plan, and the driver checks each batch's sample ids. The
driver keeps writing every output itself through the committed writer; this module only moves work and results, and
imports no stage. ``forecast_on_ray`` is the generic part: any picklable ``setup`` callable and work items. Actors
read their inputs where they lie: paths in work items must name a file system every node shares.

Fault tolerance is Ray Data's: its actor pools restart a dead actor and retry its task (``max_restarts`` and
``max_task_retries`` default to unlimited there); a task's result reaches the driver only once it succeeded,
so a killed actor never leaves a partial or duplicated result.
"""

from __future__ import annotations

import dataclasses
import functools
import os
import pickle
import uuid
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, cast

import numpy as np
import pyarrow as pa

from logpipe.dataset.reader import Dataset
from logpipe.dataset.sample_filter import SelectedSamples
from logpipe.errors import LogpipeError
from logpipe.executor import run_ordered
from logpipe.prediction.model_inputs import SampleCutter, ShardWindows, WorkItem, work_items
from logpipe.prediction.sample_shards import SampleShardRun, predict_sample_shard
from logpipe.prediction.shard_jobs import ShardDone, ShardJob
from logpipe.storage.io import read_table
from logpipe.types import SceneSample

from .registry import ChosenPredictor, load_net
from .training.device import resolve_device

Forecast = Callable[[Any], Any]
"""A work item (unpickled) → its picklable result; built once per actor by the ``setup`` callable."""

KILL_ONCE_ENV = "LOGPIPE_RAY_KILL_ONCE"
"""Test hook: a file path; the first actor to create that file ends its process (``os._exit(1)``) at its first
work item, so tests can check that Ray retries it without duplicate or partial output."""


def start(workers: int, cpus: int = 1) -> tuple[int, bool]:
    """Connect to Ray (``RAY_ADDRESS`` when set, else a local instance with ``workers`` CPUs) unless the caller
    already did; returns (actors to start, whether each gets a GPU).

    Actors: ``workers`` when given, else one per GPU on a cluster with GPUs, else one per ``cpus`` CPUs.

    Raises:
        LogpipeError: Ray Data is not installed.
    """
    try:
        import ray
        import ray.data  # Ray without its ``data`` extra lacks what the actor pool needs
    except ImportError as exc:
        raise LogpipeError("--backend ray needs Ray Data: pip install 'logpipe[ray]'") from exc
    if not ray.is_initialized():
        address = os.environ.get("RAY_ADDRESS")
        if address:
            ray.init(address=address)
        else:
            ray.init(num_cpus=workers or None, include_dashboard=False)
    resources: dict[str, float] = ray.cluster_resources()  # type: ignore[no-untyped-call]
    gpus = int(resources.get("GPU", 0))
    size = workers or gpus or int(resources.get("CPU", 1)) // cpus
    return max(size, 1), gpus > 0


class _Forecaster:
    """The actor: ``setup()`` once (loads the model), then one work item per call."""

    def __init__(self, setup: Callable[[], Forecast], kill_once: str | None) -> None:
        self._forecast = setup()
        self._kill_once = kill_once

    def __call__(self, batch: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        if self._kill_once is not None:
            marker, self._kill_once = self._kill_once, None
            try:
                os.close(os.open(marker, os.O_CREAT | os.O_EXCL | os.O_WRONLY))
            except FileExistsError:
                pass  # another actor (or this one before a restart) already died for the test
            else:
                os._exit(1)
        # Results travel pickled: forecasts are ragged arrays (targets x K x T x 2) Arrow cannot hold as one column.
        # Only bytes this job pickled itself, in memory through Ray's object store, are unpickled: never a file.
        results = [pickle.dumps(self._forecast(pickle.loads(item)), protocol=pickle.HIGHEST_PROTOCOL)
                   for item in batch["item"]]
        return {"index": batch["index"], "result": np.array(results, dtype=object)}


def forecast_on_ray(setup: Callable[[], Forecast], items: Sequence[Any], *, size: int, gpu: bool,
                    cpus: int = 1) -> Iterator[Any]:
    """Yield each item's forecast, in item order, computed on a pool of ``size`` actors of ``cpus`` CPUs (and one
    GPU each if ``gpu``).

    Call ``start`` first. Each item is its own Ray Data block and batch, so one slow item holds up only its actor.
    """
    import ray.data

    if not items:
        return
    context = ray.data.DataContext.get_current()
    bars = context.enable_progress_bars
    context.enable_progress_bars = False  # the CLI draws its own progress; Ray's bars would garble it
    try:
        rows = [{"index": i, "item": pickle.dumps(item, protocol=pickle.HIGHEST_PROTOCOL)}
                for i, item in enumerate(items)]
        dataset = ray.data.from_items(rows, override_num_blocks=len(rows)).map_batches(
            _Forecaster, fn_constructor_args=(setup, os.environ.get(KILL_ONCE_ENV)), batch_size=1,
            compute=ray.data.ActorPoolStrategy(size=min(size, len(rows))),
            num_cpus=cpus, num_gpus=1 if gpu else 0,
        )
        # Rows may finish out of order; hold early ones until their turn (the caller writes in item order).
        waiting: dict[int, bytes] = {}
        following = 0
        for row in dataset.iter_rows():
            waiting[int(row["index"])] = row["result"]
            while following in waiting:
                yield pickle.loads(waiting.pop(following))
                following += 1
        if following != len(rows):
            raise LogpipeError(f"Ray returned {following} of {len(rows)} forecast items")
    finally:
        context.enable_progress_bars = bars


# ---------------------------------------------------------------------------------------------------------
# predict's batches on the actors.

_ITEMS_PER_ACTOR = 4
"""Work items per actor: enough to even out uneven items, few enough that each amortises its shard read."""


@dataclass(frozen=True)
class ForecastJob:
    """What every actor needs to cut and forecast its work items (pickled to each actor).

    Attributes:
        dataset: the dataset predicted; ``chosen``: the predictor (its model is loaded on each actor).
        modes: K; ``seed``: the run's seed (each sample's noise comes from it and the sample id).
        batch_size: samples per batch; ``cutter``: cuts samples from track windows, as the stage does.
    """

    dataset: Dataset
    chosen: ChosenPredictor
    modes: int
    seed: int
    batch_size: int
    cutter: SampleCutter
    ranked: bool = False
    """Forecast every mode head by score (``ResidualPredictor.predict_ranked``): the run's out-of-distribution
    check chooses the K modes."""

    def forecast(self) -> Forecast:
        """The loaded model's forecast of a batch: K modes (or with ``ranked`` every head), noise from the run's
        seed and each sample's id."""
        assert self.chosen.model is not None, "load_net first"
        if self.ranked:
            return cast(Forecast, self.chosen.model.predict_ranked)  # type: ignore[attr-defined]
        return functools.partial(self.chosen.model.predict, num_modes=self.modes, seed=self.seed)


def ray_forecasts(job: ForecastJob, log_ids: list[str], samples: SelectedSamples,
                  pending: list[Path], workers: int, threads: int,
                  device: str) -> Callable[[list[SceneSample]], Sequence[Any]]:
    """The forecast function of ``--backend ray``: returns, batch after batch, the actors' forecasts of the
    batches the stage will cut from the ``pending`` shards (checked by sample id).

    Args:
        job: the run's fixed inputs.
        log_ids: the selected logs in logs-table order (the order the stage cuts batches in).
        samples: the selected sample-index rows.
        pending: the dataset shards still to predict, in the stage's order.
        workers: actors (0: one per GPU, else per ``threads`` CPUs); ``threads``: torch threads per actor (0: 1).
        device: ``--device`` (each actor resolves it).

    Raises:
        LogpipeError: Ray Data is missing, or (when called) Ray returned another batch than the one asked for.
    """
    # Each actor runs torch on ``--threads`` threads (default 1) and reserves as many CPUs. The network's float32
    # reductions round by thread count, so outputs match a local run's bytes at the same --threads (tested).
    threads = threads or 1
    size, gpu = start(workers, threads)
    items, setup = _planned_items(job, log_ids, samples, pending, size, threads, device)
    return _checked(batch for item in forecast_on_ray(setup, items, size=size, gpu=gpu, cpus=threads)
                    for batch in item)


def process_forecasts(job: ForecastJob, log_ids: list[str], samples: SelectedSamples,
                      pending: list[Path], workers: int, threads: int,
                      device: str) -> Callable[[list[SceneSample]], Sequence[Any]]:
    """``ray_forecasts`` on ``workers`` local processes instead of Ray actors (``logpipe.executor.run_ordered``):
    each loads the model once and forecasts runs of planned batches on ``threads`` torch threads (0: 1), while
    the stage cuts its own copy of the samples and writes the outputs. The same work items and the same bytes."""
    threads = threads or 1
    items, setup = _planned_items(job, log_ids, samples, pending, workers, threads, device)
    token = uuid.uuid4().hex  # names this run's model in a worker that outlives one item

    return _checked(batch for item in _in_processes([(token, setup, item) for item in items], workers)
                    for batch in item)


SHARDS_PER_WORKER = 2
"""Shards with selected logs per worker from which each worker predicts whole shards (cuts, forecasts and writes
their files, ``shard_predictions``) rather than forecasting batches the stage cuts and writes."""


def shard_predictions(job: ForecastJob, jobs: list[ShardJob[SampleShardRun]], workers: int, threads: int, device: str,
                      ray: bool) -> Iterator[ShardDone] | None:
    """Each of ``jobs`` predicted by a worker that loaded the model once (``ray``: Ray actors, else ``workers``
    local processes of ``threads`` torch threads, 0: 1), in job order; None when the jobs with logs are fewer than
    ``SHARDS_PER_WORKER`` per worker (too few to keep every worker busy: forecast batches instead).

    Each job carries only its own samples' rasters. The workers write uncommitted files in the run folder, so on a
    cluster it must lie on a file system every node shares, as the dataset must.
    """
    threads = threads or 1
    size, gpu = start(workers, threads) if ray else (workers, False)
    if sum(1 for j in jobs if j.log_ids) < SHARDS_PER_WORKER * size:
        return None
    # Each worker forecasts what it cuts, so it cuts with the rasters, of its own samples only.
    shipped = [dataclasses.replace(j, run=dataclasses.replace(
        j.run, cutter=j.run.cutter.for_samples(j.samples.column("sample_id").combine_chunks()), cut_rasters=True))
        for j in jobs]
    setup = functools.partial(_shard_actor, dataclasses.replace(job, dataset=job.dataset.without_inputs(),
                                                                cutter=SampleCutter(job.cutter.obs_len)),
                              threads, device)
    if ray:
        return forecast_on_ray(setup, shipped, size=size, gpu=gpu, cpus=threads)
    token = uuid.uuid4().hex
    return _in_processes([(token, setup, j) for j in shipped], workers)


def _in_processes(work: list[tuple[str, Callable[[], Forecast], Any]], workers: int) -> Iterator[Any]:
    """``_forecast_in_process`` over ``work`` in ``workers`` processes, dropping this process's model after."""
    try:
        yield from run_ordered(_forecast_in_process, work, workers=workers)
    finally:
        _PROCESS_FORECAST.clear()  # a single item runs in this process: do not keep its model


def _shard_actor(job: ForecastJob, threads: int, device: str) -> Callable[[ShardJob[SampleShardRun]], ShardDone]:
    """Runs once in each worker: loads the model on ``threads`` torch threads; returns the prediction of a shard
    job (``logpipe.prediction.sample_shards``)."""
    return functools.partial(predict_sample_shard, forecast=_loaded_forecast(job, threads, device))


def _loaded_forecast(job: ForecastJob, threads: int, device: str) -> Forecast:
    """The job's forecast, its model loaded in this worker (on ``device`` when a checkpoint), torch on ``threads``
    threads."""
    import torch

    load_net(job.chosen, job.dataset, job.batch_size,
             resolve_device(device) if job.chosen.checkpoint is not None else "cpu")
    torch.set_num_threads(threads)
    return job.forecast()


_PROCESS_FORECAST: dict[str, Forecast] = {}
"""The model a local worker process loaded, by run token: loaded at its first item, reused for the rest."""


def _forecast_in_process(work: tuple[str, Callable[[], Forecast], WorkItem]) -> Any:
    """One work item of ``process_forecasts``, in a worker process."""
    token, setup, item = work
    if token not in _PROCESS_FORECAST:
        _PROCESS_FORECAST.clear()  # another run's model
        _PROCESS_FORECAST[token] = setup()
    return _PROCESS_FORECAST[token](item)


def _planned_items(job: ForecastJob, log_ids: list[str], samples: SelectedSamples, pending: list[Path],
                   size: int, threads: int, device: str) -> tuple[list[WorkItem], Callable[[], Forecast]]:
    """The work items of the ``pending`` shards (batches planned as the stage will cut them, ~``_ITEMS_PER_ACTOR``
    per worker of ``size``) and each worker's set-up (picklable)."""
    planned = [(path, job.cutter.plan_batches(read_table(path), log_ids, samples, job.batch_size))
               for path in pending]
    items = work_items(planned, _ITEMS_PER_ACTOR * size)
    ids = pa.array([row["sample_id"] for _, batches in planned for batch in batches for _, row in batch], pa.string())
    worker_job = dataclasses.replace(job, dataset=job.dataset.without_inputs(), cutter=job.cutter.for_samples(ids))
    return items, functools.partial(_actor, worker_job, threads, device)


def _checked(results: Iterator[tuple[list[str], list[Any]]]) -> Callable[[list[SceneSample]], Sequence[Any]]:
    """The stage's forecast function over ``results`` (sample ids and forecasts per batch, in the stage's order)."""

    def forecast(samples: list[SceneSample]) -> Sequence[Any]:
        ids, futures = next(results)
        if ids != [s.sample_id for s in samples]:
            raise LogpipeError(f"the workers returned forecasts of samples {ids[:3]}... for a batch of "
                               f"{[s.sample_id for s in samples][:3]}... (they cut other batches)")
        return futures

    return forecast


def _actor(job: ForecastJob, threads: int, device: str) -> Callable[[WorkItem], list[tuple[list[str], list[Any]]]]:
    """Runs once in each Ray actor or forecast process: loads the model, sets ``threads`` torch threads; returns
    the forecast of a work item (sample ids and forecasts per batch), reading its shard from the shared file system
    (the last one read is kept)."""
    forecast_batch = _loaded_forecast(job, threads, device)
    shard = ShardWindows()

    def forecast(item: WorkItem) -> list[tuple[list[str], list[Any]]]:
        out = []
        for samples in job.cutter.cut_planned(shard, *item):
            futures = forecast_batch(samples)
            out.append(([s.sample_id for s in samples], [np.asarray(f) for f in futures]))
        return out

    return forecast
