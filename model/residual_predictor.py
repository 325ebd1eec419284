"""The residual driving model behind the ``Predictor`` interface, with its out-of-distribution handling.

Forecasts: mode 0 is the mean head (the K = 1 forecast), then the mode heads by score (``residual_fit.forecast``).
Every target is scored against the checkpoint's training distribution (``residual_ood``); ``out_of_distribution``
says what a flagged target gets: ``warn`` (the network's forecast; the flag is recorded), ``fallback`` (the
Kalman filter's forecast, ``model.baselines.KalmanCV``, in every mode, marked as such) or ``refuse`` (an error
naming the first flagged targets). The deterministic heads draw nothing, so ``seed`` changes nothing.
"""

from __future__ import annotations

import itertools
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np
import torch

from logpipe.errors import LogpipeError
from logpipe.types import NDArrayBool, NDArrayFloat, SceneSample

from .baselines import KalmanCV
from .residual_checkpoint import load_residual
from .residual_fit import forecast
from .residual_inputs import concat, target_inputs
from .residual_meta import ResidualMeta
from .residual_net import ResidualNet
from .residual_ood import ood_scores

OodAction = Literal["warn", "fallback", "refuse"]
OOD_ACTIONS: tuple[OodAction, ...] = ("warn", "fallback", "refuse")


def check_ood_action(value: str) -> OodAction:
    """``value`` as an ``OodAction``, or a ``LogpipeError`` naming the choices."""
    for action in OOD_ACTIONS:
        if value == action:
            return action
    raise LogpipeError(f"--out-of-distribution must be one of {', '.join(OOD_ACTIONS)}, got {value!r}")


@dataclass
class OodRecord:
    """Per target of the last ``predict`` call (rows in sample order, then target-mask order): score, flag,
    whether the Kalman fallback replaced the network's forecast, and the reasons."""

    scores: NDArrayFloat = field(default_factory=lambda: np.zeros(0))
    flags: NDArrayBool = field(default_factory=lambda: np.zeros(0, bool))
    fallback: NDArrayBool = field(default_factory=lambda: np.zeros(0, bool))
    reasons: list[str] = field(default_factory=list)


class ResidualPredictor:
    """A residual checkpoint as a ``Predictor``.

    Attributes:
        net, meta: the network (eval) and its checkpoint metadata.
        out_of_distribution: what flagged targets get (see the module docstring).
        last_ood: the scores and flags of the last ``predict`` call's targets.
    """

    name = "residual"

    def __init__(self, net: ResidualNet, meta: ResidualMeta, out_of_distribution: OodAction = "warn",
                 num_threads: int | None = None) -> None:
        check_ood_action(out_of_distribution)
        self.net, self.meta, self.out_of_distribution = net.eval(), meta, out_of_distribution
        self.last_ood = OodRecord()
        if num_threads:
            torch.set_num_threads(num_threads)

    @classmethod
    def from_checkpoint(cls, folder: Path, out_of_distribution: OodAction = "warn") -> ResidualPredictor:
        """Load a residual checkpoint folder (``residual_checkpoint.load_residual``'s checks)."""
        net, meta = load_residual(folder)
        return cls(net, meta, out_of_distribution)

    def predict(self, samples: Sequence[SceneSample], num_modes: int, seed: int) -> list[NDArrayFloat]:
        """Per sample (N_t, num_modes, T_pred, 2) world metres (see the module docstring)."""
        del seed
        config = self.net.config
        parts = [target_inputs(s, config) for s in samples]
        counts = [len(p) for p in parts]
        if not sum(counts):
            self.last_ood = OodRecord()
            return [np.zeros((0, num_modes, config.pred_len, 2)) for _ in samples]
        inputs = concat([p for p in parts if len(p)])
        world = forecast(self.net, inputs, num_modes)
        scores, flags, reasons = ood_scores(inputs, self.meta.ood)
        replaced = np.zeros(len(flags), bool)
        if flags.any() and self.out_of_distribution == "refuse":
            where = [f"{s.sample_id}" for s, n in zip(samples, counts, strict=True) for _ in range(n)]
            first = np.flatnonzero(flags)[:3].tolist()
            raise LogpipeError(f"{int(flags.sum())} of {len(flags)} targets are outside this checkpoint's training "
                               f"data (--out-of-distribution refuse), e.g. "
                               + "; ".join(f"{where[i]}: {reasons[i]}" for i in first))
        if flags.any() and self.out_of_distribution == "fallback":
            kalman = KalmanCV(pred_len=config.pred_len).predict(samples, 1, 0)
            stacked = np.concatenate([k[:, 0] for k in kalman])
            world[flags] = stacked[flags][:, None]
            replaced = flags.copy()
        self.last_ood = OodRecord(scores, flags, replaced, reasons)
        bounds = np.cumsum([0, *counts])
        return [np.ascontiguousarray(world[a:b]) for a, b in itertools.pairwise(bounds.tolist())]
