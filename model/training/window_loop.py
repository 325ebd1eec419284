"""The training loop the social baselines share: random batches of whole windows, a validation every few steps,
``best/`` (lowest validation ADE) and ``last/`` checkpoints, ``train_log.jsonl``, and a stop when validation has not
improved for a while. What a step does (one optimiser update, or a GAN's discriminator and generator updates) and
how a checkpoint is written are the family's (``step``, ``validate``, ``save``).

Every validation rewrites ``last/`` resumable: beside the weights, ``train_state.pt`` keeps the optimisers' states
(``optimizers``), the step, the best validation so far, the validations without progress, the wall time, torch's
random state and the batch source's (its generator and the windows left in this pass). ``logpipe train --resume``
(``restore``) continues from there exactly as the run would have gone on: the same batches, noise and updates
(``tests/model/test_social_resume.py``). A resumed run may change ``steps``, ``time_budget_s`` and ``patience``
(the budget counts each part's own time; ``train_log.jsonl`` goes on with the run's total seconds).
"""

from __future__ import annotations

import io
import json
import math
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from logpipe.errors import LogpipeError
from logpipe.types import NDArrayFloat

from .social_batch import SocialBatch, stack

NextBatch = Callable[[], SocialBatch]
SaveCheckpoint = Callable[[Path, int, dict[str, float], bytes | None], None]
"""``save(folder, step, metrics, train_state)``: write a checkpoint folder, resumable when ``train_state`` is given
(the bytes of ``train_state.pt``)."""


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
    resumed_at_step: int | None = None
    total_seconds: float = 0.0  # every part of a resumed run


class Batches:
    """A source of batches: windows drawn in a fresh random order each pass over ``tracks``; ``state`` and
    ``restore`` carry where it is across a resume."""

    def __init__(self, tracks: Sequence[NDArrayFloat], batch_size: int, rng: np.random.Generator) -> None:
        self.tracks, self.batch_size, self.rng = tracks, batch_size, rng
        self.order: list[int] = []

    def __call__(self) -> SocialBatch:
        chosen: list[int] = []
        while len(chosen) < min(self.batch_size, len(self.tracks)):
            if not self.order:
                self.order.extend(self.rng.permutation(len(self.tracks)).tolist())
            chosen.append(self.order.pop())
        return stack([self.tracks[i] for i in chosen])

    def state(self) -> dict[str, Any]:
        """The generator's state and the windows left in this pass."""
        return {"rng": self.rng.bit_generator.state, "order": list(self.order)}

    def restore(self, state: dict[str, Any]) -> None:
        """Continue from ``state`` (of a source over the same windows)."""
        self.rng.bit_generator.state = state["rng"]
        self.order = [int(i) for i in state["order"]]


def batches(tracks: Sequence[NDArrayFloat], batch_size: int, rng: np.random.Generator) -> Batches:
    """A source of batches (``Batches``)."""
    return Batches(tracks, batch_size, rng)


@dataclass
class _Progress:
    """Where a run is: what ``train_state.pt`` keeps besides the optimisers and the random states."""

    step: int = 0
    best_ade: float = math.inf
    best_step: int = 0
    best_metrics: dict[str, float] | None = None
    stale: int = 0
    earlier_s: float = 0.0  # wall time of the parts before a resume

    def to_dict(self) -> dict[str, Any]:
        return {"step": self.step, "best_ade": self.best_ade, "best_step": self.best_step,
                "best_metrics": self.best_metrics or {}, "stale": self.stale, "elapsed_s": self.earlier_s}


def _train_state(progress: _Progress, elapsed_s: float, optimizers: Mapping[str, torch.optim.Optimizer],
                 source: Batches) -> bytes:
    buffer = io.BytesIO()
    torch.save({**progress.to_dict(), "elapsed_s": progress.earlier_s + elapsed_s, "torch_rng": torch.get_rng_state(),
                "batches": source.state(), "optimizers": {k: o.state_dict() for k, o in optimizers.items()}}, buffer)
    return buffer.getvalue()


