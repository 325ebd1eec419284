"""The one prediction interface every method implements (``Predictor``), and the id a run records of a checkpoint
with its inference settings (``inference_id``). Each family's own wrapper lives in its package."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Protocol, runtime_checkable

from logpipe.types import NDArrayFloat, SceneSample


@runtime_checkable
class Predictor(Protocol):
    """Anything that forecasts the targets of scenes.

    ``predict`` returns, per sample, an array (N_targets, K, T_pred - T_obs, 2) of world-frame metres:
    the K candidate futures of each target (rows of ``target_mask`` in order), steps ``obs_len`` ..
    ``obs_len + pred_len - 1``. Deterministic methods repeat their one forecast K times. A target not
    observed at the current step gets NaN.
    """

    name: str

    def predict(self, samples: Sequence[SceneSample], num_modes: int, seed: int) -> list[NDArrayFloat]:
        """Forecasts for ``samples`` (see the class docstring); ``seed`` fixes any sampling."""
        ...


def inference_id(weights_sha256: str, noise_scale: float = 1.0, constant_velocity_modes: int | None = None,
                 context_max_neighbours: int | None = None) -> str:
    """The ``checkpoint_id`` predictions record: the weights' digest, then each inference setting that is not
    the checkpoint's own (noise scale not 1, constant-velocity modes or a neighbour cap given)."""
    parts = [weights_sha256]
    if noise_scale != 1.0:
        parts.append(f"noise_scale={noise_scale:g}")
    if constant_velocity_modes is not None:
        parts.append(f"constant_velocity_modes={constant_velocity_modes}")
    if context_max_neighbours is not None:
        parts.append(f"context_max_neighbours={context_max_neighbours}")
    return " ".join(parts)
