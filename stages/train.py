"""``logpipe train``: fit the predictor on a dataset's samples.

Reads top-down: open the dataset → pick the train/validation logs (a folder split such as ``eth/train``, or
a ``hash/…`` split) → cut their samples into ``SceneSample``s → ``model.training.fit`` (checkpoints, the
JSON-lines log, early stopping, resume) → a summary.
"""

from __future__ import annotations

import dataclasses
import math
import os
import time
from collections.abc import Callable, Iterable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import pyarrow as pa
import pyarrow.compute as pc

from logpipe.artifact import FolderLock
from logpipe.dataset import Dataset
from logpipe.errors import LogpipeError
from logpipe.io import sha256_file
from logpipe.rasters import RASTER_DIR, RUN_MANIFEST, RasterShards, find_raster_run
from logpipe.types import SceneSample

if TYPE_CHECKING:
    from logpipe.model.config import TrainConfig


def scene_samples(
    dataset: Dataset, split: str, limit: int | None = None, rasters: RasterShards | None = None
) -> list[SceneSample]:
    """The ``SceneSample``s of every sample whose log is in ``split`` (at most ``limit``, in index order), with
    their map rasters when a raster run is given."""
    logs = dataset.logs_in_split(split)
    keep = pc.is_in(pc.field("log_id"), value_set=pa.array(logs))
    samples: list[SceneSample] = []
    for sample in dataset.iter_scene_samples(keep):
        if rasters is not None:
            sample.raster, sample.world_to_raster = rasters.get(sample.sample_id)
        samples.append(sample)
        if limit is not None and len(samples) >= limit:
            break
    if not samples:
        raise LogpipeError(f"{dataset.root}: split {split!r} has logs but no prediction samples")
    return samples


