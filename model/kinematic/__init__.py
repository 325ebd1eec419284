"""The kinematic methods: no learned weights, world metres per step, vectorised over targets.

* ``constant_velocity``: constant velocity (CV), least-squares CV (the paper's Linear row) and the CV sampler
  (a best-of-K floor);
* ``kalman``: the constant-velocity Kalman filter (the paper's KF row);
* ``adaptive_prior``: the adaptive constant-velocity prior (least squares over a window each track chooses), the
  residual driving model's prior and ``--predictor adaptive_cv``;
* ``best_baseline``: the best of those four, each over its own grid, chosen on training targets: what the driving
  model is compared with and falls back to.

Imports: core (``logpipe.types``) and ``model.training`` (per-sample seeds) only; every predictor family may import
this package, and it imports no family. ``CLASSICAL`` names them for ``model.registry``. The LSTM and Noise-LSTM rows
are presets of the paper's network (``model.zhu2020.config.preset``), not kinematic methods.
"""

from __future__ import annotations

from .adaptive_prior import AdaptiveConstantVelocity
from .constant_velocity import ConstantVelocity, ConstantVelocitySampler, LinearFit
from .kalman import KalmanCV

CLASSICAL: dict[str, type[ConstantVelocity | LinearFit | KalmanCV | ConstantVelocitySampler
                          | AdaptiveConstantVelocity]] = {
    "constant_velocity": ConstantVelocity,
    "linear": LinearFit,
    "kalman_cv": KalmanCV,
    "cv_sampler": ConstantVelocitySampler,
    "adaptive_cv": AdaptiveConstantVelocity,
}
"""Non-learned predictors by name; construct with ``CLASSICAL[name](pred_len=...)``."""
