"""Training the residual driving model: targets cut from samples once (``collect``), then epochs of Adam over
shuffled targets (``fit_residual``), validated every ``val_every`` epochs; ``best/`` is the checkpoint with the
lowest validation score (K = 1 FDE + minFDE@K, metres: both are what the model is judged on), ``last/`` the last.

Each epoch draws at most ``max_targets_per_window`` targets of every window (all with 0), so the crowded windows
of a few recordings do not outweigh the rest. Runs on the CPU with ``num_threads`` torch threads.
"""

from __future__ import annotations

import dataclasses
import json
import math
import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import torch

from logpipe.dataset.locations import locations_of
from logpipe.storage.io import open_nofollow
from logpipe.types import NDArrayFloat, SceneSample

from ..checkpoint.format import TrainingData
from .checkpoint import load_residual, save_residual
from .config import ResidualConfig
from .inputs import CROP_UNIT, TargetInputs, concat, target_inputs, world_truth
from .meta import ResidualMeta
from .modes import model_modes
from .net import ResidualNet, training_loss
from .ood import k1_evidence, physics_forecast, training_distribution, tune_baselines

LOG = "train_log.jsonl"


def at_most(sample: SceneSample, per_window: int, seed: int, number: int) -> SceneSample:
    """``sample`` with at most ``per_window`` of its targets (all with 0), drawn by ``seed`` and the window's
    ``number``."""
    targets = np.flatnonzero(np.asarray(sample.target_mask, bool))
    if not per_window or len(targets) <= per_window:
        return sample
    picked = np.random.default_rng([seed, number]).choice(targets, per_window, replace=False)
    mask = np.zeros(len(sample.target_mask), bool)
    mask[picked] = True
    return dataclasses.replace(sample, target_mask=mask)


def collect(samples: Iterable[SceneSample], config: ResidualConfig,
            progress: Callable[[int], None] | None = None, *, per_window: int = 0,
            seed: int = 0) -> tuple[TargetInputs, np.ndarray]:
    """The inputs (with their true futures) of every target of ``samples`` (at most ``per_window`` of each, drawn
    by ``seed`` and the window's number, when not 0: what keeps a million simulated windows in memory), and each
    target's window number."""
    parts: list[TargetInputs] = []
    windows: list[np.ndarray] = []
    for number, whole in enumerate(samples):
        sample = at_most(whole, per_window, seed, number)  # cut before the inputs: crops are their costly part
        inputs = target_inputs(sample, config, with_truth=True)
        if len(inputs):
            parts.append(inputs)
            windows.append(np.full(len(inputs), number, np.int64))
        if progress:
            progress(1)
    if not parts:
        raise ValueError("no targets to train on")
    return concat(parts), np.concatenate(windows)


def tensors(inputs: TargetInputs, rows: np.ndarray) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor,
                                                              torch.Tensor | None]:
    """(features, neighbours, mask, crops or None) of ``rows`` as torch tensors."""
    crops = None if inputs.crops is None else torch.from_numpy(inputs.crops[rows]).float() / CROP_UNIT
    return (torch.from_numpy(inputs.features[rows]), torch.from_numpy(inputs.neighbours[rows]),
            torch.from_numpy(inputs.neighbour_mask[rows]), crops)


def target_locations(logs: Iterable[pa.Table], samples: Sequence[SceneSample], windows: np.ndarray | None
                     ) -> list[str | None] | None:
    """The location of each target ``collect`` drew from ``samples`` (``windows``: its window numbers), looked up in
    the logs tables ``logs``; None without targets."""
    return None if windows is None else locations_of(logs, [samples[int(w)].log_id for w in windows])


def forecast(net: ResidualNet, inputs: TargetInputs, num_modes: int) -> NDArrayFloat:
    """(N, num_modes, T, 2) world forecasts: mode 0 the mean head (the K = 1 forecast), then the mode heads as
    ``modes.spread_modes`` takes them (the mean head repeated where more are asked for than there are heads)."""
    return model_modes(ranked_forecasts(net, inputs), num_modes)