def _resume(state: dict[str, Any], optimizers: Mapping[str, torch.optim.Optimizer], source: Batches,
            where: Path) -> _Progress:
    """Put the optimisers, random states and batch source where ``state`` (``train_state.pt``) says."""
    try:
        for name, optimizer in optimizers.items():
            optimizer.load_state_dict(state["optimizers"][name])
        torch.set_rng_state(state["torch_rng"])
        source.restore(state["batches"])
        return _Progress(int(state["step"]), float(state["best_ade"]), int(state["best_step"]),
                         {str(k): float(v) for k, v in state["best_metrics"].items()}, int(state["stale"]),
                         float(state["elapsed_s"]))
    except (KeyError, TypeError, ValueError, RuntimeError) as exc:
        raise LogpipeError(f"{where}: cannot resume: training state does not fit this run: {exc}") from None


def run_loop(  # noqa: PLR0913  the family's hooks, each named
    tracks: Sequence[NDArrayFloat], settings: LoopSettings, out_dir: Path, *,
    step: Callable[[NextBatch], dict[str, float]], validate: Callable[[], dict[str, float]], save: SaveCheckpoint,
    progress: Callable[[int], None] | None = None, optimizers: Mapping[str, torch.optim.Optimizer] | None = None,
    restore: Callable[[Path], dict[str, Any]] | None = None,
) -> LoopResult:
    """Train (see the module docstring); validation metrics must hold ``ade`` (lower is better). ``restore``
    (``--resume``) loads ``out_dir/last``'s weights into the family's networks and returns its training state; a
    run folder that holds a run is refused without it, and with it an empty one starts afresh."""
    torch.manual_seed(settings.seed)
    source = batches(tracks, settings.batch_size, np.random.default_rng(settings.seed))
    optimizers = optimizers or {}
    log, last = out_dir / "train_log.jsonl", out_dir / "last"
    run = _Progress()
    if (last / "meta.json").exists():
        if restore is None:
            raise LogpipeError(f"{out_dir} already holds a run: pass --resume to continue it, or use a new folder")
        run = _resume(restore(last), optimizers, source, last / "train_state.pt")
    else:
        log.unlink(missing_ok=True)
    resumed_at = run.step if run.step else None
    started = time.perf_counter()
    losses: list[dict[str, float]] = []
    stopped = False
    for it in range(run.step + 1, settings.steps + 1):
        losses.append(step(source))
        run.step = it
        if progress is not None:
            progress(1)
        if it % settings.val_every and it != settings.steps:
            continue
        metrics = validate()
        mean_loss = {k: float(np.mean([d[k] for d in losses])) for k in losses[0]}
        losses = []
        record = {"step": it, "seconds": round(run.earlier_s + time.perf_counter() - started, 1), **mean_loss,
                  **{f"val_{k}": v for k, v in metrics.items()}}
        with log.open("a", encoding="utf-8") as fh:
            fh.write(json.dumps(record) + "\n")
        if metrics["ade"] < run.best_ade:
            run.best_ade, run.best_step, run.best_metrics, run.stale = metrics["ade"], it, metrics, 0
            save(out_dir / "best", it, metrics, None)
        else:
            run.stale += 1
        save(last, it, metrics, _train_state(run, time.perf_counter() - started, optimizers, source))
        over_time = 0 < settings.time_budget_s <= time.perf_counter() - started
        if over_time or (settings.patience and run.stale >= settings.patience):
            stopped = True
            break
    seconds = time.perf_counter() - started
    done = run.step - (resumed_at or 0)
    return LoopResult(run.step, run.best_step, run.best_metrics or {}, stopped,
                      out_dir / "best" if run.best_step else None, last, seconds,
                      done * settings.batch_size / max(seconds, 1e-9), resumed_at, run.earlier_s + seconds)
