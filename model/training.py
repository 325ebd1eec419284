"""Training loop: best-of-H loss (eq. 23) with Adam, validation ADE/FDE, early stopping, checkpoints,
resume, a JSON-lines log and a rich progress bar.

Output folder layout::

    config.json         the resolved TrainConfig (features the data cannot feed switched off)
    train_log.jsonl     one JSON object per line: {"event": "train"|"val"|"start"|"end", "step": ..., ...}
    last/               resumable checkpoint written at every validation (see ``checkpoints``)
    best/               checkpoint with the lowest validation ADE so far

Each step decodes the H modes without autograd, picks each scene's best mode (eq. 23) and back-propagates
through a re-decode of that mode only (``TrainConfig.select_then_backprop``; the same gradient, ~2.4x
faster here than back-propagating through all H).

Determinism: batches, augmentation angles and the noise z of each step come from generators seeded with
(seed, epoch) / (seed, step), so a run resumed from ``last/`` continues exactly as the uninterrupted run
for Sequence inputs (streams restart their current pass).
"""

from __future__ import annotations

import functools
import hashlib
import itertools
import json
import math
import os
import time
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any, ParamSpec, TypeVar

import numpy as np
import torch

from logpipe.errors import LogpipeError
from logpipe.progress import report_total
from logpipe.types import SceneSample

from .batching import Batch, collate
from .checkpoints import (
    CheckpointMismatchError,
    TrainingData,
    check_meta,
    load_averaged,
    load_training_state,
    read_meta,
    save_checkpoint,
    warm_start,
)
from .config import ConfigError, ModelConfig, TrainConfig, config_to_dict, save_config
from .device import autocast, grad_scaler, resolve_device
from .feature_cache import BackboneFeatureCache, scene_keys
from .loss import DisplacementErrors, best_of_h_loss
from .nets import TrajectoryNet


class TrainingError(LogpipeError):
    """Training cannot start or continue (empty data, existing run without ``resume``)."""


@dataclass
class TrainResult:
    """Outcome of ``fit``.

    Attributes:
        out_dir: the run folder.
        best_checkpoint: folder of the best-validation checkpoint (None if never validated).
        last_checkpoint: folder of the resumable last checkpoint.
        log_path: the JSON-lines training log.
        config: the resolved config that was trained.
        steps: optimiser steps done in total (including resumed ones).
        best_step: step of the best validation.
        best_val_ade: best-of-K ADE (metres) at ``best_step`` (NaN without validation data).
        best_val_fde: best-of-K FDE (metres) at ``best_step``.
        stopped_early: whether early stopping ended the run.
        elapsed_s: wall time of this call.
        total_elapsed_s: wall time of the whole run, every resumed part included (``elapsed_s`` without resume).
        resumed_at_step: the step this call resumed from (None when it started the run).
        train_samples_per_s: scenes per second in optimiser steps (excluding validation).
        weights_sha256: digest of the final weights (equal on every process of a data-parallel run).
        processes: data-parallel processes (1 without torchrun).
        device: the torch device the run trained on (``cpu``, ``cuda``).
    """

    out_dir: Path
    best_checkpoint: Path | None
    last_checkpoint: Path
    log_path: Path
    config: TrainConfig
    steps: int
    best_step: int
    best_val_ade: float
    best_val_fde: float
    stopped_early: bool
    elapsed_s: float
    train_samples_per_s: float
    weights_sha256: str = ""
    processes: int = 1
    total_elapsed_s: float = 0.0
    resumed_at_step: int | None = None
    device: str = "cpu"


def _probe(samples: Iterable[SceneSample], limit: int = 256) -> tuple[bool, int | None, int, int]:
    """(any ego, raster channels or None, obs_len, total steps) over the first ``limit`` samples."""
    has_ego = False
    channels: int | None = None
    obs_len = steps = -1
    for s in itertools.islice(samples, limit):
        has_ego |= s.ego_index >= 0
        if s.raster is not None:
            channels = int(s.raster.shape[0])
        obs_len, steps = s.obs_len, int(s.positions.shape[1])
    if obs_len < 0:
        raise TrainingError("the training data is empty")
    return has_ego, channels, obs_len, steps


