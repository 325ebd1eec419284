"""Out-of-distribution awareness of the residual driving model: what its training targets looked like, and how far
outside that a target of another log lies.

A checkpoint records (``meta.json`` ``ood``) of its training targets: the 0.1 % and 99.9 % quantiles of speed
(m/s), acceleration along the track (m/s^2) and yaw rate (rad/s); the frame rates (Hz); the agent types with their
counts; and the share of targets with a map under them. A target's score is the largest excess over those ranges
in units of the range's width (0 inside), plus 1 for an agent type or a frame rate (beyond 5 %) the training
never had, and 1 for a target without a map when fewer than ``UNSEEN_SHARE`` of the training targets lacked one
(the network has learnt to forecast without a map only if it saw enough targets without one). A target is flagged
when its score exceeds ``FLAG_SCORE`` (a quarter of a range beyond, or any unseen type or rate, or no map). The
reasons name the descriptors that put it there.

``OodCheck`` applies this in ``logpipe predict`` (``--out-of-distribution warn|fallback|refuse``); the fallback is a
constant-velocity Kalman filter whose noise was chosen on the training targets (``tune_fallback``, stored in the
``ood`` record).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from logpipe.errors import LogpipeError
from logpipe.types import OBJECT_TYPES, NDArrayBool, NDArrayFloat, SceneSample

from ..kinematic.kalman import KalmanCV
from .config import ResidualConfig
from .inputs import TargetInputs, target_inputs

QUANTILES = (0.001, 0.999)
"""The range each numeric descriptor is checked against."""
FLAG_SCORE = 0.25
"""Scores above this are flagged."""
RATE_TOLERANCE = 0.05
"""A frame rate within this relative difference of a training rate is a training rate."""
UNSEEN_SHARE = 0.01
"""A condition rarer than this among the training targets (a target without a map under it) counts as never seen."""
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
        if ood["map_share"] > 1.0 - UNSEEN_SHARE and not inputs.has_map[i]:
            score[i] += 1.0
            reasons[i].append("no map under the target")
    return score, score > FLAG_SCORE, ["; ".join(r) for r in reasons]


FALLBACK_GRID = tuple((q, r) for q in (0.003, 0.01, 0.03, 0.1, 0.3) for r in (0.01, 0.03, 0.1, 0.3, 1.0))
"""Candidate (accel_std m/step^2, meas_std m) of the fallback Kalman filter, chosen on the training targets."""


def tune_fallback(inputs: TargetInputs, max_targets: int = 20_000, seed: int = 0) -> dict[str, float]:
    """The Kalman filter's noise with the lowest mean FDE on (at most ``max_targets`` of) the training targets."""
    assert inputs.truth is not None
    rows = np.arange(len(inputs))
    if len(rows) > max_targets:
        rows = np.sort(np.random.default_rng(seed).choice(rows, max_targets, replace=False))
    part = inputs.take(rows)
    assert part.truth is not None
    truth = part.prior + np.einsum("nji,ntj->nti", part.rotation, part.truth * part.scale[:, None, None])
    pred_len = truth.shape[1]

    def fde(q: float, r: float) -> float:
        forecast = KalmanCV(pred_len=pred_len, accel_std=q, meas_std=r).filter_tracks(part.observed)
        return float(np.nanmean(np.linalg.norm(forecast[:, -1] - truth[:, -1], axis=1)))

    q, r = min(FALLBACK_GRID, key=lambda g: fde(*g))
    return {"accel_std": q, "meas_std": r}


@dataclass(frozen=True)
class OodCheck:
    """``logpipe predict``'s out-of-distribution check for a residual checkpoint (picklable: shard workers run it).

    Attributes:
        ood: the checkpoint's ``ood`` record; ``config``: its ``ResidualConfig`` (the inputs are computed as the
            network's, without crops); ``action``: ``warn``, ``fallback`` or ``refuse``.
    """

    ood: dict[str, Any]
    config: ResidualConfig
    action: str

    def __call__(self, samples: Sequence[SceneSample], futures: Sequence[Any]
                 ) -> tuple[list[Any], list[tuple[NDArrayFloat, NDArrayBool, NDArrayBool]]]:
        """(the forecasts to write, each sample's (scores, flags, fallback) per target)."""
        config = replace(self.config, environment=False)
        fallback = self.ood.get("fallback_kalman", {})
        kalman = KalmanCV(pred_len=config.pred_len, **fallback)
        out, rows = [], []
        for sample, given in zip(samples, futures, strict=True):
            inputs = target_inputs(sample, config)
            scores, flags, reasons = ood_scores(inputs, self.ood)
            if flags.any() and self.action == "refuse":
                first = int(np.flatnonzero(flags)[0])
                raise LogpipeError(f"{int(flags.sum())} targets of {sample.sample_id} are outside the checkpoint's "
                                   f"training data (--out-of-distribution refuse), e.g. "
                                   f"{sample.track_ids[int(np.flatnonzero(sample.target_mask)[first])]}: "
                                   f"{reasons[first]}")
            replaced = flags & (self.action == "fallback")
            future = np.array(given, np.float64, copy=True)
            if replaced.any():
                future[replaced] = kalman.filter_tracks(inputs.observed[replaced])[:, None, : future.shape[2]]
            out.append(future)
            rows.append((scores, flags, replaced))
        return out, rows


def ood_check_for(checkpoint: Path, action: str) -> OodCheck:
    """The check of a residual checkpoint folder with ``--out-of-distribution`` ``action``."""
    from .meta import read_residual_meta  # here: the check is built only for residual checkpoints

    meta = read_residual_meta(checkpoint)
    return OodCheck(meta.ood, meta.config, action)
