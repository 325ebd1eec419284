"""``logpipe train``: fit the predictor on a dataset's samples (or on several datasets' together).

Driving data without ``--config`` trains the shipped driving default's recipe (``model.residual.fleet``); a
``[residual]`` config the residual model (``model.residual.run``); ``--preset social_*`` a social baseline
(``model.social``). Otherwise: open the dataset(s) → the config (``model.zhu2020.train_config``) → the train and
validation logs (``eth/train``, ``hash/…``, in each dataset) → their ``SceneSample``s (in dataset order, each with
its raster run) → ``model.zhu2020.fit.fit`` in the run folder's lock (checkpoints, log, early stop, resume) → a summary.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, cast

import pyarrow as pa
import pyarrow.compute as pc

from logpipe.dataset.reader import Dataset
from logpipe.errors import DatasetError, LogpipeError
from logpipe.raster.runs import RasterShards, find_raster_run
from logpipe.storage.io import sha256_file
from logpipe.summaries import TrainPerDataset, TrainResumed, TrainSummary
from logpipe.types import SceneSample

if TYPE_CHECKING:
    from logpipe.model.zhu2020.config import TrainConfig
    from logpipe.model.zhu2020.fit import TrainResult


def scene_samples(
    dataset: Dataset, split: str, limit: int | None = None, rasters: RasterShards | None = None
) -> list[SceneSample]:
    """The ``SceneSample``s of every sample whose log is in ``split`` (at most ``limit``, in index order), with
    their map rasters when a raster run is given."""
    samples = _log_samples(dataset, dataset.logs_in_split(split), rasters, limit)
    if not samples:
        raise LogpipeError(f"{dataset.root}: split {split!r} has logs but no prediction samples")
    return samples


def _log_samples(
    dataset: Dataset, logs: Sequence[str], rasters: RasterShards | None, limit: int | None = None
) -> list[SceneSample]:
    """The ``SceneSample``s of the logs ``logs`` of ``dataset`` (see ``scene_samples``)."""
    if not logs:
        return []
    keep = pc.is_in(pc.field("log_id"), value_set=pa.array(logs))
    samples: list[SceneSample] = []
    for sample in dataset.iter_scene_samples(keep):
        if rasters is not None:
            sample.raster, sample.world_to_raster = rasters.get(sample.sample_id)
        samples.append(sample)
        if limit is not None and len(samples) >= limit:
            break
    return samples


def train(  # noqa: PLR0913  stage entry: keyword options mirror `logpipe train` one to one
    dataset_dir: Path | Sequence[Path],
    out_dir: Path,
    *,
    train_split: str | None,
    val_split: str | None,
    config_path: Path | None = None,
    overrides: dict[str, Any] | None = None,
    preset: str | None = None,
    raster_run: str | None = None,
    loader_workers: int = 0,
    resume: bool = False,
    progress: bool | Callable[[int], None] = True,
    init_from: Path | None = None,
    device: str = "auto",
) -> TrainSummary:
    """Train on ``train_split`` of ``dataset_dir``, validating on ``val_split``; returns the run summary.

    Args:
        dataset_dir: an ingested dataset, or several trained on together (splits apply in each; samples in the
            order given, each with its own raster run; the checkpoints record every format and recording).
        out_dir: the run folder (checkpoints ``best/`` and ``last/``, ``train_log.jsonl``, ``config.toml``).
        train_split: e.g. ``eth/train`` (ETH/UCY leave-one-scene-out) or ``hash/train``; None: driving data
            without a config picks its own validation data (``model.residual.fleet``), other data ``hash/train``.
        val_split: e.g. ``eth/val``; None trains without validation (no early stopping).
        config_path: TOML/JSON with every hyper-parameter (defaults: on driving data, the shipped driving
            default's recipe, ``model.residual.fleet``; elsewhere the paper's).
        overrides: ``TrainConfig`` fields to replace (``{"steps": 50}``); preset: a row of the paper's tables, or a
            social baseline (``social_lstm``, ``social_gan_20v``, ``social_gan_20vp``: ``model.social``).
        raster_run: the raster run under ``DATASET/rasters/`` (default: the only one; none: environment net off).
        loader_workers: 0 cuts every training sample into memory first (exact resume); N > 0 streams them from
            the shards through a DataLoader of N workers (memory bounded by a shard per worker).
        resume: continue from ``out_dir/last``.
        progress: True: ``fit``'s progress bar (a terminal); a callable: ``logpipe.progress`` callback (steps).
        init_from: start a new run from this checkpoint folder (``model.zhu2020.checkpoint.warm_start``).
        device: ``auto`` (CUDA when torch can use a GPU, else the CPU), ``cpu`` or ``cuda`` (autocast there).
    """
    from logpipe.model.checkpoint.format import TrainingData, combined_kind, combined_manifest_hash
    from logpipe.model.registry import driving_recipe
    from logpipe.model.residual.config import is_residual_config
    from logpipe.model.residual.run import train_residual
    from logpipe.model.social import train_social
    from logpipe.model.training.run_folder import run_folder, train_device
    from logpipe.model.zhu2020.fit import fit
    from logpipe.model.zhu2020.train_config import train_config, with_protocol_lengths

    started, callback = time.perf_counter(), progress if callable(progress) else None
    torch_device = train_device(device)  # a bad --device fails before any data is read
    datasets = _open_datasets([dataset_dir] if isinstance(dataset_dir, Path) else list(dataset_dir))
    _check_lengths(datasets)  # one model: every dataset's windows of the same steps, which the config takes
    recipe = driving_recipe(datasets) if config_path is None and preset is None else None
    if recipe is not None:  # driving data without a config: the shipped driving default's recipe
        from logpipe.model.residual.fleet import train_fleet

        paper_only = [name for name, given in (("--steps", "steps" in (overrides or {})), ("--resume", resume), (
            "--loader-workers", loader_workers > 0)) if given]
        return cast(TrainSummary, train_fleet(
            datasets, out_dir, shipped=recipe, train_split=train_split, val_split=val_split, raster_run=raster_run,
            paper_only=paper_only, seed=(overrides or {}).get("seed"), init_from=init_from, progress=callback))
    train_split, val_split = train_split or "hash/train", val_split if train_split else "hash/val"
    summary: TrainSummary | None = None
    if preset is not None and preset.startswith("social_"):  # Social-LSTM / Social-GAN baselines (issue 63)
        summary = train_social(preset, datasets, out_dir, train_split=train_split, val_split=val_split,
                               config_path=config_path, overrides=overrides, progress=callback, resume=resume)
    elif config_path is not None and is_residual_config(config_path):  # the residual driving model (our extension)
        summary = train_residual(datasets, out_dir, config_path, train_split=train_split, val_split=val_split,
                                 overrides=overrides, raster_run=raster_run, init_from=init_from, progress=callback)
    if summary is not None:
        return summary
    config = train_config(config_path, overrides, preset)
    config = with_protocol_lengths(config, datasets[0].protocol)
    inputs = _resolve_inputs(datasets, config, train_split, val_split, raster_run, loader_workers)
    with run_folder(out_dir):
        result = fit(
            inputs.train_samples, inputs.val_samples, config, out_dir, resume=resume, progress=progress,
            dataset_kind=combined_kind([ds.kind for ds in datasets]),
            manifest_hash=combined_manifest_hash([sha256_file(ds.root / "manifest.json") for ds in datasets]),
            init_from=init_from,
            training_data=TrainingData.of_logs(list(zip(datasets, inputs.train_logs, inputs.val_logs, strict=True)),
                                               train_split, val_split),
            device=torch_device,
        )
    return _summary(dataset_dir, out_dir, inputs, result, init_from, started)


@dataclass
class _Inputs:
    """What a run trains and validates on: per dataset (in the order given) its raster run, logs and samples."""

    datasets: list[Dataset]
    runs: list[RasterShards | None]
    train_split: str
    val_split: str | None
    train_logs: list[list[str]]
    val_logs: list[list[str]]
    train_samples: Sequence[SceneSample] | Iterable[SceneSample]
    train_counts: list[int | str]
    """Samples each dataset gave, ``streamed`` for a dataset streamed through a DataLoader."""
    val_samples: list[SceneSample] | None
    val_counts: list[int | str]


def _resolve_inputs(datasets: list[Dataset], config: TrainConfig, train_split: str, val_split: str | None,
                    raster_run: str | None, loader_workers: int) -> _Inputs:
    """Each dataset's raster run (checked against the environment net), train/val logs and samples (in memory, or
    streamed from the shards with ``loader_workers`` > 0)."""
    runs = [find_raster_run(ds.root, raster_run, None) for ds in datasets]  # several unnamed runs: an error
    _check_rasters(datasets, runs, needed=config.model.features.environment)
    train_logs = _split_logs(datasets, train_split)
    val_logs = _split_logs(datasets, val_split) if val_split else [[] for _ in datasets]
    train_samples: Sequence[SceneSample] | Iterable[SceneSample]
    train_counts: list[int | str]
    if loader_workers > 0:
        from logpipe.model.training.run_folder import ChainedScenes
        from logpipe.model.training.scene_stream import scene_loader

        loaders = [scene_loader(ds.root, logs, workers=loader_workers,
                                raster_run=run.run_dir.name if run is not None else None)
                   for ds, logs, run in zip(datasets, train_logs, runs, strict=True) if logs]
        train_samples = loaders[0] if len(loaders) == 1 else ChainedScenes(loaders)
        train_counts = ["streamed" if logs else 0 for logs in train_logs]
    else:
        train_samples, train_counts = _samples(datasets, train_logs, runs, train_split)
    val_samples, val_counts = _samples(datasets, val_logs, runs, val_split) if val_split else (None, [])
    return _Inputs(datasets, runs, train_split, val_split, train_logs, val_logs, train_samples, train_counts,
                   val_samples, val_counts)


def _summary(dataset_dir: Path | Sequence[Path], out_dir: Path, inputs: _Inputs, result: TrainResult,
             init_from: Path | None, started: float) -> TrainSummary:
    """The run summary ``train`` returns (and ``logpipe train --json`` prints)."""
    datasets, runs, val_counts, val_samples = inputs.datasets, inputs.runs, inputs.val_counts, inputs.val_samples
    several = len(datasets) > 1
    per_dataset: TrainPerDataset = (
        {"per_dataset": [{"dataset": str(ds.root), "format": ds.kind, "train_samples": n,
                          "val_samples": val_counts[i] if val_counts else 0}
                         for i, (ds, n) in enumerate(zip(datasets, inputs.train_counts, strict=True))]}
        if several else {})
    # A resumed run: where this part started, and the wall time of all parts (None: an earlier part had no clock).
    resumed: TrainResumed = (
        {"resumed_at_step": result.resumed_at_step,
         "seconds_total": round(result.total_elapsed_s, 1) if math.isfinite(result.total_elapsed_s) else None}
        if result.resumed_at_step is not None else {})
    return {
        # With several datasets: their folders and raster runs as lists, and the samples each gave.
        "dataset": [str(ds.root) for ds in datasets] if several else str(dataset_dir),
        **per_dataset,
        "run": str(out_dir), "train_split": inputs.train_split, "val_split": inputs.val_split,
        "train_samples": len(inputs.train_samples) if isinstance(inputs.train_samples, list) else "streamed",
        "val_samples": len(val_samples) if val_samples else 0,
        "steps": result.steps, "best_step": result.best_step,
        "best_val_ade": result.best_val_ade, "best_val_fde": result.best_val_fde,
        "stopped_early": result.stopped_early,
        "best_checkpoint": str(result.best_checkpoint) if result.best_checkpoint else None,
        "last_checkpoint": str(result.last_checkpoint),
        "train_samples_per_s": round(result.train_samples_per_s, 1),
        "raster_run": ([r.run_dir.name if r is not None else None for r in runs] if several
                       else runs[0].run_dir.name if runs[0] is not None else None),
        "init_from": str(init_from) if init_from is not None and result.resumed_at_step is None else None,
        "environment_net": result.config.model.features.environment,
        "device": result.device,
        "seconds": round(time.perf_counter() - started, 1),
        **resumed,
    }


def _open_datasets(folders: Sequence[Path]) -> list[Dataset]:
    """The datasets to train on, in the order given (one given twice would count its samples twice)."""
    if not folders:
        raise LogpipeError("give at least one dataset")
    seen: set[Path] = set()
    for folder in folders:
        if folder.resolve() in seen:
            raise LogpipeError(f"{folder}: dataset given twice")
        seen.add(folder.resolve())
    return [Dataset.open(folder) for folder in folders]


def _check_lengths(datasets: Sequence[Dataset]) -> None:
    """Datasets trained together must cut windows of the same observed + predicted steps (one model)."""
    first = datasets[0].protocol
    for ds in datasets[1:]:
        p = ds.protocol
        if (p.obs_len, p.pred_len) != (first.obs_len, first.pred_len):
            raise LogpipeError(f"{ds.root}: samples of {p.obs_len}+{p.pred_len} steps ({p.name}) but "
                               f"{datasets[0].root} has {first.obs_len}+{first.pred_len} ({first.name}); "
                               "re-index one with `logpipe index --obs N --pred N`")


def _check_rasters(datasets: Sequence[Dataset], runs: Sequence[RasterShards | None], *, needed: bool) -> None:
    """With the environment net on, no dataset has rasters (it is then off) or every one has a run of one setting."""
    if not needed or len(datasets) < 2:
        return
    have = [str(ds.root) for ds, run in zip(datasets, runs, strict=True) if run is not None]
    missing = [str(ds.root) for ds, run in zip(datasets, runs, strict=True) if run is None]
    if have and missing:
        raise LogpipeError(f"{', '.join(missing)}: no raster run, but {', '.join(have)} has one and the "
                           "environment net needs a raster for every sample; rasterise it (`logpipe rasterise`) "
                           "or train without the environment net (--preset v4)")
    # Run folder names hash every raster setting, so equal names mean equal settings.
    names = {run.run_dir.name for run in runs if run is not None}
    if len(names) > 1:
        shown = "; ".join(f"{ds.root}: {run.run_dir.name}" for ds, run in zip(datasets, runs, strict=True)
                          if run is not None)
        raise LogpipeError(f"raster runs made with different settings ({shown}); rasterise every dataset with the "
                           "same size, extent, channels, rotation and centre")


def _split_logs(datasets: Sequence[Dataset], split: str) -> list[list[str]]:
    """The logs of ``split`` in each dataset; with several, one where it selects none adds none (an error in all)."""
    if len(datasets) == 1:
        return [datasets[0].logs_in_split(split)]
    found: list[list[str]] = []
    errors: list[str] = []
    for ds in datasets:
        try:
            found.append(ds.logs_in_split(split))
        except DatasetError as exc:
            found.append([])
            errors.append(str(exc))
    if not any(found):
        raise DatasetError("; ".join(errors))
    return found


def _samples(datasets: Sequence[Dataset], logs: Sequence[Sequence[str]], runs: Sequence[RasterShards | None],
             split: str) -> tuple[list[SceneSample], list[int | str]]:
    """The samples of each dataset's logs, concatenated in dataset order, and how many each gave."""
    samples: list[SceneSample] = []
    counts: list[int | str] = []
    for ds, ids, run in zip(datasets, logs, runs, strict=True):
        part = _log_samples(ds, ids, run)
        samples += part
        counts.append(len(part))
    if not samples:
        raise LogpipeError(f"{', '.join(str(ds.root) for ds in datasets)}: split {split!r} has logs but no "
                           "prediction samples")
    return samples, counts