def resolve_config(config: TrainConfig, train: Iterable[SceneSample]) -> TrainConfig:
    """Fit the config to the data: switch off the features the data cannot feed (no ego: EMF, ETF; no
    raster: EF), take the raster channel count C from the rasters, and check the sample lengths."""
    has_ego, channels, obs_len, steps = _probe(train)
    m = config.model
    if obs_len != m.obs_len or steps < m.obs_len + m.pred_len:
        raise ConfigError(
            f"samples have obs_len {obs_len} and {steps} steps but model.obs_len={m.obs_len}, "
            f"model.pred_len={m.pred_len}; set them to the dataset's protocol"
        )
    m = m.resolved(has_ego=has_ego, has_map=channels is not None)
    if channels is not None and m.features.environment:
        m = replace(m, raster_channels=channels)
    return replace(config, model=m)


def targets_with_future(batch_target: torch.Tensor, valid: torch.Tensor, obs_len: int) -> torch.Tensor:
    """Targets whose whole predicted horizon has ground truth (the rows eq. 23 sums over)."""
    return batch_target & valid[:, obs_len:].all(dim=1)


def best_of_h_step_loss(
    net: TrajectoryNet, batch: Batch, num_modes: int, generator: torch.Generator, reduce: str, select_first: bool,
    feature_map: torch.Tensor | None = None,
) -> torch.Tensor:
    """Eq. 23 for one batch, ready for ``backward`` (``feature_map``: the backbone's maps of ``batch.raster``
    from ``feature_cache``, else the backbone runs).

    With ``select_first`` the H modes are decoded without autograd, the best modes are picked, and only
    those are decoded again with autograd from the same encoder state and the same noise z. Modes are
    independent copies of the scene, so the re-decoded trajectories equal the picked ones and the gradient
    is exactly eq. 23's (which reaches only the picked modes), at the cost of a small extra decode instead of
    back-propagating through all H:

    * per-scene min (the paper): one mode per scene, a one-mode decode;
    * per-agent min: each scene's distinct picked modes, packed into as many decode slots as the scene
      with the most of them needs (slot l holds a different mode in each scene; scenes never interact).
    """
    cfg = net.config
    enc = net.encode(batch, feature_map)
    rows = batch.active.nonzero().squeeze(1)
    # z from the CPU generator whatever the device: a run draws the same z on every device.
    noise = torch.randn(num_modes, len(rows), cfg.noise_dim, generator=generator).to(rows.device)
    truth = batch.positions[rows, cfg.obs_len :]
    mask = targets_with_future(batch.target, batch.valid, cfg.obs_len)[rows]
    scene = batch.scene[rows]
    if not select_first or num_modes == 1:
        pred = net.decode(batch, enc, noise)
        return best_of_h_loss(pred.positions, truth, mask, scene, batch.size, reduce)[0]
    with torch.no_grad():
        pred = net.decode(batch, enc, noise)
        _, best = best_of_h_loss(pred.positions, truth, mask, scene, batch.size, reduce)
    every_row = torch.arange(len(rows), device=rows.device)
    if reduce == "scene":
        pred = net.decode(batch, enc, noise[best[scene], every_row][None])  # (1, R, noise_dim)
        return best_of_h_loss(pred.positions, truth, mask, scene, batch.size, reduce)[0]
    picked = torch.zeros(batch.size, num_modes, dtype=torch.bool, device=rows.device)
    picked[scene[mask], best[mask]] = True
    slot_of = picked.cumsum(dim=1) - 1  # (B, H): slot of each picked mode in its scene
    slots = max(int(picked.sum(dim=1).max()), 1)
    mode_in_slot = torch.zeros(batch.size, slots, dtype=torch.long, device=rows.device)  # unused: mode 0
    pick_scene, pick_mode = picked.nonzero(as_tuple=True)
    mode_in_slot[pick_scene, slot_of[pick_scene, pick_mode]] = pick_mode
    pred = net.decode(batch, enc, noise[mode_in_slot[scene].t(), every_row])  # (slots, R, noise_dim)
    mine = pred.positions[slot_of[scene, best].clamp(min=0), every_row]  # (R, T, 2): each row's picked mode
    loss, _ = best_of_h_loss(mine[None], truth, mask, scene, batch.size, "agent")
    return loss


