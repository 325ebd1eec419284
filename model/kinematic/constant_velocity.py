"""Constant velocity from the last observed displacement (``ConstantVelocity``), fitted by least squares over the
observed steps (``LinearFit``, the paper's Linear row), and the constant-velocity sampler used as a best-of-K floor
(``ConstantVelocitySampler``). World metres per step (the protocols sample at a fixed rate), vectorised over targets.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from logpipe.types import NDArrayBool, NDArrayFloat, SceneSample

from ..training.seeding import sample_seed


def observed_targets(sample: SceneSample) -> tuple[NDArrayFloat, NDArrayBool]:
    """Observed target tracks (N_t, T_obs, 2) world metres and their validity (N_t, T_obs)."""
    obs = np.asarray(sample.positions, np.float64)[np.asarray(sample.target_mask, bool), : sample.obs_len]
    ok: NDArrayBool = np.all(np.isfinite(obs), axis=-1)
    return obs, ok


def last_velocity(obs: NDArrayFloat, ok: NDArrayBool) -> tuple[NDArrayFloat, NDArrayFloat]:
    """(current position, velocity per step) from the last two observations of each track.

    The velocity uses the latest earlier observation (divided by the step gap); 0 with only one.
    """
    t = obs.shape[1]
    cur = obs[:, -1]
    idx = np.arange(t - 1)
    earlier = np.where(ok[:, :-1], idx, -1).max(axis=1)  # latest observed step before the current one
    has = earlier >= 0
    prev = obs[np.arange(len(obs)), np.maximum(earlier, 0)]
    gap = np.maximum((t - 1) - earlier, 1)[:, None]
    vel = np.where(has[:, None], (cur - prev) / gap, 0.0)
    return cur, vel


@dataclass
class ConstantVelocity:
    """p̂^(T_obs + k) = p^(T_obs) + k v, v the last observed displacement per step."""

    pred_len: int = 12
    name: str = "constant_velocity"

    def predict(self, samples: Sequence[SceneSample], num_modes: int, seed: int) -> list[NDArrayFloat]:
        """Deterministic: the forecast repeated ``num_modes`` times."""
        del seed
        return [self.predict_tracks(observed_targets(s)[0], num_modes) for s in samples]

    def predict_tracks(self, observed: NDArrayFloat, num_modes: int) -> NDArrayFloat:
        """(N, K, pred_len, 2) forecasts of N targets from their own (N, T_obs, 2) observed tracks (world
        metres, NaN where unobserved) alone: the columnar path (``logpipe.dataset.target_tracks``)."""
        ok = np.all(np.isfinite(observed), axis=-1)
        cur, vel = last_velocity(observed, ok)
        steps = np.arange(1, self.pred_len + 1, dtype=np.float64)[None, :, None]
        fut = cur[:, None] + vel[:, None] * steps
        # A read-only view of the K equal modes: whoever lays them out copies them once.
        modes: NDArrayFloat = np.broadcast_to(fut[:, None], (len(fut), num_modes, *fut.shape[1:]))
        return modes


@dataclass
class LinearFit:
    """The paper's Linear row: least-squares line p(t) = a + b t through the observed steps, extrapolated.

    Attributes:
        history: fit on the last this many observed steps (None = all).
    """

    pred_len: int = 12
    history: int | None = None
    name: str = "linear"

    def predict(self, samples: Sequence[SceneSample], num_modes: int, seed: int) -> list[NDArrayFloat]:
        """Deterministic: the forecast repeated ``num_modes`` times."""
        del seed
        return [np.repeat(self.fit_tracks(observed_targets(s)[0])[:, None], num_modes, axis=1) for s in samples]

    def fit_tracks(self, observed: NDArrayFloat) -> NDArrayFloat:
        """(N, pred_len, 2) forecasts of N tracks (N, T_obs, 2) world metres, NaN where unobserved (a track
        without two observed steps in the window stands still at its mean position)."""
        ok = np.all(np.isfinite(observed), axis=-1)
        t_obs = observed.shape[1]
        t = np.arange(t_obs, dtype=np.float64)
        if self.history is not None:
            ok = ok & (t >= t_obs - self.history)[None]
        w = ok.astype(np.float64)
        n = np.maximum(w.sum(axis=1), 1.0)
        t_mean = (w * t).sum(axis=1) / n
        p = np.nan_to_num(observed)
        p_mean = (w[..., None] * p).sum(axis=1) / n[:, None]
        dt = (t[None] - t_mean[:, None]) * w
        var = (dt**2).sum(axis=1)
        cov = (dt[..., None] * (p - p_mean[:, None])).sum(axis=1)
        slope = np.where(var[:, None] > 0, cov / np.where(var > 0, var, 1.0)[:, None], 0.0)
        t_fut = np.arange(t_obs, t_obs + self.pred_len, dtype=np.float64)
        fut: NDArrayFloat = p_mean[:, None] + slope[:, None] * (t_fut[None, :, None] - t_mean[:, None, None])
        return fut


@dataclass
class ConstantVelocitySampler:
    """K constant-velocity forecasts with the last velocity's heading and speed perturbed by Gaussian noise:
    heading + N(0, heading_std_rad), speed x (1 + N(0, speed_std_frac)) (clipped at 0).

    Attributes:
        heading_std_rad: heading noise std (radians).
        speed_std_frac: relative speed noise std.
        include_unperturbed: make mode 0 the plain constant-velocity forecast.
    """

    pred_len: int = 12
    heading_std_rad: float = 0.25
    speed_std_frac: float = 0.1
    include_unperturbed: bool = False
    name: str = "cv_sampler"

    def predict(self, samples: Sequence[SceneSample], num_modes: int, seed: int) -> list[NDArrayFloat]:
        """Random per (sample, target, mode), reproducible from ``seed``; each sample draws from its own stream
        (``sample_seed``), so its forecasts do not depend on the other samples or their order."""
        steps = np.arange(1, self.pred_len + 1, dtype=np.float64)[None, None, :, None]
        out = []
        for s in samples:
            rng = np.random.default_rng(sample_seed(seed, s.sample_id))
            cur, vel = last_velocity(*observed_targets(s))
            n = len(cur)
            dtheta = rng.normal(0.0, self.heading_std_rad, size=(n, num_modes))
            scale = np.maximum(1.0 + rng.normal(0.0, self.speed_std_frac, size=(n, num_modes)), 0.0)
            if self.include_unperturbed and num_modes:
                dtheta[:, 0], scale[:, 0] = 0.0, 1.0
            c, sn = np.cos(dtheta), np.sin(dtheta)
            vx = (c * vel[:, None, 0] - sn * vel[:, None, 1]) * scale
            vy = (sn * vel[:, None, 0] + c * vel[:, None, 1]) * scale
            v = np.stack((vx, vy), axis=-1)[:, :, None, :]  # (N, K, 1, 2)
            out.append(cur[:, None, None, :] + v * steps)
        return out
