"""The config a ``logpipe train`` run trains with (``logpipe.model.zhu2020.train_config``): file, overrides, preset and
the protocol's steps, applied in that order."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import pytest

from logpipe.model.zhu2020.config import PRESETS, ConfigError, ModelConfig, TrainConfig, load_config
from logpipe.model.zhu2020.train_config import train_config, with_preset, with_protocol_lengths
from logpipe.types import SampleProtocol

REPO = Path(__file__).resolve().parents[2]


def test_no_position_preset_is_the_full_model_without_pf() -> None:
    full, ablation = PRESETS["full"], PRESETS["no_position"]
    assert not ablation.position and ablation == replace(full, position=False)
    config = with_preset(TrainConfig(model=ModelConfig(noise_dim=4)), "no_position")
    assert config.model.features == ablation and config.model.noise_dim == 4 and config.num_modes == 20


def test_lstm_preset_draws_one_mode_and_keeps_the_schedule() -> None:
    shipped = load_config(REPO / "configs" / "ethucy.toml")
    config = with_preset(shipped, "lstm")
    assert (config.model.noise_dim, config.num_modes, config.val_modes) == (0, 1, 1)
    assert config.model.constant_velocity_modes == 0 and not any(vars(config.model.features).values())
    assert (config.steps, config.lr, config.batch_size) == (shipped.steps, shipped.lr, shipped.batch_size)


def test_overrides_apply_before_the_preset() -> None:
    path = REPO / "configs" / "ethucy.toml"
    config = train_config(path, {"steps": 7, "num_modes": 5}, "baseline")
    assert config.steps == 7 and config.num_modes == 5 and config.model.features == PRESETS["baseline"]
    assert train_config(path, None, None) == load_config(path)
    assert train_config(None, None, None) == TrainConfig()
    # The preset comes last: a lstm preset overrides the num_modes an override asked for.
    assert train_config(path, {"num_modes": 5}, "lstm").num_modes == 1
    with pytest.raises(ConfigError, match="unknown preset"):
        train_config(None, None, "v9")


def test_protocol_lengths_replace_the_models_only_when_they_differ() -> None:
    config = TrainConfig()
    same = SampleProtocol("custom", obs_len=config.model.obs_len, pred_len=config.model.pred_len)
    assert with_protocol_lengths(config, same) is config
    other = with_protocol_lengths(config, SampleProtocol("custom", obs_len=3, pred_len=5))
    assert (other.model.obs_len, other.model.pred_len) == (3, 5)
    assert other.model == replace(config.model, obs_len=3, pred_len=5) and other.steps == config.steps
