"""Social-LSTM's settings (``SocialLstmConfig``), preset ``social_lstm``; where each figure comes from is in the
package docstring."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

from logpipe.errors import LogpipeError

from ..training.config_table import WindowSchedule, read_table, typed_config

MODEL_KIND = "social_lstm"
PRESETS = ("social_lstm",)


@dataclass(frozen=True)
class SocialLstmConfig(WindowSchedule):
    """Network, pooling grid and schedule (see the package docstring for the source of each value)."""

    embedding_dim: int = 64
    hidden_dim: int = 128
    grid_size: int = 8
    neighbourhood_m: float = 2.0
    learning_rate: float = 3e-3
    clip_grad_norm: float = 10.0
    batch_size: int = 32

    @classmethod
    def from_dict(cls, data: dict[str, Any], where: str) -> SocialLstmConfig:
        """Parse a config table; an unknown key or a value of the wrong type is an error naming ``where``."""
        config = typed_config(cls, data, where, "Social-LSTM")
        if min(config.grid_size, config.batch_size, config.steps, config.val_every, config.obs_len,
               config.pred_len) < 1 or not config.neighbourhood_m > 0:
            raise LogpipeError(f"{where}: grid_size, batch_size, steps, val_every, obs_len, pred_len and "
                               "neighbourhood_m must be positive")
        return config


def load_config(name: str, config_path: Path | None, overrides: dict[str, Any] | None) -> SocialLstmConfig:
    """The published settings, then the ``[social_lstm]`` table of ``config_path`` (if any), then ``overrides``."""
    if name not in PRESETS:
        raise LogpipeError(f"unknown Social-LSTM preset {name!r}; presets: {', '.join(PRESETS)}")
    table = read_table(config_path, MODEL_KIND)
    merged = {**SocialLstmConfig().to_dict(), **table, **(overrides or {})}
    return SocialLstmConfig.from_dict(merged, str(config_path or "--preset " + name))