@torch.no_grad()
def evaluate(
    net: TrajectoryNet,
    samples: Iterable[SceneSample],
    *,
    num_modes: int,
    seed: int = 0,
    batch_size: int = 32,
    limit: int | None = None,
) -> DisplacementErrors:
    """Best-of-K ADE/FDE (metres) of ``net`` on ``samples`` (targets with a full future only), on the device
    ``net`` is on (under ``device.autocast`` there)."""
    was_training = net.training
    net.eval()
    device = next(net.parameters()).device
    gen = torch.Generator().manual_seed(seed)
    errors = DisplacementErrors()
    cfg = net.config
    it = iter(samples if limit is None else itertools.islice(samples, limit))
    while chunk := list(itertools.islice(it, batch_size)):
        batch = collate(chunk, cfg).to(device)
        with autocast(device):
            pred = net(batch, num_modes, gen)
        rows = pred.rows
        mask = targets_with_future(batch.target, batch.valid, cfg.obs_len)[rows]
        scene = batch.scene[rows]  # errors in metres whatever the model frame's scale
        errors.add(batch.metres(pred.positions.transpose(0, 1), scene).transpose(0, 1),
                   batch.metres(batch.positions[rows, cfg.obs_len :], scene), mask)
    net.train(was_training)
    return errors


def _batches(
    train: Sequence[SceneSample] | Iterable[SceneSample], config: TrainConfig, epoch: int, skip: int
) -> Iterator[tuple[int, int, list[SceneSample]]]:
    """Yield (epoch, position in epoch, batch) forever (or until a one-shot stream ends)."""
    bs = config.batch_size
    while True:
        rng = np.random.default_rng([config.seed, epoch])
        if isinstance(train, Sequence):
            if len(train) == 0:
                raise TrainingError("the training data is empty")
            order = rng.permutation(len(train))
            for pos in range(skip, len(order) - bs + 1 if len(order) >= bs else 1, bs):
                yield epoch, pos + bs, [train[int(i)] for i in order[pos : pos + bs]]
        else:
            buffer: list[SceneSample] = []
            batch: list[SceneSample] = []
            pos = 0
            stream = iter(train)
            exhausted = False
            while not exhausted or buffer:
                if not exhausted:
                    try:
                        buffer.append(next(stream))
                    except StopIteration:
                        exhausted = True
                    if len(buffer) < config.shuffle_buffer and not exhausted:
                        continue
                if buffer:
                    batch.append(buffer.pop(int(rng.integers(len(buffer)))))
                if len(batch) == bs:
                    pos += bs
                    yield epoch, pos, batch
                    batch = []
            if iter(train) is train:  # a one-shot iterator cannot be re-read
                return
        epoch += 1
        skip = 0


@dataclass(frozen=True)
class _Ranks:
    """Data-parallel training under ``torchrun`` (one process per core or machine).

    Each process takes its share (every ``world``-th scene) of the same shuffled global batch, gradients are
    averaged with an all-reduce before clipping and the Adam step, so every process holds the same weights;
    process 0 alone validates, writes checkpoints and the log, and tells the others when to stop. Without
    ``torchrun`` (``WORLD_SIZE`` unset or 1) this is the single-process loop unchanged.

    Attributes:
        rank: this process (0 = the one that writes).
        world: number of processes.
    """

    rank: int = 0
    world: int = 1

    @classmethod
    def from_env(cls) -> _Ranks:
        """Join the process group torchrun describes in the environment (gloo: CPU only)."""
        world = int(os.environ.get("WORLD_SIZE", "1"))
        if world <= 1:
            return cls()
        import torch._dynamo  # noqa: F401  (see below)
        import torch.distributed as dist

        # torch._dynamo, imported lazily by the first optimizer, holds C++ references to any process group that
        # exists when it loads, so destroy_process_group cannot free that group's gloo threads, and about one
        # torchrun exit in six then aborts ("terminate called without an active exception"). Imported before
        # the group exists, it holds none.
        if not dist.is_initialized():
            dist.init_process_group("gloo")
        return cls(rank=dist.get_rank(), world=dist.get_world_size())

    @property
    def main(self) -> bool:
        return self.rank == 0

    def average_gradients(self, net: torch.nn.Module) -> None:
        if self.world == 1:
            return
        import torch.distributed as dist

        for param in net.parameters():
            if param.grad is None:
                param.grad = torch.zeros_like(param)
            dist.all_reduce(param.grad)
            param.grad /= self.world

    def agree(self, flag: bool) -> bool:
        """Process 0's ``flag`` on every process."""
        if self.world == 1:
            return flag
        import torch.distributed as dist

        value = torch.tensor([1 if flag else 0])
        dist.broadcast(value, src=0)
        return bool(value.item())


