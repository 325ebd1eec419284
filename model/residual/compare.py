"""A trained residual model against the kinematic baselines on the same held-out targets: what ``logpipe train``
on driving data reports (summary, ``--json``, the run folder's ``MODEL_CARD.md``).

K = 1 (FDE and ADE at the protocol's horizon): constant velocity (the last displacement), least-squares CV, a
constant-velocity Kalman filter and the adaptive prior, each with its setting chosen on the training targets
(``model.kinematic.best_baseline``), the model's own prior as it trains on, and the model's mean head. K = ``K``
(minFDE per agent): the model's mean head and its heads (``modes``) against the CV sampler, whose mode 0 is plain
CV (so it is never worse than CV) and whose heading and speed noise are chosen on the training targets from a grid
that reaches far below and above every choice seen (``SAMPLER_HEADINGS``, ``SAMPLER_SPEEDS``; the record says when
the choice lies on the grid's upper edge, and no noise is the lower bound). The best kinematic baseline at K = 1 is
the one with the lowest FDE on the training targets (the same choice as the model's fallback,
``ood.tune_baselines``); the verdict names every baseline the model does not beat on validation.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from logpipe.types import NDArrayFloat

from ..kinematic import best_baseline
from ..kinematic.constant_velocity import last_velocity
from .fit import forecast
from .inputs import TargetInputs, world_truth
from .net import ResidualNet

K = 6
"""Modes of the best-of-K comparison (the driving benchmarks' K)."""
SAMPLER_HEADINGS = (0.0, 0.00125, 0.0025, 0.005, 0.01, 0.02, 0.04, 0.08, 0.16, 0.32)
"""Heading noise candidates of the CV sampler, radians: from none (a speed spread alone, the domain's bound, not an
edge of the grid) to 0.32, far around the 0.02 at which the leave-one-location-out grid's edge stopped."""
SAMPLER_SPEEDS = (0.0, 0.0125, 0.025, 0.05, 0.1, 0.2, 0.4, 0.8, 1.6)
"""Relative speed noise candidates of the CV sampler (0: a heading spread alone)."""
TUNE_TARGETS = 5_000
"""At most this many training targets choose the sampler's noise (drawn by the seed)."""
K1_BASELINES = ("cv", "least_squares_cv", "kalman", "adaptive_prior")


def cv_sampler(observed: NDArrayFloat, pred_len: int, modes: int, heading_std: float, speed_std: float,
               seed: int) -> NDArrayFloat:
    """(N, modes, T, 2): mode 0 plain constant velocity, the others its heading and speed perturbed by Gaussian
    noise (``model.kinematic.constant_velocity.ConstantVelocitySampler`` with ``include_unperturbed``)."""
    cur, vel = last_velocity(observed, np.all(np.isfinite(observed), axis=-1))
    rng = np.random.default_rng(seed)
    n = len(cur)
    turn = rng.normal(0.0, heading_std, (n, modes))
    stretch = np.maximum(1.0 + rng.normal(0.0, speed_std, (n, modes)), 0.0)
    turn[:, 0], stretch[:, 0] = 0.0, 1.0
    c, s = np.cos(turn), np.sin(turn)
    v = np.stack([(c * vel[:, None, 0] - s * vel[:, None, 1]) * stretch,
                  (s * vel[:, None, 0] + c * vel[:, None, 1]) * stretch], -1)
    steps = np.arange(1, pred_len + 1, dtype=np.float64)[None, None, :, None]
    out: NDArrayFloat = cur[:, None, None] + v[:, :, None] * steps
    return out


def _min_fde(forecasts: NDArrayFloat, truth: NDArrayFloat) -> float:
    return float(np.linalg.norm(forecasts[:, :, -1] - truth[:, None, -1], axis=-1).min(axis=1).mean())


def tune_sampler(train: TargetInputs, seed: int = 0) -> dict[str, Any]:
    """The sampler's noise with the lowest minFDE@K on (at most ``TUNE_TARGETS`` of) the training targets, and
    whether it lies on the grid's edge (then the optimum may lie beyond it)."""
    rows = np.arange(len(train))
    if len(rows) > TUNE_TARGETS:
        rows = np.sort(np.random.default_rng(seed).choice(rows, TUNE_TARGETS, replace=False))
    part = train.take(rows)
    return choose_sampler_noise(part.observed, world_truth(part), K, seed)


def choose_sampler_noise(observed: NDArrayFloat, truth: NDArrayFloat, modes: int, seed: int = 0, *,
                         headings: tuple[float, ...] = SAMPLER_HEADINGS, speeds: tuple[float, ...] = SAMPLER_SPEEDS
                         ) -> dict[str, Any]:
    """The CV sampler's noise (``headings`` x ``speeds``, ascending) with the lowest minFDE@``modes`` on tracks
    ``observed`` with true futures ``truth`` (world metres), and whether it lies on the grid's edge."""
    scores = {(h, s): _min_fde(cv_sampler(observed, truth.shape[1], modes, h, s, seed), truth)
              for h in headings for s in speeds}
    h, s = min(scores, key=lambda g: scores[g])
    edge = h == headings[-1] or s == speeds[-1]  # 0 is no noise at all: nothing lies beyond it
    return {"heading_std_rad": h, "speed_std_frac": s, "includes_cv": True, "on_grid_edge": edge,
            "chosen_on": "training targets", "train_min_fde": round(scores[(h, s)], 4)}


def kinematic_k1(inputs: TargetInputs, baselines: dict[str, dict[str, Any]]) -> dict[str, NDArrayFloat]:
    """(N, T, 2) K = 1 forecasts of the kinematic baselines with their chosen settings, and the model's own prior."""
    pred_len = inputs.prior.shape[1]
    out = {name: best_baseline.forecast(baselines[name], inputs.observed, pred_len) for name in K1_BASELINES}
    return out | {"model_prior": inputs.prior}


def _k1(path: NDArrayFloat, truth: NDArrayFloat) -> dict[str, float]:
    dist = np.linalg.norm(path - truth, axis=-1)
    return {"fde": round(float(dist[:, -1].mean()), 4), "ade": round(float(dist.mean()), 4)}


def compare(net: ResidualNet, val: TargetInputs, train: TargetInputs, baselines: dict[str, dict[str, Any]], *,
            shipped: ResidualNet | None = None, seed: int = 0) -> dict[str, Any]:
    """The comparison record (see the module docstring); ``baselines``: each kinematic method's setting chosen on
    the training targets (the checkpoint's ``ood["baselines"]``); ``shipped``: the shipped model as it is, a row of
    its own."""
    truth = world_truth(val)
    model = forecast(net, val, K)
    k1 = {name: _k1(path, truth) for name, path in kinematic_k1(val, baselines).items()}
    k1["model"] = _k1(model[:, 0], truth)
    sampler = tune_sampler(train, seed)
    k6 = {"cv_sampler": round(_min_fde(cv_sampler(val.observed, truth.shape[1], K, sampler["heading_std_rad"],
                                                  sampler["speed_std_frac"], seed), truth), 4),
          "model": round(_min_fde(model, truth), 4)}
    if shipped is not None:
        theirs = forecast(shipped, val, K)
        k1["shipped_model"] = _k1(theirs[:, 0], truth)
        k6["shipped_model"] = round(_min_fde(theirs, truth), 4)
    best = best_baseline.choose(baselines)["method"]
    cv_fde = k1["cv"]["fde"]
    losses = [f"{name} (FDE {k1[name]['fde']:.2f} m against the model's {k1['model']['fde']:.2f})"
              for name in K1_BASELINES if k1["model"]["fde"] >= k1[name]["fde"]]
    if k6["model"] >= k6["cv_sampler"]:
        losses.append(f"the CV sampler at K = {K} (minFDE {k6['cv_sampler']:.2f} m against {k6['model']:.2f})")
    verdict = ("the trained model beats every kinematic baseline on the validation data" if not losses else
               "the trained model does NOT beat " + "; ".join(losses) + " on the validation data")
    return {"targets": len(val), "k": K, "k1": k1, f"min_fde_{K}": k6, "baselines": baselines, "cv_sampler": sampler,
            "best_kinematic": best, "best_kinematic_chosen_on": "training targets (K = 1 FDE)",
            "model_fde_to_cv": round(k1["model"]["fde"] / cv_fde, 4) if cv_fde else None,
            "model_fde_to_best_kinematic": round(k1["model"]["fde"] / k1[best]["fde"], 4) if k1[best]["fde"] else None,
            f"model_min_fde_{K}_to_cv_fde": round(k6["model"] / cv_fde, 4) if cv_fde else None,
            "beats": {name: k1["model"]["fde"] < k1[name]["fde"] for name in K1_BASELINES}
            | {"cv_sampler": k6["model"] < k6["cv_sampler"]}, "verdict": verdict}


def not_compared(why: str) -> dict[str, Any]:
    """The comparison record of a run with no validation data."""
    return {"targets": 0, "k": K, "beats": {}, "verdict": f"not compared with the kinematic baselines: no validation "
            f"data ({why})"}


def k1_source(comparison: dict[str, Any]) -> dict[str, str]:
    """What ``logpipe predict`` forecasts at K = 1 with the trained checkpoint (its ``ood["k1_source"]``): the
    model's mean head only where validation showed it beats the best kinematic baseline, else that baseline."""
    if not comparison["targets"]:
        return {"source": "physics", "reason": "no validation data showed that the model beats the best kinematic "
                "baseline at K = 1"}
    best = comparison["best_kinematic"]
    mine, theirs = comparison["k1"]["model"]["fde"], comparison["k1"][best]["fde"]
    if mine < theirs:
        return {"source": "model", "reason": f"on validation its K = 1 FDE {mine:.2f} m beats the best kinematic "
                f"baseline's ({best}) {theirs:.2f} m"}
    return {"source": "physics", "reason": f"on validation its K = 1 FDE {mine:.2f} m does not beat the best "
            f"kinematic baseline's ({best}) {theirs:.2f} m"}
