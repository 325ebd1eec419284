"""The best kinematic baseline: of constant velocity (CV), least-squares CV over the last n steps, a constant-velocity
Kalman filter and the adaptive prior, each over its own grid of settings, the one with the lowest mean final
displacement error on training targets.

One definition for every place that compares with physics or falls back to it: the residual model's comparison
with its baselines (``model.residual.compare``), its fallback for targets it has no evidence for
(``model.residual.ood``) and the leave-one-location-out report (``scripts.driving_lolo``). A choice is a small JSON
record (``{"method": "kalman", "accel_std": 0.3, "meas_std": 0.3}``) that checkpoints store and ``forecast`` replays.

Units: world metres, steps of the log's frame; ``(N, T, 2)`` tracks, NaN where a step is unobserved.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

from logpipe.types import NDArrayFloat

from .adaptive_prior import WINDOWS, adaptive_fit
from .constant_velocity import ConstantVelocity, LinearFit
from .kalman import KalmanCV

LS_HISTORIES = (3, 4, 5, 6, 8, 10, 12, 15)
"""Fit windows (steps) of least-squares CV (2 steps is plain CV, a method of its own)."""
KALMAN_GRID = tuple((q, r) for q in (0.003, 0.01, 0.03, 0.1, 0.3, 1.0, 3.0, 10.0)
                    for r in (0.01, 0.03, 0.1, 0.3, 1.0, 3.0, 10.0))
"""(accel_std m/step^2, meas_std m) of the Kalman filter: a grid far wider than any choice seen on the driving data
(0.01-1.0 each), so a choice on its edge says the data wants more."""
PRIOR_GRID = tuple((h, b) for h in (1, 2, 3, 5) for b in (4, 8, 12, 16, 18))
"""(backtest horizon, backtest steps) of the adaptive prior; (3, 8) is the residual model's own prior, frozen since
issue 57 (it was settled while looking at driving results), so the baseline row chooses its own here. A horizon of
1 step is the domain's bound, not an edge of the grid, and so is a backtest over every observed step it can use
(``obs_len - 2``)."""
MAX_TARGETS = 20_000
"""At most this many training targets choose (a seeded draw)."""


def candidates(obs_len: int) -> list[dict[str, Any]]:
    """Every setting tried, in a fixed order (ties go to the first: the simplest)."""
    out: list[dict[str, Any]] = [{"method": "cv"}]
    out += [{"method": "least_squares_cv", "history": n} for n in LS_HISTORIES if n <= obs_len]
    out += [{"method": "kalman", "accel_std": q, "meas_std": r} for q, r in KALMAN_GRID]
    out += [{"method": "adaptive_prior", "horizon": h, "backtest": b} for h, b in PRIOR_GRID if b + 2 <= obs_len]
    return out


def forecast(choice: Mapping[str, Any], observed: NDArrayFloat, pred_len: int) -> NDArrayFloat:
    """(N, pred_len, 2) forecasts of ``observed`` (N, T_obs, 2) by the baseline ``choice`` (a ``candidates`` record).

    Raises:
        ValueError: an unknown method.
    """
    method = choice.get("method")
    if method == "cv":
        return np.ascontiguousarray(ConstantVelocity(pred_len=pred_len).predict_tracks(observed, 1)[:, 0])
    if method == "least_squares_cv":
        return LinearFit(pred_len=pred_len, history=int(choice["history"])).fit_tracks(observed)
    if method == "kalman":
        return KalmanCV(pred_len=pred_len, accel_std=float(choice["accel_std"]),
                        meas_std=float(choice["meas_std"])).filter_tracks(observed)
    if method == "adaptive_prior":
        return adaptive_fit(observed, WINDOWS, int(choice.get("horizon", 3)),
                            int(choice.get("backtest", 8))).forecast(pred_len)
    raise ValueError(f"unknown kinematic baseline {method!r}")


SETTINGS = ("history", "accel_std", "meas_std", "horizon", "backtest")
"""The settings a choice may carry, in the order ``label`` names them."""


def label(choice: Mapping[str, Any]) -> str:
    """A short name of a choice: ``kalman(accel_std 0.3, meas_std 0.3)``, ``least_squares_cv(history 8)``, ``cv``."""
    args = [f"{key} {choice[key]}" for key in SETTINGS if key in choice]
    return f"{choice['method']}({', '.join(args)})" if args else str(choice["method"])


def final_errors(observed: NDArrayFloat, truth: NDArrayFloat) -> dict[str, NDArrayFloat]:
    """Per candidate (keyed by ``label``) the (N,) final displacement errors on targets with true futures
    ``truth`` (N, T, 2)."""
    pred_len = truth.shape[1]
    return {label(c): np.linalg.norm(forecast(c, observed, pred_len)[:, -1] - truth[:, -1], axis=-1)
            for c in candidates(observed.shape[1])}


def choose_per_method(observed: NDArrayFloat, truth: NDArrayFloat, seed: int = 0, max_targets: int = MAX_TARGETS
                      ) -> dict[str, dict[str, Any]]:
    """Per method (``cv``, ``least_squares_cv``, ``kalman``, ``adaptive_prior``) its setting with the lowest mean
    FDE on (at most ``max_targets`` of) the training targets ``observed`` (N, T_obs, 2) with true futures ``truth``
    (N, T, 2): the ``candidates`` record plus ``train_fde`` (m) and ``on_grid_edge`` (a Kalman or least-squares
    choice at its grid's largest value, where the optimum may lie beyond)."""
    rows = np.arange(len(observed))
    if len(rows) > max_targets:
        rows = np.sort(np.random.default_rng(seed).choice(rows, max_targets, replace=False))
    errors = final_errors(observed[rows], truth[rows])
    best: dict[str, dict[str, Any]] = {}
    for candidate in candidates(observed.shape[1]):
        fde = float(np.nanmean(errors[label(candidate)])) if len(rows) else 0.0
        method = candidate["method"]
        if method not in best or fde < best[method]["train_fde"]:
            edge = (candidate.get("accel_std") == KALMAN_GRID[-1][0] or candidate.get("meas_std") == KALMAN_GRID[-1][1]
                    or candidate.get("history") == LS_HISTORIES[-1] or candidate.get("horizon") == PRIOR_GRID[-1][0]
                    or candidate.get("backtest") == PRIOR_GRID[-1][1] < observed.shape[1] - 2)
            best[method] = dict(candidate) | {"train_fde": fde, "on_grid_edge": bool(edge)}
    for record in best.values():
        record["train_fde"] = round(record["train_fde"], 4)
    return best


def choose(per_method: Mapping[str, Mapping[str, Any]]) -> dict[str, Any]:
    """The best kinematic baseline of ``choose_per_method``'s records: the lowest training FDE (ties: the first)."""
    return dict(min(per_method.values(), key=lambda record: float(record["train_fde"])))