@torch.inference_mode()
def ranked_forecasts(net: ResidualNet, inputs: TargetInputs, batch: int = 1024) -> NDArrayFloat:
    """(N, 1 + heads, T, 2) world forecasts: the mean head, then every mode head by descending score."""
    out = []
    for lo in range(0, len(inputs), batch):
        rows = np.arange(lo, min(lo + batch, len(inputs)))
        mean, modes, logits = (t.numpy() for t in net(*tensors(inputs, rows)))
        order = np.argsort(-logits, axis=1, kind="stable")
        ranked = np.take_along_axis(modes, order[:, :, None, None], axis=1)
        out.append(np.concatenate([mean[:, None], ranked], axis=1))
    from .inputs import to_world

    empty = np.zeros((0, net.config.modes + 1, net.config.pred_len, 2))
    return to_world((np.concatenate(out) if out else empty).astype(np.float64), inputs)


def evaluate(net: ResidualNet, inputs: TargetInputs) -> dict[str, float]:
    """K = 1 FDE/ADE and minFDE@K (K = modes + 1) on targets with their truth, metres."""
    k = net.config.modes + 1
    world = forecast(net, inputs, k)
    truth = world_truth(inputs)
    dist = np.linalg.norm(world - truth[:, None], axis=-1)  # (N, K, T)
    return {"fde": float(dist[:, 0, -1].mean()), "ade": float(dist[:, 0].mean()),
            f"min_fde_{k}": float(dist[:, :, -1].min(axis=1).mean()), "targets": float(len(inputs))}


@dataclass
class ResidualFitResult:
    """What ``fit_residual`` did: epochs run, the best epoch and its validation figures (metres), throughput."""

    epochs: int
    best_epoch: int
    steps: int
    best_step: int
    best_metrics: dict[str, float]
    best_checkpoint: Path
    last_checkpoint: Path
    train_targets: int
    targets_per_s: float
    stopped_early: bool


def _epoch_rows(windows: np.ndarray, cap: int, rng: np.random.Generator) -> np.ndarray:
    """This epoch's target rows, shuffled: all of them, or at most ``cap`` per window drawn anew."""
    if cap <= 0:
        return rng.permutation(len(windows))
    keys = rng.random(len(windows))
    order = np.lexsort((keys, windows))
    first = np.searchsorted(windows[order], windows[order], side="left")
    rank = np.arange(len(order)) - first
    return rng.permutation(order[rank < cap])


def _record_evidence(best: Path, val: TargetInputs, val_locations: Sequence[str | None]) -> None:
    """Add to the checkpoint in ``best`` where, by location, its K = 1 beat the best kinematic baseline on ``val``."""
    net, meta = load_residual(best)
    truth = world_truth(val)
    model = ranked_forecasts(net, val)[:, 0, -1]  # the mean head
    physics = physics_forecast(meta.ood, val.observed, truth.shape[1])[:, -1]
    meta.ood["k1_by_location"] = k1_evidence(np.linalg.norm(model - truth[:, -1], axis=-1),
                                             np.linalg.norm(physics - truth[:, -1], axis=-1), val_locations)
    save_residual(best, net, meta)


