"""Settings of the driving model's residual formulation (our extension of the paper, issue 57).

The network and its training read one frozen ``ResidualConfig``; a TOML file gives it as a ``[residual]`` table
(``configs/driving_residual.toml``), every key optional, unknown keys an error. Lengths are metres, times steps
of the protocol (10 Hz for the driving data) unless a name says otherwise.
"""

from __future__ import annotations

import dataclasses
import tomllib
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from logpipe.errors import LogpipeError

MODEL_KIND = "prior_residual"
"""``meta.json`` ``model_kind`` of a residual checkpoint (the paper's network is ``zhu2020``)."""


class ResidualConfigError(LogpipeError):
    """A residual config file or value is malformed."""


@dataclass(frozen=True)
class ResidualConfig:
    """Architecture, inputs and training of the residual driving model.

    Attributes:
        obs_len, pred_len: observed steps (the current one included) and predicted steps.
        modes: mode heads (K at most this + 1: the mean forecast is mode 0, then the heads as ``modes`` takes them).
        environment: the environment net (EN): a CNN over each target's raster crop in its own frame.
        crop_px, crop_res_m, crop_behind_m: the crop, crop_px x crop_px cells of crop_res_m metres, its back edge
            crop_behind_m behind the target (it looks ahead: 48 px of 1 m see 36 m ahead, 12 m behind, 24 m aside).
        neighbours: nearest agents (observed at the current step within neighbour_radius_m) each target sees.
        neighbour_steps: their last observed steps read.
        min_scale_m, horizon_scale_s: the target's length scale L = max(speed x horizon_scale_s, min_scale_m):
            inputs and residuals are in units of L, so a correction means the same manoeuvre at every speed.
        hidden: width of the encoders; head_hidden: width of the fused layers.
        epochs, batch_size, lr, weight_decay, seed: training (Adam, targets per batch).
        score_weight: weight of the mode-score cross-entropy beside the two displacement losses.
        max_targets_per_window: at most this many targets of a window per epoch (drawn anew each epoch), so
            crowded windows do not dominate; 0 = all.
        val_every: validate every this many epochs (model selection on the validation split's K=1 FDE).
        patience: stop after this many validations without a better one (0: never).
        num_threads: torch threads while training (1 keeps two jobs from waiting on each other's threads).
    """

    obs_len: int = 20
    pred_len: int = 30
    modes: int = 6
    environment: bool = True
    crop_px: int = 48
    crop_res_m: float = 1.0
    crop_behind_m: float = 12.0
    neighbours: int = 16
    neighbour_radius_m: float = 60.0
    neighbour_steps: int = 5
    min_scale_m: float = 5.0
    horizon_scale_s: float = 3.0
    hidden: int = 128
    head_hidden: int = 256
    epochs: int = 30
    batch_size: int = 128
    lr: float = 1e-3
    weight_decay: float = 1e-5
    seed: int = 0
    score_weight: float = 0.5
    max_targets_per_window: int = 0
    val_every: int = 1
    patience: int = 0
    num_threads: int = 1

    def __post_init__(self) -> None:
        checks = [
            (self.obs_len >= 13, "obs_len must be >= 13 (the prior backtests over the last 8 steps)"),
            (self.pred_len >= 1 and self.modes >= 1, "pred_len and modes must be >= 1"),
            (self.crop_px >= 16 and self.crop_px % 16 == 0, "crop_px must be a multiple of 16, >= 16"),
            (self.crop_res_m > 0 and 0 <= self.crop_behind_m < self.crop_px * self.crop_res_m, "bad crop geometry"),
            (self.neighbours >= 0 and self.neighbour_steps >= 2 and self.neighbour_radius_m > 0, "bad neighbours"),
            (self.min_scale_m > 0 and self.horizon_scale_s > 0, "scales must be > 0"),
            (8 <= self.hidden <= 4096 and 8 <= self.head_hidden <= 4096, "layers must be 8..4096 wide"),
            # bounded before anything is allocated: a checkpoint's metadata is read before its weights
            (self.obs_len <= 1000 and self.pred_len <= 1000 and self.modes <= 64, "lengths <= 1000, modes <= 64"),
            (self.crop_px <= 256 and self.neighbours <= 256 and self.neighbour_steps <= self.obs_len, "too large"),
            (self.epochs >= 1 and self.batch_size >= 1 and self.lr > 0 and self.weight_decay >= 0, "bad training"),
            (self.val_every >= 1 and self.patience >= 0 and self.num_threads >= 1, "bad schedule"),
            (self.max_targets_per_window >= 0 and self.score_weight >= 0, "bad sampling or weight"),
        ]
        for ok, message in checks:
            if not ok:
                raise ResidualConfigError(f"residual config: {message} ({self})")

    @property
    def step_len(self) -> int:
        """Observed + predicted steps of a window."""
        return self.obs_len + self.pred_len

    def to_dict(self) -> dict[str, Any]:
        """Plain dict (``meta.json``, the run's config file)."""
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, data: dict[str, Any], where: str = "config") -> ResidualConfig:
        """From a plain dict; unknown keys are an error, so a typo never falls back to a default."""
        known = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(data) - known)
        if unknown:
            raise ResidualConfigError(f"{where}: unknown residual settings {unknown}; known: {sorted(known)}")
        try:
            return cls(**data)
        except TypeError as err:
            raise ResidualConfigError(f"{where}: {err}") from None


def is_residual_config(path: Path | None) -> bool:
    """Whether a config file describes the residual model (it has a ``[residual]`` table)."""
    if path is None or path.suffix != ".toml" or not path.is_file():
        return False
    try:
        return "residual" in tomllib.loads(path.read_text())
    except (OSError, tomllib.TOMLDecodeError):
        return False


def load_residual_config(path: Path | None, overrides: dict[str, Any] | None = None) -> ResidualConfig:
    """The ``[residual]`` table of a TOML file (defaults without one) with ``overrides`` applied.

    Raises:
        ResidualConfigError: unreadable TOML, other tables, unknown keys or bad values.
    """
    data: dict[str, Any] = {}
    if path is not None:
        try:
            doc = tomllib.loads(path.read_text())
        except (OSError, tomllib.TOMLDecodeError) as err:
            raise ResidualConfigError(f"{path}: not a readable TOML config: {err}") from None
        extra = sorted(set(doc) - {"residual"})
        if extra:
            raise ResidualConfigError(f"{path}: a residual config has one [residual] table, found also {extra}")
        data = dict(doc.get("residual", {}))
    return ResidualConfig.from_dict({**data, **(overrides or {})}, str(path or "overrides"))