def train(
    dataset_dir: Path,
    out_dir: Path,
    *,
    train_split: str,
    val_split: str | None,
    config_path: Path | None = None,
    overrides: dict[str, Any] | None = None,
    preset: str | None = None,
    raster_run: str | None = None,
    loader_workers: int = 0,
    resume: bool = False,
    progress: bool | Callable[[int], None] = True,
    init_from: Path | None = None,
) -> dict[str, Any]:
    """Train on ``train_split`` of ``dataset_dir``, validating on ``val_split``; returns the run summary.

    Args:
        dataset_dir: an ingested dataset.
        out_dir: the run folder (checkpoints ``best/`` and ``last/``, ``train_log.jsonl``, ``config.toml``).
        train_split: e.g. ``eth/train`` (ETH/UCY leave-one-scene-out) or ``hash/train``.
        val_split: e.g. ``eth/val``; None trains without validation (no early stopping).
        config_path: TOML/JSON with every hyper-parameter (defaults: the paper's).
        overrides: ``TrainConfig`` fields to replace (e.g. ``{"steps": 50}``).
        preset: a row of the paper's tables applied over the config's model (``full``, ``v1``..``v4``,
            ``baseline`` = Noise-LSTM, ``lstm``); ``lstm`` has no noise, so it trains and validates with one mode.
        raster_run: the raster run under ``DATASET/rasters/`` to train the environment net on (default: the only
            one; none: the environment net is off).
        loader_workers: 0 cuts every training sample into memory first (exact resume); N > 0 streams them from
            the shards through a torch DataLoader with N worker processes (memory bounded by a shard per worker,
            shuffled through a buffer).
        resume: continue from ``out_dir/last``.
        progress: True: ``fit``'s progress bar (a terminal); a callable: ``logpipe.progress`` callback (steps).
        init_from: start a new run from this checkpoint folder (e.g. a Noise-LSTM checkpoint into the full
            model; see ``logpipe.model.checkpoints.warm_start``).
    """
    from logpipe.model.checkpoints import TrainingData
    from logpipe.model.config import TrainConfig, load_config
    from logpipe.model.training import fit

    started = time.perf_counter()
    dataset = Dataset.open(dataset_dir)
    config = load_config(config_path) if config_path else TrainConfig()
    if overrides:
        config = dataclasses.replace(config, **overrides)
    if preset is not None:
        config = with_preset(config, preset)
    protocol = dataset.protocol
    if (config.model.obs_len, config.model.pred_len) != (protocol.obs_len, protocol.pred_len):
        config = dataclasses.replace(
            config, model=dataclasses.replace(config.model, obs_len=protocol.obs_len, pred_len=protocol.pred_len)
        )
    rasters = _raster_run(dataset, raster_run)
    train_samples: Sequence[SceneSample] | Iterable[SceneSample]
    if loader_workers > 0:
        from logpipe.model.data import scene_loader

        train_samples = scene_loader(dataset.root, dataset.logs_in_split(train_split), workers=loader_workers,
                                     raster_run=rasters.run_dir.name if rasters is not None else None)
    else:
        train_samples = scene_samples(dataset, train_split, rasters=rasters)
    val_samples = scene_samples(dataset, val_split, rasters=rasters) if val_split else None
    # One training per run folder: under torchrun only process 0 writes, so only it holds the lock.
    lock = FolderLock(out_dir) if os.environ.get("RANK", "0") == "0" else None
    created = not out_dir.exists()
    if lock is not None:
        out_dir.mkdir(parents=True, exist_ok=True)
        lock.acquire()
    try:
        result = fit(
            train_samples,
            val_samples,
            config,
            out_dir,
            resume=resume,
            progress=progress,
            dataset_kind=dataset.kind,
            manifest_hash=sha256_file(dataset.root / "manifest.json"),
            init_from=init_from,
            training_data=TrainingData.of(dataset, train_split, val_split),
        )
    finally:
        if lock is not None:
            lock.release()
            if created and not any(out_dir.iterdir()):
                out_dir.rmdir()  # a run that could not start leaves no folder
    return {
        "dataset": str(dataset_dir),
        "run": str(out_dir),
        "train_split": train_split,
        "val_split": val_split,
        "train_samples": len(train_samples) if isinstance(train_samples, list) else "streamed",
        "val_samples": len(val_samples) if val_samples else 0,
        "steps": result.steps,
        "best_step": result.best_step,
        "best_val_ade": result.best_val_ade,
        "best_val_fde": result.best_val_fde,
        "stopped_early": result.stopped_early,
        "best_checkpoint": str(result.best_checkpoint) if result.best_checkpoint else None,
        "last_checkpoint": str(result.last_checkpoint),
        "train_samples_per_s": round(result.train_samples_per_s, 1),
        "raster_run": rasters.run_dir.name if rasters is not None else None,
        "init_from": str(init_from) if init_from is not None and result.resumed_at_step is None else None,
        "environment_net": result.config.model.features.environment,
        "seconds": round(time.perf_counter() - started, 1),
        # A resumed run: where this part started, and the training wall time of all parts (None for a run whose
        # earlier part predates the training state's clock).
        **({"resumed_at_step": result.resumed_at_step,
            "seconds_total": round(result.total_elapsed_s, 1) if math.isfinite(result.total_elapsed_s) else None}
           if result.resumed_at_step is not None else {}),
    }


def with_preset(config: TrainConfig, name: str) -> TrainConfig:
    """``config`` with the features (and noise) of preset ``name``; every other setting is kept, so a baseline
    trains with the same schedule, data and augmentation as the method it is compared with."""
    from logpipe.model.config import preset

    row = preset(name)
    if row.noise_dim:
        return dataclasses.replace(config, model=dataclasses.replace(config.model, features=row.features))
    # Without noise all modes are equal: one is drawn, so none is held at constant velocity.
    model = dataclasses.replace(config.model, features=row.features, noise_dim=0, constant_velocity_modes=0)
    return dataclasses.replace(config, model=model, num_modes=1, val_modes=1)


def _raster_run(dataset: Dataset, name: str | None) -> RasterShards | None:
    """The raster run to train on: ``name``, else the only finished one; several unnamed runs are an error."""
    root = dataset.root / RASTER_DIR
    runs = sorted(p.parent.name for p in root.glob(f"*/{RUN_MANIFEST}")) if root.is_dir() else []
    if name is None and len(runs) > 1:
        raise LogpipeError(f"{dataset.root}: several raster runs ({', '.join(runs)}); name one with --raster-run")
    return find_raster_run(dataset.root, name, None)
