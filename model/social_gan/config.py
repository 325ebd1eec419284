"""Social-GAN's settings (``SocialGanConfig``) and its two published variants, ``social_gan_20v`` (no pooling) and
``social_gan_20vp`` (the pooling module); where each figure comes from is in the package docstring."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

from logpipe.errors import LogpipeError

from ..training.config_table import WindowSchedule, read_table, typed_config

MODEL_KIND = "social_gan"
PRESETS = ("social_gan_20v", "social_gan_20vp")


@dataclass(frozen=True)
class SocialGanConfig(WindowSchedule):
    """Network, losses and schedule (see the package docstring for the source of each value)."""

    pooling: bool = False
    embedding_dim: int = 16
    encoder_h_dim: int = 16
    decoder_h_dim: int = 32
    discriminator_h_dim: int = 64
    mlp_dim: int = 64
    bottleneck_dim: int = 32
    pool_hidden_dim: int = 512
    pool_batch_norm: bool = False
    context_batch_norm: bool = False
    noise_dim: int = 8
    best_k: int = 20
    l2_loss_weight: float = 1.0
    g_learning_rate: float = 1e-3
    d_learning_rate: float = 1e-3
    g_steps: int = 1
    d_steps: int = 2
    clipping_threshold_g: float = 1.5
    clipping_threshold_d: float = 0.0
    batch_size: int = 64

    @classmethod
    def from_dict(cls, data: dict[str, Any], where: str) -> SocialGanConfig:
        """Parse a config table; an unknown key or a value of the wrong type is an error naming ``where``."""
        return _typed(cls, data, where)


def preset_config(name: str) -> SocialGanConfig:
    """The config of a published variant: 20V-20 (no pooling) or 20VP-20 (pooling, with batch norm in the
    generator's MLPs: a labelled deviation, see the package docstring)."""
    if name not in PRESETS:
        raise LogpipeError(f"unknown Social-GAN preset {name!r}; presets: {', '.join(PRESETS)}")
    pooling = name == "social_gan_20vp"
    return SocialGanConfig(pooling=pooling, pool_batch_norm=pooling, context_batch_norm=pooling)


def load_config(name: str, config_path: Path | None, overrides: dict[str, Any] | None) -> SocialGanConfig:
    """The preset, then the ``[social_gan]`` table of ``config_path`` (if any), then ``overrides``."""
    config = preset_config(name)
    table = read_table(config_path, MODEL_KIND)
    merged = {**config.to_dict(), **table, **(overrides or {})}
    return SocialGanConfig.from_dict(merged, str(config_path or "--preset " + name))


def _typed(cls: type[SocialGanConfig], data: dict[str, Any], where: str) -> SocialGanConfig:
    config = typed_config(cls, data, where, "Social-GAN")
    if min(config.best_k, config.batch_size, config.steps, config.val_every, config.obs_len, config.pred_len) < 1:
        raise LogpipeError(f"{where}: best_k, batch_size, steps, val_every, obs_len and pred_len must be >= 1")
    if config.noise_dim >= config.decoder_h_dim:
        raise LogpipeError(f"{where}: noise_dim must be below decoder_h_dim (the noise fills part of its state)")
    return config
