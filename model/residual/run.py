"""``logpipe train`` for the residual driving model (a config with a ``[residual]`` table): the datasets' split
samples with their rasters → targets (``residual_fit.collect``) → ``fit_residual`` into the run folder, holding its
lock; returns the same summary as the paper's network's training.

Several datasets train one model (as for the paper's network): the splits apply in each (a dataset where a split
selects no log adds none), each dataset with its only raster run (or the one named), and the checkpoint records
every format and the union of the recordings. A run starts afresh (no ``--resume``: runs are minutes long);
``--init-from`` fine-tunes a residual checkpoint of the same architecture.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any, cast

from logpipe.dataset.locations import window_locations
from logpipe.dataset.reader import Dataset
from logpipe.errors import LogpipeError
from logpipe.raster.runs import find_raster_run
from logpipe.storage.io import sha256_file
from logpipe.summaries import TrainSummary
from logpipe.types import SceneSample

from ..checkpoint.format import TrainingData, combined_kind, combined_manifest_hash
from ..training.run_folder import run_folder
from ..training.splits import logs_filter, split_logs
from .config import load_residual_config
from .fit import collect, fit_residual, target_locations


def _split_samples(datasets: Sequence[Dataset], split: str, raster_run: str | None, environment: bool
                   ) -> tuple[list[SceneSample], list[list[str]]]:
    """Samples (with rasters when the environment net is on) of ``split`` in each dataset, and its logs."""
    logs = split_logs(datasets, split)
    samples: list[SceneSample] = []
    for ds, ids in zip(datasets, logs, strict=True):
        if not ids:
            continue
        run = find_raster_run(ds.root, raster_run, None) if environment else None
        if environment and run is None:
            raise LogpipeError(f"{ds.root}: no raster run; the residual model's environment net needs one (`logpipe "
                               "rasterise DS --rotate`), or set environment = false in the config")
        for sample in ds.iter_scene_samples(logs_filter(ids)):
            if run is not None:
                sample.raster, sample.world_to_raster = run.get(sample.sample_id)
            samples.append(sample)
    return samples, logs


def train_residual(  # noqa: PLR0913  the command's options one to one
    datasets: Sequence[Dataset], out_dir: Path, config_path: Path, *, train_split: str, val_split: str | None,
    overrides: dict[str, Any] | None = None, raster_run: str | None = None, init_from: Path | None = None,
    progress: Callable[[int], None] | None = None,
) -> TrainSummary:
    """Train the residual model (see the module docstring)."""
    started = time.perf_counter()
    config = load_residual_config(config_path, overrides)
    protocol = datasets[0].protocol
    config = replace(config, obs_len=protocol.obs_len, pred_len=protocol.pred_len)
    train_samples, train_logs = _split_samples(datasets, train_split, raster_run, config.environment)
    val_samples, val_logs = (_split_samples(datasets, val_split, raster_run, config.environment) if val_split
                             else ([], [[] for _ in datasets]))
    train, windows = collect(train_samples, config)
    val, val_windows = collect(val_samples, config) if val_samples else (None, None)
    training_data = TrainingData.of_logs(list(zip(datasets, train_logs, val_logs, strict=True)), train_split, val_split)
    manifests = combined_manifest_hash([sha256_file(d.root / "manifest.json") for d in datasets])
    with run_folder(out_dir):
        result = fit_residual(train, windows, val, config, out_dir,
                              dataset_kind=combined_kind([d.kind for d in datasets]), manifest_hash=manifests,
                              training_data=training_data, init_from=init_from, progress=progress,
                              locations=window_locations([d.logs() for d in datasets],
                                                         [s.log_id for s in train_samples]),
                              val_locations=target_locations([d.logs() for d in datasets], val_samples, val_windows))
    several = len(datasets) > 1
    k = config.modes + 1
    return cast(TrainSummary, {
        "dataset": [str(d.root) for d in datasets] if several else str(datasets[0].root), "run": str(out_dir),
        "train_split": train_split, "val_split": val_split, "train_samples": len(train_samples),
        "val_samples": len(val_samples), "steps": result.steps, "best_step": result.best_step,
        "best_val_ade": result.best_metrics.get("ade", float("nan")),
        "best_val_fde": result.best_metrics.get("fde", float("nan")), "stopped_early": result.stopped_early,
        "best_checkpoint": str(result.best_checkpoint), "last_checkpoint": str(result.last_checkpoint),
        "train_samples_per_s": round(result.targets_per_s * len(train_samples) / max(len(train), 1), 1),
        "raster_run": raster_run, "init_from": str(init_from) if init_from else None,
        "environment_net": config.environment, "device": "cpu", "seconds": round(time.perf_counter() - started, 1),
        "best_val_min_fde": result.best_metrics.get(f"min_fde_{k}", float("nan")),
    })
