"""The training loop the social baselines share: random batches of whole windows, a validation every few steps,
``best/`` (lowest validation ADE) and ``last/`` checkpoints, ``train_log.jsonl``, and a stop when validation has not
improved for a while. What a step does (one optimiser update, or a GAN's discriminator and generator updates) and
how a checkpoint is written are the family's (``step``, ``validate``, ``save``).

A run starts afresh (no resume): these baselines train in minutes to hours on 2 cores and their runs are repeated
whole by ``make``.
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from logpipe.types import NDArrayFloat

from .social_batch import SocialBatch, stack

NextBatch = Callable[[], SocialBatch]


@dataclass(frozen=True)
class LoopSettings:
    """How long and how a run trains.

    Attributes:
        steps: iterations at most (an iteration is the family's ``step``).
        batch_size: windows per batch (each window with all its agents).
        val_every: iterations between validations.
        patience: validations without a better ADE before stopping (0: never stop early).
        seed: seeds torch and the batch order.
        time_budget_s: stop (validating and saving) at the first validation after this many seconds (0: none),
            for a run that must fit a machine's time; its log says how far it got.
    """

    steps: int
    batch_size: int
    val_every: int
    patience: int
    seed: int
    time_budget_s: float = 0.0


@dataclass(frozen=True)
class LoopResult:
    """What a run did: iterations, the best validation and its step, where the checkpoints are, the time."""

    steps: int
    best_step: int
    best_metrics: dict[str, float]
    stopped_early: bool
    best_checkpoint: Path | None
    last_checkpoint: Path
    seconds: float
    windows_per_s: float


def batches(tracks: Sequence[NDArrayFloat], batch_size: int, rng: np.random.Generator) -> NextBatch:
    """A source of batches: windows drawn in a fresh random order each pass over ``tracks``."""
    order: list[int] = []

    def next_batch() -> SocialBatch:
        chosen: list[int] = []
        while len(chosen) < min(batch_size, len(tracks)):
            if not order:
                order.extend(rng.permutation(len(tracks)).tolist())
            chosen.append(order.pop())
        return stack([tracks[i] for i in chosen])

    return next_batch


def run_loop(
    tracks: Sequence[NDArrayFloat], settings: LoopSettings, out_dir: Path, *,
    step: Callable[[NextBatch], dict[str, float]], validate: Callable[[], dict[str, float]],
    save: Callable[[Path, int, dict[str, float]], None], progress: Callable[[int], None] | None = None,
) -> LoopResult:
    """Train (see the module docstring); validation metrics must hold ``ade`` (lower is better)."""
    torch.manual_seed(settings.seed)
    next_batch = batches(tracks, settings.batch_size, np.random.default_rng(settings.seed))
    log = out_dir / "train_log.jsonl"
    log.unlink(missing_ok=True)
    started = time.perf_counter()
    best_ade, best_step, best_metrics, stale, done = math.inf, 0, dict[str, float](), 0, 0
    last_metrics: dict[str, float] = {}
    losses: list[dict[str, float]] = []
    stopped = False
    for it in range(1, settings.steps + 1):
        losses.append(step(next_batch))
        done = it
        if progress is not None:
            progress(1)
        if it % settings.val_every and it != settings.steps:
            continue
        metrics = last_metrics = validate()
        mean_loss = {k: float(np.mean([d[k] for d in losses])) for k in losses[0]}
        losses = []
        record = {"step": it, "seconds": round(time.perf_counter() - started, 1), **mean_loss,
                  **{f"val_{k}": v for k, v in metrics.items()}}
        with log.open("a", encoding="utf-8") as fh:
            fh.write(json.dumps(record) + "\n")
        if metrics["ade"] < best_ade:
            best_ade, best_step, best_metrics, stale = metrics["ade"], it, metrics, 0
            save(out_dir / "best", it, metrics)
        else:
            stale += 1
        over_time = 0 < settings.time_budget_s <= time.perf_counter() - started
        if over_time or (settings.patience and stale >= settings.patience):
            stopped = True
            break
    seconds = time.perf_counter() - started
    save(out_dir / "last", done, last_metrics)
    return LoopResult(done, best_step, best_metrics, stopped, out_dir / "best" if best_step else None,
                      out_dir / "last", seconds, done * settings.batch_size / max(seconds, 1e-9))