def fit_residual(  # noqa: PLR0913  the run's data, config and where it goes
    train: TargetInputs, windows: np.ndarray, val: TargetInputs | None, config: ResidualConfig, out_dir: Path, *,
    dataset_kind: str, manifest_hash: str, training_data: TrainingData | None = None, init_from: Path | None = None,
    locations: dict[str, int] | None = None, baselines: dict[str, Any] | None = None,
    val_locations: Sequence[str | None] | None = None, progress: Callable[[int], None] | None = None,
) -> ResidualFitResult:
    """Train on ``train`` (validating on ``val``), writing ``best/``, ``last/`` and ``train_log.jsonl`` into
    ``out_dir``; ``init_from`` starts from a checkpoint of the same architecture (pre-training → fine-tuning);
    ``locations``: the training windows per location (``logpipe.dataset.locations.window_locations``), which the
    checkpoint records so that predict knows the roads it has evidence for (None: not known); ``baselines``:
    ``ood.tune_baselines`` of ``train`` when the caller already has it (candidates trained on the same targets
    choose once); ``val_locations``: each validation target's location, so the best checkpoint records where its
    K = 1 beat the best kinematic baseline (``ood.k1_evidence``; predict keeps physics elsewhere)."""
    assert train.truth is not None
    torch.set_num_threads(config.num_threads)
    torch.manual_seed(config.seed)
    rng = np.random.default_rng(config.seed)
    net = ResidualNet(config)
    if init_from is not None:
        net.load_state_dict(load_residual(init_from)[0].state_dict())
    opt = torch.optim.Adam(net.parameters(), lr=config.lr, weight_decay=config.weight_decay)
    truth, scale = torch.from_numpy(train.truth), torch.from_numpy(train.scale.astype(np.float32))
    ood = training_distribution(train, locations) | (
        baselines if baselines is not None else tune_baselines(train, seed=config.seed))
    meta = ResidualMeta(config, dataset_kind, manifest_hash, 0, {}, ood, training_data=training_data)
    best_score, best_epoch, best_metrics, bad, seen, clock = math.inf, 0, {}, 0, 0, 0.0
    steps = best_step = 0
    out_dir.mkdir(parents=True, exist_ok=True)
    log = open_nofollow(out_dir / LOG, "w")
    epoch = 0
    try:
        for epoch in range(1, config.epochs + 1):
            started = time.perf_counter()
            net.train()
            rows = _epoch_rows(windows, config.max_targets_per_window, rng)
            total = 0.0
            for lo in range(0, len(rows), config.batch_size):
                batch = rows[lo:lo + config.batch_size]
                loss = training_loss(net(*tensors(train, batch)), truth[batch], scale[batch], config.score_weight)
                opt.zero_grad()
                loss.backward()  # type: ignore[no-untyped-call]
                opt.step()
                steps += 1
                total += float(loss.detach()) * len(batch)
            clock += time.perf_counter() - started
            seen += len(rows)
            record: dict[str, Any] = {"epoch": epoch, "train_loss": total / max(len(rows), 1), "targets": len(rows)}
            if val is not None and (epoch % config.val_every == 0 or epoch == config.epochs):
                net.eval()
                metrics = evaluate(net, val)
                record["val"] = metrics
                score = metrics["fde"] + metrics[f"min_fde_{config.modes + 1}"]
                if score < best_score:
                    best_score, best_epoch, best_step, best_metrics, bad = score, epoch, steps, metrics, 0
                    meta.epoch, meta.metrics = epoch, {f"val_{k}": v for k, v in metrics.items()}
                    save_residual(out_dir / "best", net, meta)
                else:
                    bad += 1
            log.write(json.dumps(record, sort_keys=True) + "\n")
            log.flush()
            if progress:
                progress(1)
            if config.patience and bad >= config.patience:
                break
    finally:
        log.close()
    net.eval()
    meta.epoch, meta.metrics = epoch, ({"val_" + k: v for k, v in evaluate(net, val).items()} if val else {})
    save_residual(out_dir / "last", net, meta)
    if val is None:  # without validation the last epoch is the one to use
        save_residual(out_dir / "best", net, meta)
        best_epoch, best_step = epoch, steps
    elif val_locations is not None:
        _record_evidence(out_dir / "best", val, val_locations)
    return ResidualFitResult(epoch, best_epoch, steps, best_step, best_metrics, out_dir / "best", out_dir / "last",
                             len(train), seen / clock if clock > 0 else 0.0, epoch < config.epochs)
