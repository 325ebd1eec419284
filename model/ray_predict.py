"""Forecasts on a Ray cluster for ``logpipe predict --backend ray``: Ray Data ``map_batches`` over work items
with a pool of actors, each loading the model once (a GPU per actor where the cluster has GPUs).

This module only moves work and results: what a work item is and how it is forecast come from the caller as
a picklable ``setup`` callable (``logpipe.stages.predict`` builds it from its own windowing code), so the model
layer never imports a stage and the driver keeps writing every output itself through the committed writer.
Actors read their inputs where they lie: paths in work items must name a file system every node shares.

Fault tolerance is Ray Data's: its actor pools restart a dead actor and retry its task (``max_restarts`` and
``max_task_retries`` default to unlimited there); a task's result reaches the driver only once it succeeded,
so a killed actor never leaves a partial or duplicated result.
"""

from __future__ import annotations

import os
import pickle
from collections.abc import Callable, Iterator, Sequence
from typing import Any

import numpy as np

from logpipe.errors import LogpipeError

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
