"""The ``TrainConfig`` a ``logpipe train`` run trains with: the config file (or the paper's defaults), the
command's overrides and preset, and the observed/predicted steps of the dataset's protocol.

Steps are protocol steps (``SampleProtocol.obs_len`` / ``pred_len``); the preset rows are those of
``config.PRESETS`` (the paper's Table 4 ablations and baselines).
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

from logpipe.types import SampleProtocol

from .config import TrainConfig, load_config, preset


def train_config(config_path: Path | None, overrides: dict[str, Any] | None, preset_name: str | None) -> TrainConfig:
    """The config file (``load_config``; None: the paper's defaults) with ``overrides`` (``TrainConfig``
    fields) and then the preset ``preset_name`` (``with_preset``) applied."""
    config = load_config(config_path) if config_path else TrainConfig()
    if overrides:
        config = dataclasses.replace(config, **overrides)
    if preset_name is not None:
        config = with_preset(config, preset_name)
    return config


def with_preset(config: TrainConfig, name: str) -> TrainConfig:
    """``config`` with the features (and noise) of preset ``name``; every other setting is kept, so a baseline
    trains with the same schedule, data and augmentation as the method it is compared with."""
    row = preset(name)
    if row.noise_dim:
        return dataclasses.replace(config, model=dataclasses.replace(config.model, features=row.features))
    # Without noise all modes are equal: one is drawn, so none is held at constant velocity.
    model = dataclasses.replace(config.model, features=row.features, noise_dim=0, constant_velocity_modes=0)
    return dataclasses.replace(config, model=model, num_modes=1, val_modes=1)


def with_protocol_lengths(config: TrainConfig, protocol: SampleProtocol) -> TrainConfig:
    """``config`` with the model's observed and predicted steps those of ``protocol`` (the samples'
    windows), unchanged when they already are."""
    if (config.model.obs_len, config.model.pred_len) == (protocol.obs_len, protocol.pred_len):
        return config
    return dataclasses.replace(
        config, model=dataclasses.replace(config.model, obs_len=protocol.obs_len, pred_len=protocol.pred_len)
    )
