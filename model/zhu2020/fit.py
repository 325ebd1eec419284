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

``fit`` runs these steps in order: fit the config to the data (``train_inputs``), set up the run (``_Run``:
network, optimiser, weight average), resume or warm-start it, then ``_train_loop``: one ``_Run.train_step``
(eq. 23 per batch, ``step_loss``) per batch of ``train_inputs.training_batches``, and every ``eval_every``
steps ``_Run.validate`` (``evaluation``) with its checkpoints and early stopping. ``data_parallel`` holds the
torchrun parts.
"""

from __future__ import annotations

import hashlib
import itertools
import json
import math
import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from logpipe.progress import report_total
from logpipe.storage.io import open_nofollow
from logpipe.types import SceneSample

from ..checkpoint.format import CheckpointMismatchError, TrainingData
from ..training.data_parallel import Ranks, leaves_process_group
from ..training.device import autocast, grad_scaler, resolve_device
from .batching import collate
from .checkpoint import load_averaged, load_training_state, save_checkpoint, warm_start
from .config import ConfigError, ModelConfig, TrainConfig, config_to_dict, save_config
from .evaluation import evaluate
from .feature_cache import BackboneFeatureCache, scene_keys
from .meta import check_meta, read_meta
from .network import TrajectoryNet
from .step_loss import best_of_h_step_loss
from .train_inputs import TrainingError, resolve_config, training_batches


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


class _Log:
    """Append-only JSON-lines log (written by process 0 only in a data-parallel run)."""

    def __init__(self, path: Path, enabled: bool = True) -> None:
        self.path = path
        self.enabled = enabled

    def write(self, event: str, **fields: Any) -> None:
        if not self.enabled:
            return
        with open_nofollow(self.path, "a") as fh:
            fh.write(json.dumps({"event": event, "time": time.time(), **fields}) + "\n")


_Scenes = Sequence[SceneSample] | Iterable[SceneSample]


@dataclass
class _Counters:
    """Where a run is and its best validation so far (what ``last/train_state.json`` keeps, with the wall time)."""

    step: int = 0
    epoch: int = 0
    pos_in_epoch: int = 0
    best_ade: float = math.inf  # metres
    best_fde: float = math.inf  # metres
    best_step: int = -1
    bad_evals: int = 0
    earlier_elapsed: float = 0.0  # seconds: the parts of the run before a resume (NaN: not recorded)
    resumed_at_step: int | None = None


class _Run:
    """One training run in ``out_dir``: network, optimiser, weight average, backbone cache, counters and log.

    Its methods are ``fit``'s steps; the order they run in (and so the order of every random draw) is ``fit``'s.
    """

    def __init__(  # noqa: PLR0913  fit()'s run context, stored as given
        self, cfg: TrainConfig, out_dir: Path, ranks: Ranks, dev: torch.device, val: _Scenes | None, *,
        dataset_kind: str, manifest_hash: str, training_data: TrainingData | None, start_time: float,
    ) -> None:
        self.cfg, self.ranks, self.dev, self.val = cfg, ranks, dev, val
        self.dataset_kind, self.manifest_hash, self.training_data = dataset_kind, manifest_hash, training_data
        self.start_time = start_time
        self.last_dir, self.best_dir = out_dir / "last", out_dir / "best"
        self.log = _Log(out_dir / "train_log.jsonl", enabled=ranks.main)
        torch.manual_seed(cfg.seed)
        self.net = TrajectoryNet(cfg.model).to(dev)  # initialised on the CPU (same weights on every device), then moved
        self.scaler = grad_scaler(dev)
        self.optimizer = torch.optim.Adam(self.net.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
        self.average = _weight_average(self.net, cfg.ema_decay)
        # Frozen backbone's maps of the training samples (validation runs the backbone); see feature_cache.
        self.cache = BackboneFeatureCache(cfg.cache_backbone_max_mb * 10**6) if cfg.cache_backbone_features else None
        self.state = _Counters()

    def restore(self, resume: bool) -> None:
        """Continue from ``last/`` when the run folder holds one (which ``resume`` must allow)."""
        last_dir, cfg, s = self.last_dir, self.cfg, self.state
        if not (last_dir / "meta.json").exists():
            return
        if not resume:
            raise TrainingError(f"{last_dir.parent} already holds a run; pass resume=True or use a new folder")
        meta = read_meta(last_dir)
        check_meta(meta, last_dir, expect_kind=self.dataset_kind, expect_manifest_hash=self.manifest_hash)
        if meta.config.model != cfg.model or meta.config.seed != cfg.seed:
            try:
                check_meta(meta, last_dir, expect_config=cfg.model)
            except CheckpointMismatchError as exc:
                raise CheckpointMismatchError(f"cannot resume: {exc}") from exc
            raise CheckpointMismatchError(f"{last_dir}: cannot resume: seed {meta.config.seed} != {cfg.seed}")
        from safetensors.torch import load_file

        self.net.load_state_dict(load_file(str(last_dir / "weights.safetensors")))
        state = load_training_state(last_dir, self.optimizer)
        if self.average is not None:
            self.average.load_state_dict(load_averaged(last_dir))
        s.step, s.epoch, s.pos_in_epoch = state["step"], state["epoch"], state["pos_in_epoch"]
        s.best_ade, s.best_fde, s.best_step = state["best_ade"], state["best_fde"], state["best_step"]
        s.bad_evals = state["bad_evals"]
        s.earlier_elapsed = float(state.get("elapsed_s", math.nan))  # NaN: written before the state kept it
        s.resumed_at_step = s.step
        self.log.write("resume", step=s.step)

    def warm_start(self, init_from: Path) -> dict[str, Any]:
        """Start from ``init_from``'s weights (``checkpoints.warm_start``); returns what the start event logs."""
        warm = warm_start(self.net, init_from)  # every DDP rank reads the same file, so replicas start equal
        self.average = _weight_average(self.net, self.cfg.ema_decay)  # averages from the warm-started weights
        return warm.to_dict()

    def evaluated(self) -> TrajectoryNet:
        """The weights validation scores and ``best/`` keeps: the average when the run keeps one."""
        return self.net if self.average is None else self.average.module  # type: ignore[return-value]

    def checkpoint(self, folder: Path, metrics: dict[str, float], resumable: bool) -> None:
        """Write ``folder`` (process 0 only): the raw weights with the optimiser when ``resumable``, else the
        evaluated ones."""
        if not self.ranks.main:
            return
        s = self.state
        save_checkpoint(
            folder,
            self.net if resumable else self.evaluated(),
            self.cfg,
            dataset_kind=self.dataset_kind,
            manifest_hash=self.manifest_hash,
            step=s.step,
            metrics=metrics,
            training_data=self.training_data,
            optimizer=self.optimizer if resumable else None,
            averaged=dict(self.average.state_dict()) if resumable and self.average is not None else None,
            train_state={
                "step": s.step,
                "epoch": s.epoch,
                "pos_in_epoch": s.pos_in_epoch,
                "best_ade": s.best_ade,
                "best_fde": s.best_fde,
                "best_step": s.best_step,
                "bad_evals": s.bad_evals,
                "elapsed_s": s.earlier_elapsed + time.perf_counter() - self.start_time,
            },
        )

    def validate(self) -> dict[str, float]:
        """Score the evaluated weights on the validation data, keep them as ``best/`` when they improved, and
        write ``last/``; returns the metrics (empty without validation data or off process 0)."""
        s, cfg = self.state, self.cfg
        if self.val is None or not self.ranks.main:
            self.checkpoint(self.last_dir, {}, resumable=True)
            return {}
        err = evaluate(self.evaluated(), self.val, num_modes=cfg.val_modes, seed=cfg.seed, limit=cfg.val_max_samples)
        improved = err.ade < s.best_ade
        if improved:
            s.best_ade, s.best_fde, s.best_step, s.bad_evals = err.ade, err.fde, s.step, 0
        else:
            s.bad_evals += 1
        metrics = {"val_ade": err.ade, "val_fde": err.fde}
        if improved:
            self.checkpoint(self.best_dir, metrics, resumable=False)
        self.checkpoint(self.last_dir, metrics, resumable=True)
        self.log.write("val", step=s.step, val_ade=err.ade, val_fde=err.fde, best=improved, targets=err.count)
        return metrics

    def train_step(self, chunk: list[SceneSample]) -> torch.Tensor:
        """One optimiser step on ``chunk`` (this process's share of the global batch); returns its loss (eq. 23).

        Augmentation angles and the noise z come from generators seeded with (seed, step), the backbone's maps
        from the cache when the run keeps one.
        """
        cfg, net, step = self.cfg, self.net, self.state.step
        rotations = None
        if cfg.augment_rotate:
            rotations = np.random.default_rng([cfg.seed, step, 1]).uniform(0, 2 * np.pi, len(chunk)).tolist()
        batch = collate(chunk, cfg.model, rotations=rotations)
        keys = scene_keys(chunk, batch) if self.cache is not None and net.env is not None else None
        batch = batch.to(self.dev)
        gen = torch.Generator().manual_seed(cfg.seed * 1_000_003 + step + 7_919 * self.ranks.rank)
        for group in self.optimizer.param_groups:
            group["lr"] = cfg.lr * cfg.lr_decay ** (step // cfg.lr_decay_every)
        with autocast(self.dev):
            fmap = None
            if self.cache is not None and keys is not None and net.env is not None and batch.raster is not None:
                fmap = self.cache.feature_maps(net.env, batch.raster, keys)
            loss = best_of_h_step_loss(net, batch, cfg.num_modes, gen, cfg.loss_min_over,
                                       cfg.select_then_backprop, fmap)
        self._descend(loss)
        self.state.step += 1
        return loss

    def _descend(self, loss: torch.Tensor) -> None:
        """Back-propagate ``loss``, average the gradients over the processes, clip them and take the Adam step."""
        optimizer, scaler = self.optimizer, self.scaler
        optimizer.zero_grad(set_to_none=True)
        if scaler is None:
            loss.backward()  # type: ignore[no-untyped-call]
        else:  # fp16 autocast: scale the loss so small gradients do not underflow
            scaler.scale(loss).backward()  # type: ignore[no-untyped-call]
        self.ranks.average_gradients(self.net)
        if scaler is not None:
            scaler.unscale_(optimizer)  # clip the true gradients
        if self.cfg.grad_clip > 0:
            torch.nn.utils.clip_grad_norm_(self.net.parameters(), self.cfg.grad_clip)
        if scaler is None:
            optimizer.step()
        else:  # skips the step when the scaled gradients overflowed, then adapts the scale
            scaler.step(optimizer)
            scaler.update()
        if self.average is not None:
            self.average.update_parameters(self.net)


def _prepare(
    train: Sequence[SceneSample] | Iterable[SceneSample],
    val: Sequence[SceneSample] | Iterable[SceneSample] | None,
    config: TrainConfig | ModelConfig,
    ranks: Ranks,
    device: torch.device | str,
) -> tuple[TrainConfig, torch.device, _Scenes, _Scenes | None]:
    """Check the set-up and fit the config to the data: (config, device, training scenes, validation scenes)."""
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
    return cfg, dev, train, val


@dataclass
class _LoopStats:
    """What the training loop measured: optimiser-step wall time (s), scenes stepped, and whether it stopped early."""

    train_time: float = 0.0
    train_samples: int = 0
    stopped_early: bool = False


def _train_loop(run: _Run, train: Sequence[SceneSample] | Iterable[SceneSample],
                progress: bool | Callable[[int], None]) -> _LoopStats:
    """Step until ``train.steps``, early stopping or the end of a one-shot stream; validate (and checkpoint) every
    ``eval_every`` steps and at the last; log the mean loss every ``log_every`` steps."""
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

    cfg, ranks, s = run.cfg, run.ranks, run.state
    bar = Progress(
        TextColumn("train"),
        BarColumn(),
        MofNCompleteColumn(),
        TextColumn("loss {task.fields[loss]:.4f}  val ADE {task.fields[ade]:.3f} FDE {task.fields[fde]:.3f}"),
        TimeRemainingColumn(),
        disable=progress is not True or not ranks.main,
    )
    task = bar.add_task("train", total=cfg.steps, completed=s.step, loss=math.nan, ade=s.best_ade, fde=s.best_fde)
    advance = progress if callable(progress) and ranks.main else None
    if advance is not None:
        report_total(advance, cfg.steps)
        advance(s.step)  # a resumed run starts where it stopped
    stats = _LoopStats()
    loss_sum, loss_n = 0.0, 0
    run.net.train()
    batches = training_batches(train, cfg, s.epoch, s.pos_in_epoch)
    with bar:
        while s.step < cfg.steps:
            try:
                s.epoch, s.pos_in_epoch, chunk = next(batches)
            except StopIteration:
                run.log.write("stream_end", step=s.step)
                break
            t0 = time.perf_counter()
            chunk = chunk[ranks.rank :: ranks.world]
            loss = run.train_step(chunk)
            stats.train_time += time.perf_counter() - t0
            stats.train_samples += len(chunk)
            loss_sum += loss.item()
            loss_n += 1
            if s.step % cfg.log_every == 0:
                run.log.write("train", step=s.step, loss=loss_sum / loss_n, lr=run.optimizer.param_groups[0]["lr"],
                              samples_per_s=stats.train_samples / max(stats.train_time, 1e-9))
                loss_sum, loss_n = 0.0, 0
            bar.update(task, completed=s.step, loss=loss.item())
            if advance is not None:
                advance(1)
            if s.step % cfg.eval_every == 0 or s.step == cfg.steps:
                if run.validate():
                    bar.update(task, ade=s.best_ade, fde=s.best_fde)
                patience_spent = bool(cfg.early_stop_patience) and s.bad_evals >= cfg.early_stop_patience
                if ranks.agree(patience_spent and s.step >= cfg.early_stop_min_steps):
                    stats.stopped_early = True
                    run.log.write("early_stop", step=s.step, best_step=s.best_step)
                    break
    return stats


@leaves_process_group
def fit(  # noqa: PLR0913  public entry: keyword options mirror `logpipe train`'s
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
        device: where the network trains and validates (``model.training.device.resolve_device``: ``cpu``, ``cuda`` or
            ``auto``). On CUDA the forward passes run under autocast (bf16, else fp16 with a gradient scaler whose
            scale is not checkpointed, so a resumed fp16 run re-learns it); batches, shuffling, augmentation and
            noise are drawn on the CPU as before, and checkpoints hold the same CPU tensors on every device.
            Data-parallel runs (torchrun, gloo) are CPU only.
    """
    start_time = time.perf_counter()
    ranks = Ranks.from_env()
    cfg, dev, train, val = _prepare(train, val, config, ranks, device)
    if cfg.num_threads > 0:
        torch.set_num_threads(cfg.num_threads)
    if init_from is not None:
        read_meta(init_from)  # a bad source fails before the run folder is made
    out_dir.mkdir(parents=True, exist_ok=True)
    run = _Run(cfg, out_dir, ranks, dev, val, dataset_kind=dataset_kind, manifest_hash=manifest_hash,
               training_data=training_data, start_time=start_time)
    run.restore(resume)
    s = run.state
    warm = run.warm_start(init_from) if init_from is not None and s.resumed_at_step is None else None
    if ranks.main:
        save_config(cfg, out_dir / "config.json")
    run.log.write("start", step=s.step, config=config_to_dict(cfg), processes=ranks.world, device=str(dev),
                  **({"init_from": warm} if warm is not None else {}))
    stats = _train_loop(run, train, progress)
    if ranks.main and (not (run.last_dir / "meta.json").exists() or read_meta(run.last_dir).step != s.step):
        run.validate()
    elapsed = time.perf_counter() - start_time
    rate = stats.train_samples / stats.train_time if stats.train_time > 0 else 0.0
    cache = run.cache
    run.log.write("end", step=s.step, best_step=s.best_step, best_val_ade=s.best_ade, elapsed_s=elapsed,
                  samples_per_s=rate, **({"backbone_cache": asdict(cache.stats)} if cache is not None else {}))
    return TrainResult(
        out_dir=out_dir,
        best_checkpoint=run.best_dir if (run.best_dir / "meta.json").exists() else None,
        last_checkpoint=run.last_dir,
        log_path=run.log.path,
        config=cfg,
        steps=s.step,
        best_step=s.best_step,
        best_val_ade=s.best_ade if math.isfinite(s.best_ade) else math.nan,
        best_val_fde=s.best_fde if math.isfinite(s.best_fde) else math.nan,
        stopped_early=stats.stopped_early,
        elapsed_s=elapsed,
        train_samples_per_s=rate,
        weights_sha256=_weights_digest(run.net),
        processes=ranks.world,
        total_elapsed_s=s.earlier_elapsed + elapsed,
        resumed_at_step=s.resumed_at_step,
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
