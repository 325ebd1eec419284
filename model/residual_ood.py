"""Out-of-distribution awareness of the residual driving model: what its training targets looked like, and how far
outside that a target of another log lies.

A checkpoint records (``meta.json`` ``ood``) of its training targets: the 0.1 % and 99.9 % quantiles of speed
(m/s), acceleration along the track (m/s^2) and yaw rate (rad/s); the frame rates (Hz); the agent types with their
counts; and the share of targets with a map under them. A target's score is the largest excess over those ranges
in units of the range's width (0 inside), plus 1 for an agent type or a frame rate (beyond 5 %) the training
never had, and 1 for a target without a map when at least half the training targets had one. A target is flagged
when its score exceeds ``FLAG_SCORE`` (a quarter of a range beyond, or any unseen type or rate, or no map). The
reasons name the descriptors that put it there.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from logpipe.types import OBJECT_TYPES, NDArrayBool, NDArrayFloat

from .residual_inputs import TargetInputs

QUANTILES = (0.001, 0.999)
"""The range each numeric descriptor is checked against."""
FLAG_SCORE = 0.25
"""Scores above this are flagged."""
RATE_TOLERANCE = 0.05
"""A frame rate within this relative difference of a training rate is a training rate."""
_NUMERIC = ("speed_mps", "accel_mps2", "yaw_rate_rps")


def _numeric(inputs: TargetInputs) -> dict[str, NDArrayFloat]:
    return {"speed_mps": inputs.speed, "accel_mps2": inputs.motion[:, 0], "yaw_rate_rps": inputs.motion[:, 1]}


def training_distribution(inputs: TargetInputs) -> dict[str, Any]:
    """The ``ood`` record of a checkpoint trained on ``inputs``."""
    ranges = {name: [float(np.quantile(v, q)) for q in QUANTILES] for name, v in _numeric(inputs).items()}
    types, counts = np.unique(inputs.object_type, return_counts=True)
    return {"quantiles": list(QUANTILES), "ranges": ranges,
            "rates_hz": sorted({round(float(r), 3) for r in inputs.rate_hz}),
            "object_types": {OBJECT_TYPES[int(t)]: int(c) for t, c in zip(types, counts, strict=True)},
            "map_share": float(np.mean(inputs.has_map)) if len(inputs) else 0.0, "targets": len(inputs),
            "flag_score": FLAG_SCORE}


def ood_scores(inputs: TargetInputs, ood: dict[str, Any]) -> tuple[NDArrayFloat, NDArrayBool, list[str]]:
    """(scores (N,), flags (N,), reasons (N,): the descriptors outside, ``""`` for none) of targets against a
    checkpoint's ``ood`` record."""
    n = len(inputs)
    score = np.zeros(n)
    reasons: list[list[str]] = [[] for _ in range(n)]
    for name, values in _numeric(inputs).items():
        lo, hi = ood["ranges"][name]
        width = max(hi - lo, 1e-6)
        excess = np.maximum(np.maximum(values - hi, lo - values), 0.0) / width
        score = np.maximum(score, excess)
        for i in np.flatnonzero(excess > FLAG_SCORE).tolist():
            reasons[i].append(f"{name} {values[i]:.2f} outside [{lo:.2f}, {hi:.2f}]")
    seen_types = set(ood["object_types"])
    rates = np.asarray(ood["rates_hz"], np.float64)
    for i in range(n):
        kind = OBJECT_TYPES[int(inputs.object_type[i])]
        if kind not in seen_types:
            score[i] += 1.0
            reasons[i].append(f"agent type {kind} not in training")
        rate = float(inputs.rate_hz[i])
        if not len(rates) or np.min(np.abs(rates - rate) / rates) > RATE_TOLERANCE:
            score[i] += 1.0
            reasons[i].append(f"frame rate {rate:g} Hz not in training {rates.tolist()}")
        if ood["map_share"] >= 0.5 and not inputs.has_map[i]:
            score[i] += 1.0
            reasons[i].append("no map under the target")
    return score, score > FLAG_SCORE, ["; ".join(r) for r in reasons]
