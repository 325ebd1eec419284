"""The residual driving model behind the ``Predictor`` interface.

Forecasts: mode 0 is the mean head (the K = 1 forecast), then the mode heads as ``modes.spread_modes`` takes them
(``residual_fit.forecast``); ``predict_ranked`` gives every head by score, for ``logpipe predict``'s check to choose
mode 0 and the K modes.
The deterministic heads draw nothing, so ``seed`` changes nothing. What a target outside the checkpoint's training
data gets is ``logpipe predict``'s business (``residual_ood.OodCheck``, ``--out-of-distribution``).
"""

from __future__ import annotations

import itertools
from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path

import numpy as np

from logpipe.types import NDArrayFloat, SceneSample

from .checkpoint import load_residual
from .fit import ranked_forecasts
from .inputs import concat, target_inputs
from .meta import ResidualMeta
from .modes import model_modes
from .net import ResidualNet
from .ood import OodCheck


class ResidualPredictor:
    """A residual checkpoint as a ``Predictor``.

    Attributes:
        net, meta: the network (eval) and its checkpoint metadata.
    """

    name = "residual"

    def __init__(self, net: ResidualNet, meta: ResidualMeta) -> None:
        self.net, self.meta = net.eval(), meta

    @classmethod
    def from_checkpoint(cls, folder: Path) -> ResidualPredictor:
        """Load a residual checkpoint folder (``residual_checkpoint.load_residual``'s checks)."""
        return cls(*load_residual(folder))

    def predict(self, samples: Sequence[SceneSample], num_modes: int, seed: int) -> list[NDArrayFloat]:
        """Per sample (N_t, num_modes, T_pred, 2) world metres (see the module docstring)."""
        del seed
        return [model_modes(r, num_modes) for r in self.predict_ranked(samples)]

    def predict_ranked(self, samples: Sequence[SceneSample]) -> list[NDArrayFloat]:
        """Per sample (N_t, 1 + heads, T_pred, 2) world metres: the mean head, then every mode head by score."""
        config = self.net.config
        parts = [target_inputs(s, config) for s in samples]
        counts = [len(p) for p in parts]
        if not sum(counts):
            return [np.zeros((0, config.modes + 1, config.pred_len, 2)) for _ in samples]
        world = ranked_forecasts(self.net, concat([p for p in parts if len(p)]))
        bounds = np.cumsum([0, *counts])
        return [np.ascontiguousarray(world[a:b]) for a, b in itertools.pairwise(bounds.tolist())]


class CheckedPredictor:
    """A residual predictor with ``logpipe predict``'s out-of-distribution check applied to its forecasts: what
    predict writes (``--out-of-distribution`` as the check's action), for scripts that score predictors directly.
    """

    name = "residual"

    def __init__(self, inner: ResidualPredictor, check: OodCheck) -> None:
        self.inner, self.check = inner, check

    def predict(self, samples: Sequence[SceneSample], num_modes: int, seed: int) -> list[NDArrayFloat]:
        """As ``ResidualPredictor.predict``, then the check (mode 0 physics where it falls back)."""
        del seed
        checked, _ = replace(self.check, num_modes=num_modes)(samples, self.inner.predict_ranked(samples))
        return [np.asarray(f) for f in checked]
