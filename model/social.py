"""The social baselines the paper compares with (issue 63): ``logpipe train --preset social_lstm | social_gan_20v |
social_gan_20vp`` trains one (``model.social_lstm``, ``model.social_gan``) on a dataset's split, and ``logpipe
predict --checkpoint`` finds its family by the checkpoint's ``model_kind`` (``registry``).

Every dataset kind the other baselines run on is accepted (ETH/UCY, ApolloScape, the driving formats): the
networks read tracks only (no map), and take the window lengths of the dataset's protocol.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, cast

from logpipe.dataset.reader import Dataset
from logpipe.errors import LogpipeError
from logpipe.storage.io import sha256_file
from logpipe.summaries import TrainSummary
from logpipe.types import SceneSample

from .checkpoint.format import TrainingData, combined_kind, combined_manifest_hash
from .checkpoint.weights_folder import WeightsMeta
from .training.splits import logs_filter, split_logs

SOCIAL_PRESETS = ("social_lstm", "social_gan_20v", "social_gan_20vp")
SOCIAL_KINDS = ("social_lstm", "social_gan")
"""``model_kind`` of their checkpoints (``meta.json``)."""


def split_samples(datasets: Sequence[Dataset], split: str) -> tuple[list[SceneSample], list[list[str]]]:
    """The samples of ``split`` in each dataset (a dataset where it selects no log adds none) and its logs."""
    logs = split_logs(datasets, split)
    samples: list[SceneSample] = []
    for ds, ids in zip(datasets, logs, strict=True):
        if ids:
            samples += ds.iter_scene_samples(logs_filter(ids))
    return samples, logs


def train_social(  # noqa: PLR0913  keyword options mirror `logpipe train` one to one
    preset: str, datasets: Sequence[Dataset], out_dir: Path, *, train_split: str, val_split: str | None,
    config_path: Path | None = None, overrides: dict[str, Any] | None = None,
    progress: Callable[[int], None] | None = None, resume: bool = False,
) -> TrainSummary:
    """Train the baseline ``preset`` (see the module docstring), or with ``resume`` go on from ``out_dir/last``
    (``model.training.window_loop``); returns ``logpipe train``'s summary."""
    started = time.perf_counter()
    protocol = datasets[0].protocol
    lengths = {"obs_len": protocol.obs_len, "pred_len": protocol.pred_len}
    train, train_logs = split_samples(datasets, train_split)
    val, val_logs = split_samples(datasets, val_split) if val_split else ([], [[] for _ in datasets])
    if not train:
        raise LogpipeError(f"split {train_split!r} has logs but no prediction samples")
    meta = WeightsMeta(model_kind="", config={}, dataset_kind=combined_kind([d.kind for d in datasets]),
                       manifest_hash=combined_manifest_hash([sha256_file(d.root / "manifest.json") for d in datasets]),
                       obs_len=protocol.obs_len, pred_len=protocol.pred_len, step=0,
                       training_data=TrainingData.of_logs(list(zip(datasets, train_logs, val_logs, strict=True)),
                                                          train_split, val_split))
    from .training.run_folder import run_folder

    with run_folder(out_dir):
        if preset == "social_lstm":
            from .social_lstm.config import load_config as lstm_config
            from .social_lstm.fit import train_social_lstm

            result = train_social_lstm(train, val, lstm_config(preset, config_path, {**(overrides or {}), **lengths}),
                                       out_dir, meta, progress, resume=resume)
        elif preset in SOCIAL_PRESETS:
            from .social_gan.config import load_config as gan_config
            from .social_gan.fit import train_social_gan

            result = train_social_gan(train, val, gan_config(preset, config_path, {**(overrides or {}), **lengths}),
                                      out_dir, meta, progress, resume=resume)
        else:
            raise LogpipeError(f"unknown social preset {preset!r}; presets: {', '.join(SOCIAL_PRESETS)}")
    several = len(datasets) > 1
    return cast(TrainSummary, {
        "dataset": [str(d.root) for d in datasets] if several else str(datasets[0].root), "run": str(out_dir),
        "train_split": train_split, "val_split": val_split, "train_samples": len(train), "val_samples": len(val),
        "steps": result.steps, "best_step": result.best_step,
        "best_val_ade": result.best_metrics.get("ade", float("nan")),
        "best_val_fde": result.best_metrics.get("fde", float("nan")), "stopped_early": result.stopped_early,
        "best_checkpoint": str(result.best_checkpoint) if result.best_checkpoint else None,
        "last_checkpoint": str(result.last_checkpoint), "train_samples_per_s": round(result.windows_per_s, 1),
        "raster_run": None, "init_from": None, "environment_net": False, "device": "cpu",
        "seconds": round(time.perf_counter() - started, 1), "preset": preset,
        **({"resumed_at_step": result.resumed_at_step, "seconds_total": round(result.total_seconds, 1)}
           if result.resumed_at_step is not None else {}),
    })


def load_social(folder: Path, kind: str) -> Any:
    """The ``Predictor`` of a social-baseline checkpoint folder of ``model_kind`` ``kind``."""
    if kind == "social_lstm":
        from .social_lstm.predictor import SocialLstmPredictor

        return SocialLstmPredictor.from_checkpoint(folder)
    from .social_gan.predictor import SocialGanPredictor

    return SocialGanPredictor.from_checkpoint(folder)
