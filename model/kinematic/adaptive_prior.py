"""The kinematic prior of the driving model: constant velocity fitted by least squares over a window of the last
observed steps that each track chooses for itself.

Why adaptive: sensors differ. On NGSIM's smoothed tracks the last displacement is the best velocity estimate; on
Argoverse 1's detections a fit over 8-10 steps is (their FDE at 3 s: 5.5 m from the last step against 3.2 m over 8
steps on AV1 MIA; 2.49 against 2.74 the other way round on US-101). A window chosen on other recordings is wrong for
the next sensor, so each track picks its own: every candidate window is backtested on the track's own history
(fit on the steps before step ``t``, predict ``t + horizon - 1``, over the last ``backtest`` steps) and the one
with the smallest error is used. Nothing is learned and nothing is tuned on a dataset.

Units: metres and steps of the log's frame (velocities in metres per step); ``(N, T, 2)`` tracks, NaN where a step
is unobserved (only the trailing observed run of a track is used).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from logpipe.types import NDArrayFloat, NDArrayInt, SceneSample

WINDOWS: tuple[int, ...] = (2, 3, 4, 5, 6, 8, 10, 12)
"""Candidate fit windows, steps (2 = the last displacement: plain constant velocity)."""
HORIZON = 3
"""Steps ahead each candidate predicts in the backtest."""
BACKTEST = 8
"""The backtest's predicted steps lie among the last this many observed steps."""


@dataclass(frozen=True)
class PriorFit:
    """Each track's fitted motion at its current step.

    Attributes:
        origin: (N, 2) fitted position at the current step (metres, world frame).
        velocity: (N, 2) metres per step.
        window: (N,) the fit window each track chose (0 for a track with a single observed step).
    """

    origin: NDArrayFloat
    velocity: NDArrayFloat
    window: NDArrayInt

    def forecast(self, pred_len: int) -> NDArrayFloat:
        """(N, pred_len, 2) positions of the next ``pred_len`` steps, metres."""
        steps = np.arange(1, pred_len + 1, dtype=np.float64)[None, :, None]
        out: NDArrayFloat = self.origin[:, None] + self.velocity[:, None] * steps
        return out

    def take(self, rows: NDArrayInt) -> PriorFit:
        """The fits of ``rows``."""
        return PriorFit(self.origin[rows], self.velocity[rows], self.window[rows])


def _line_fit(track: NDArrayFloat, n: int, end: int) -> tuple[NDArrayFloat, NDArrayFloat]:
    """(position at step ``end - 1``, velocity per step) of the least-squares line through steps ``end - n`` ..
    ``end - 1`` of every track (N, T, 2)."""
    t = np.arange(n, dtype=np.float64) - (n - 1)
    t_mean = t.mean()
    part = track[:, end - n:end]
    p_mean = part.mean(axis=1)
    slope = ((t - t_mean)[None, :, None] * (part - p_mean[:, None])).sum(axis=1) / ((t - t_mean) ** 2).sum()
    return p_mean - slope * t_mean, slope


def trailing_observed(observed: NDArrayFloat) -> NDArrayInt:
    """(N,) length of each track's run of observed steps ending at its last step (0 when that step is not)."""
    ok = np.all(np.isfinite(observed), axis=-1)
    gaps = ~ok[:, ::-1]
    run: NDArrayInt = np.where(gaps.any(axis=1), np.argmax(gaps, axis=1), ok.shape[1]).astype(np.int64)
    return run


def adaptive_fit(observed: NDArrayFloat, windows: Sequence[int] = WINDOWS, horizon: int = HORIZON,
                 backtest: int = BACKTEST) -> PriorFit:
    """Fit each track of ``observed`` (N, T, 2) with the window its own backtest prefers (see the module
    docstring). A track with fewer observed trailing steps than a window does not consider it; one with a single
    observed step stands still there; one not observed at its last step gets NaN."""
    if observed.ndim != 3 or observed.shape[2] != 2:
        raise ValueError(f"tracks must be (N, T, 2) positions, got shape {observed.shape}")
    n_tracks, t_obs = observed.shape[:2]
    run = trailing_observed(observed)
    filled = np.where(np.isfinite(observed), observed, 0.0)
    errors = np.full((len(windows), n_tracks), np.inf)
    for w, n in enumerate(windows):
        first_end = max(n, t_obs - backtest)
        ends = range(first_end, t_obs - horizon + 1)
        if not ends:
            continue
        total = np.zeros(n_tracks)
        for end in ends:
            origin, slope = _line_fit(filled, n, end)
            total += np.linalg.norm(origin + slope * horizon - filled[:, end - 1 + horizon], axis=1)
        # the backtest reads steps first_end - n .. t_obs - 1: only tracks observed over all of them may use it
        errors[w] = np.where(run >= t_obs - (first_end - n), total / len(ends), np.inf)
    tested = np.isfinite(errors).any(axis=0)
    # a track too short to backtest any window: the last displacement (2 steps), or standing still (1 step)
    chosen = np.where(tested, np.asarray(windows)[np.argmin(errors, axis=0)], np.where(run >= 2, 2, 0))
    origin = filled[:, -1].copy()
    velocity = np.zeros((n_tracks, 2))
    for n in np.unique(chosen[chosen > 0]).tolist():
        rows = chosen == n
        origin[rows], velocity[rows] = _line_fit(filled[rows], n, t_obs)
    window = chosen.astype(np.int64)
    unseen = run == 0
    origin[unseen] = np.nan
    velocity[unseen] = np.nan
    return PriorFit(origin, velocity, window)


@dataclass
class AdaptiveConstantVelocity:
    """``--predictor adaptive_cv``: the prior alone (constant velocity over each track's own best window),
    deterministic, repeated over the K modes."""

    pred_len: int = 12
    name: str = "adaptive_cv"

    def predict(self, samples: Sequence[SceneSample], num_modes: int, seed: int) -> list[NDArrayFloat]:
        """Each sample's targets (N_t, K, pred_len, 2), world metres."""
        del seed
        out = []
        for s in samples:
            obs = np.asarray(s.positions, np.float64)[np.asarray(s.target_mask, bool), : s.obs_len]
            fut = adaptive_fit(obs).forecast(self.pred_len)
            out.append(np.repeat(fut[:, None], num_modes, axis=1))
        return out