class _Log:
    """Append-only JSON-lines log (written by process 0 only in a data-parallel run)."""

    def __init__(self, path: Path, enabled: bool = True) -> None:
        self.path = path
        self.enabled = enabled

    def write(self, event: str, **fields: Any) -> None:
        if not self.enabled:
            return
        with self.path.open("a", encoding="utf-8") as fh:
            fh.write(json.dumps({"event": event, "time": time.time(), **fields}) + "\n")


_Params = ParamSpec("_Params")
_Result = TypeVar("_Result")


def _leaves_process_group(train: Callable[_Params, _Result]) -> Callable[_Params, _Result]:
    """``train``, leaving the torchrun process group it joined when it returns.

    Why: a gloo group alive at interpreter exit keeps its threads running into teardown. Not on an exception,
    where another process may still be inside a collective and the teardown could hang (torchtitan's rule too);
    torchrun ends the others then.
    """

    @functools.wraps(train)
    def wrapper(*args: _Params.args, **kwargs: _Params.kwargs) -> _Result:
        import torch.distributed as dist

        joined_here = not dist.is_initialized()
        result = train(*args, **kwargs)
        if joined_here and dist.is_initialized():
            dist.destroy_process_group()
        return result

    return wrapper


@_leaves_process_group
def fit(
    train: Sequence[SceneSample] | Iterable[SceneSample],
    val: Sequence[SceneSample] | Iterable[SceneSample] | None,
    config: TrainConfig | ModelConfig,
    out_dir: Path,
    *,
    resume: bool = False,
    progress: bool | Callable[[int], None] = True,
    dataset_kind: str = "unknown",
    manifest_hash: str = "",
    init_from: Path | None = None,
    training_data: TrainingData | None = None,
    device: torch.device | str = "cpu",
) -> TrainResult:
    """Train ``TrajectoryNet`` and write checkpoints and the log into ``out_dir``.

    Args:
        train: training scenes (a Sequence is shuffled per epoch; any other iterable is streamed through
            a shuffle buffer and re-iterated per epoch when possible).
        val: validation scenes (None: no validation, no early stopping, ``best/`` not written); a one-shot
            iterator is read once into memory (up to ``val_max_samples``), anything else is re-iterated.
        config: the run's config (a bare ModelConfig trains with default TrainConfig settings).
        out_dir: run folder; created if needed.
        resume: continue from ``out_dir/last`` (whose model config, dataset kind and manifest hash must
            match); without it an existing run in ``out_dir`` is an error.
        progress: True: a rich progress bar with loss and validation ADE/FDE (on a terminal); a callable: called
            with the steps each optimiser step adds (``logpipe.progress``: the total is reported first).
        dataset_kind: stored in checkpoints and checked on load.
        manifest_hash: hash of the dataset manifest, stored in checkpoints.
        init_from: a checkpoint folder to start a new run from (``checkpoints.warm_start``: e.g. a Noise-LSTM
            checkpoint into the full model, whose extra inputs start at zero); ignored on resume, where the
            weights come from ``last/``. Logged in the ``start`` event.
        training_data: the splits and recordings of ``train`` / ``val``, stored in every checkpoint so predicting
            over them can be flagged.
        device: where the network trains and validates (``model.device.resolve_device``: ``cpu``, ``cuda`` or
            ``auto``). On CUDA the forward passes run under autocast (bf16, else fp16 with a gradient scaler whose
            scale is not checkpointed, so a resumed fp16 run re-learns it); batches, shuffling, augmentation and
            noise are drawn on the CPU as before, and checkpoints hold the same CPU tensors on every device.
            Data-parallel runs (torchrun, gloo) are CPU only.
    """
    start_time = time.perf_counter()
    ranks = _Ranks.from_env()
    cfg = config if isinstance(config, TrainConfig) else TrainConfig(model=config)
    if cfg.batch_size < ranks.world:
        raise ConfigError(f"train.batch_size {cfg.batch_size} must be >= the {ranks.world} torchrun processes")
    dev = resolve_device(device)
    if ranks.world > 1 and dev.type != "cpu":
        raise ConfigError(f"data-parallel training under torchrun runs on the CPU (gloo), not {dev}: use --device cpu")
    if not isinstance(train, Sequence) and iter(train) is train:
        # A one-shot iterator: probe its head, then put the head back in front of the rest.
        head = list(itertools.islice(train, 256))
        cfg = resolve_config(cfg, head)
        train = itertools.chain(head, train)
    else:
        cfg = resolve_config(cfg, train)
    if val is not None and not isinstance(val, Sequence) and iter(val) is val:
        val = list(itertools.islice(val, cfg.val_max_samples))  # validated repeatedly: keep a one-shot stream
    if cfg.num_threads > 0:
        torch.set_num_threads(cfg.num_threads)
    if init_from is not None:
        read_meta(init_from)  # a bad source fails before the run folder is made
    out_dir.mkdir(parents=True, exist_ok=True)
    last_dir, best_dir = out_dir / "last", out_dir / "best"
    log = _Log(out_dir / "train_log.jsonl", enabled=ranks.main)
    torch.manual_seed(cfg.seed)
    net = TrajectoryNet(cfg.model).to(dev)  # initialised on the CPU (same weights on every device), then moved
    scaler = grad_scaler(dev)
    optimizer = torch.optim.Adam(net.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
    average = _weight_average(net, cfg.ema_decay)
    # Frozen backbone's maps of the training samples (validation runs the backbone); see feature_cache.
    cache = BackboneFeatureCache(cfg.cache_backbone_max_mb * 10**6) if cfg.cache_backbone_features else None
    step, epoch, pos_in_epoch = 0, 0, 0
    best_ade, best_fde, best_step, bad_evals = math.inf, math.inf, -1, 0
    earlier_elapsed, resumed_at_step = 0.0, None  # wall time of the parts before a resume, and where it resumed
    if (last_dir / "meta.json").exists():
        if not resume:
            raise TrainingError(f"{out_dir} already holds a run; pass resume=True or use a new folder")
        meta = read_meta(last_dir)
        check_meta(meta, last_dir, expect_kind=dataset_kind, expect_manifest_hash=manifest_hash)
        if meta.config.model != cfg.model or meta.config.seed != cfg.seed:
            try:
                check_meta(meta, last_dir, expect_config=cfg.model)
            except CheckpointMismatchError as exc:
                raise CheckpointMismatchError(f"cannot resume: {exc}") from exc
            raise CheckpointMismatchError(f"{last_dir}: cannot resume: seed {meta.config.seed} != {cfg.seed}")
        from safetensors.torch import load_file

        net.load_state_dict(load_file(str(last_dir / "weights.safetensors")))
        state = load_training_state(last_dir, optimizer)
        if average is not None:
            average.load_state_dict(load_averaged(last_dir))
        step, epoch, pos_in_epoch = state["step"], state["epoch"], state["pos_in_epoch"]
        best_ade, best_fde, best_step = state["best_ade"], state["best_fde"], state["best_step"]
        bad_evals = state["bad_evals"]
        earlier_elapsed = float(state.get("elapsed_s", math.nan))  # NaN: written before the state kept it
        resumed_at_step = step
        log.write("resume", step=step)
    warm = None
    if init_from is not None and resumed_at_step is None:
        warm = warm_start(net, init_from)  # every DDP rank reads the same file, so replicas start equal
        average = _weight_average(net, cfg.ema_decay)  # averages from the warm-started weights
    if ranks.main:
        save_config(cfg, out_dir / "config.json")
    log.write("start", step=step, config=config_to_dict(cfg), processes=ranks.world, device=str(dev),
              **({"init_from": warm.to_dict()} if warm is not None else {}))

    def evaluated() -> TrajectoryNet:
        """The weights validation scores and ``best/`` keeps: the average when the run keeps one."""
        return net if average is None else average.module  # type: ignore[return-value]

    def checkpoint(folder: Path, metrics: dict[str, float], resumable: bool) -> None:
        if not ranks.main:
            return
        save_checkpoint(
            folder,
            net if resumable else evaluated(),
            cfg,
            dataset_kind=dataset_kind,
            manifest_hash=manifest_hash,
            step=step,
            metrics=metrics,
            training_data=training_data,
            optimizer=optimizer if resumable else None,
            averaged=dict(average.state_dict()) if resumable and average is not None else None,
            train_state={
                "step": step,
                "epoch": epoch,
                "pos_in_epoch": pos_in_epoch,
                "best_ade": best_ade,
                "best_fde": best_fde,
                "best_step": best_step,
                "bad_evals": bad_evals,
                "elapsed_s": earlier_elapsed + time.perf_counter() - start_time,
            },
        )

    def validate() -> dict[str, float]:
        nonlocal best_ade, best_fde, best_step, bad_evals
        if val is None or not ranks.main:
            checkpoint(last_dir, {}, resumable=True)
            return {}
        err = evaluate(evaluated(), val, num_modes=cfg.val_modes, seed=cfg.seed, limit=cfg.val_max_samples)
        improved = err.ade < best_ade
        if improved:
            best_ade, best_fde, best_step, bad_evals = err.ade, err.fde, step, 0
        else:
            bad_evals += 1
        metrics = {"val_ade": err.ade, "val_fde": err.fde}
        if improved:
            checkpoint(best_dir, metrics, resumable=False)
        checkpoint(last_dir, metrics, resumable=True)
        log.write("val", step=step, val_ade=err.ade, val_fde=err.fde, best=improved, targets=err.count)
        return metrics

    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

    bar = Progress(
        TextColumn("train"),
        BarColumn(),
        MofNCompleteColumn(),
        TextColumn("loss {task.fields[loss]:.4f}  val ADE {task.fields[ade]:.3f} FDE {task.fields[fde]:.3f}"),
        TimeRemainingColumn(),
        disable=progress is not True or not ranks.main,
    )
    task = bar.add_task("train", total=cfg.steps, completed=step, loss=math.nan, ade=best_ade, fde=best_fde)
    advance = progress if callable(progress) and ranks.main else None
    if advance is not None:
        report_total(advance, cfg.steps)
        advance(step)  # a resumed run starts where it stopped
    train_time, train_samples, stopped_early = 0.0, 0, False
    loss_sum, loss_n = 0.0, 0
    net.train()
    batches = _batches(train, cfg, epoch, pos_in_epoch)
    with bar:
        while step < cfg.steps:
            try:
                epoch, pos_in_epoch, chunk = next(batches)
            except StopIteration:
                log.write("stream_end", step=step)
                break
            t0 = time.perf_counter()
            chunk = chunk[ranks.rank :: ranks.world]
            rotations = None
            if cfg.augment_rotate:
                rotations = np.random.default_rng([cfg.seed, step, 1]).uniform(0, 2 * np.pi, len(chunk)).tolist()
            batch = collate(chunk, cfg.model, rotations=rotations)
            keys = scene_keys(chunk, batch) if cache is not None and net.env is not None else None
            batch = batch.to(dev)
            gen = torch.Generator().manual_seed(cfg.seed * 1_000_003 + step + 7_919 * ranks.rank)
            for group in optimizer.param_groups:
                group["lr"] = cfg.lr * cfg.lr_decay ** (step // cfg.lr_decay_every)
            with autocast(dev):
                fmap = None
                if cache is not None and keys is not None and net.env is not None and batch.raster is not None:
                    fmap = cache.feature_maps(net.env, batch.raster, keys)
                loss = best_of_h_step_loss(net, batch, cfg.num_modes, gen, cfg.loss_min_over,
                                           cfg.select_then_backprop, fmap)
            optimizer.zero_grad(set_to_none=True)
            if scaler is None:
                loss.backward()  # type: ignore[no-untyped-call]
            else:  # fp16 autocast: scale the loss so small gradients do not underflow
                scaler.scale(loss).backward()  # type: ignore[no-untyped-call]
            ranks.average_gradients(net)
            if scaler is not None:
                scaler.unscale_(optimizer)  # clip the true gradients
            if cfg.grad_clip > 0:
                torch.nn.utils.clip_grad_norm_(net.parameters(), cfg.grad_clip)
            if scaler is None:
                optimizer.step()
            else:  # skips the step when the scaled gradients overflowed, then adapts the scale
                scaler.step(optimizer)
                scaler.update()
            if average is not None:
                average.update_parameters(net)
            step += 1
            train_time += time.perf_counter() - t0
            train_samples += len(chunk)
            loss_sum += loss.item()
            loss_n += 1
            if step % cfg.log_every == 0:
                log.write(
                    "train",
                    step=step,
                    loss=loss_sum / loss_n,
                    lr=optimizer.param_groups[0]["lr"],
                    samples_per_s=train_samples / max(train_time, 1e-9),
                )
                loss_sum, loss_n = 0.0, 0
            bar.update(task, completed=step, loss=loss.item())
            if advance is not None:
                advance(1)
            if step % cfg.eval_every == 0 or step == cfg.steps:
                metrics = validate()
                if metrics:
                    bar.update(task, ade=best_ade, fde=best_fde)
                patience_spent = bool(cfg.early_stop_patience) and bad_evals >= cfg.early_stop_patience
                if ranks.agree(patience_spent and step >= cfg.early_stop_min_steps):
                    stopped_early = True
                    log.write("early_stop", step=step, best_step=best_step)
                    break
    if ranks.main and (not (last_dir / "meta.json").exists() or read_meta(last_dir).step != step):
        validate()
    elapsed = time.perf_counter() - start_time
    rate = train_samples / train_time if train_time > 0 else 0.0
    log.write("end", step=step, best_step=best_step, best_val_ade=best_ade, elapsed_s=elapsed, samples_per_s=rate,
              **({"backbone_cache": asdict(cache.stats)} if cache is not None else {}))
    return TrainResult(
        out_dir=out_dir,
        best_checkpoint=best_dir if (best_dir / "meta.json").exists() else None,
        last_checkpoint=last_dir,
        log_path=log.path,
        config=cfg,
        steps=step,
        best_step=best_step,
        best_val_ade=best_ade if math.isfinite(best_ade) else math.nan,
        best_val_fde=best_fde if math.isfinite(best_fde) else math.nan,
        stopped_early=stopped_early,
        elapsed_s=elapsed,
        train_samples_per_s=rate,
        weights_sha256=_weights_digest(net),
        processes=ranks.world,
        total_elapsed_s=earlier_elapsed + elapsed,
        resumed_at_step=resumed_at_step,
        device=str(dev),
    )


def _weight_average(net: TrajectoryNet, decay: float) -> torch.optim.swa_utils.AveragedModel | None:
    """An exponential moving average of ``net``'s weights (None when ``decay`` is 0)."""
    if decay == 0:
        return None
    from torch.optim.swa_utils import AveragedModel, get_ema_multi_avg_fn

    ema = get_ema_multi_avg_fn(decay)  # type: ignore[no-untyped-call]
    return AveragedModel(net, multi_avg_fn=ema, use_buffers=True)


def _weights_digest(net: torch.nn.Module) -> str:
    digest = hashlib.sha256()
    for name, tensor in sorted(net.state_dict().items()):
        digest.update(name.encode())
        digest.update(tensor.detach().cpu().contiguous().numpy().tobytes())
    return digest.hexdigest()
