"""The paper's KF row: a constant-velocity Kalman filter over the observed steps, then propagated without
updates. World metres per step, vectorised over targets."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from logpipe.types import NDArrayBool, NDArrayFloat, SceneSample

from .constant_velocity import observed_targets


@dataclass
class KalmanCV:
    """The paper's KF row: a constant-velocity Kalman filter (state x, y, vx, vy per step) run over the
    observed steps, then propagated without updates.

    Attributes:
        accel_std: process noise, white acceleration std (m / step^2).
        meas_std: measurement noise std (m).
        init_vel_std: prior std of the initial velocity (m / step).
    """

    pred_len: int = 12
    accel_std: float = 0.1
    meas_std: float = 0.05
    init_vel_std: float = 2.0
    name: str = "kalman_cv"

    def predict(self, samples: Sequence[SceneSample], num_modes: int, seed: int) -> list[NDArrayFloat]:
        """Deterministic: the filter's mean forecast repeated ``num_modes`` times."""
        del seed
        return [np.repeat(self.filter_tracks(observed_targets(s)[0])[:, None], num_modes, axis=1) for s in samples]

    def predict_tracks(self, observed: NDArrayFloat, num_modes: int) -> NDArrayFloat:
        """(N, K, pred_len, 2): ``filter_tracks`` repeated as K equal modes (a read-only view), the columnar path
        (``logpipe.prediction.columnar.TrackPredictor``)."""
        fut = self.filter_tracks(observed)
        modes: NDArrayFloat = np.broadcast_to(fut[:, None], (len(fut), num_modes, *fut.shape[1:]))
        return modes

    def filter_tracks(self, observed: NDArrayFloat) -> NDArrayFloat:
        """(N, pred_len, 2) forecasts of N tracks (N, T_obs, 2) world metres, NaN where unobserved."""
        obs = np.asarray(observed, np.float64)
        ok: NDArrayBool = np.all(np.isfinite(obs), axis=-1)
        f = np.array([[1, 0, 1, 0], [0, 1, 0, 1], [0, 0, 1, 0], [0, 0, 0, 1]], np.float64)
        g = np.array([[0.5, 0], [0, 0.5], [1, 0], [0, 1]])
        q = self.accel_std**2 * g @ g.T
        h = np.eye(2, 4)
        r = self.meas_std**2 * np.eye(2)
        n, t_obs = ok.shape
        first = np.argmax(ok, axis=1)
        x = np.zeros((n, 4))
        x[:, :2] = np.nan_to_num(obs[np.arange(n), first])
        p = np.tile(np.diag([self.meas_std**2] * 2 + [self.init_vel_std**2] * 2), (n, 1, 1))
        for t in range(t_obs):
            upd = ok[:, t] & (t > first)
            pred_x = x @ f.T
            pred_p = f @ p @ f.T + q
            started = (t > first)[:, None]
            x = np.where(started, pred_x, x)
            p = np.where(started[..., None], pred_p, p)
            innov = np.nan_to_num(obs[:, t]) - x[:, :2]
            s_mat = h @ p @ h.T + r
            gain = p @ h.T @ np.linalg.inv(s_mat)
            x = np.where(upd[:, None], x + np.einsum("nij,nj->ni", gain, innov), x)
            p = np.where(upd[:, None, None], (np.eye(4) - gain @ h) @ p, p)
        fut = np.empty((n, self.pred_len, 2))
        for k in range(self.pred_len):
            x = x @ f.T
            fut[:, k] = x[:, :2]
        return fut
