"""Out-of-distribution awareness of the residual driving model: what its training targets looked like, and how far
outside that a target of another log lies.

A checkpoint records (``meta.json`` ``ood``) of its training targets: the 0.1 % and 99.9 % quantiles of speed
(m/s), acceleration along the track (m/s^2) and yaw rate (rad/s); the frame rates (Hz); the agent types with their
counts; and the share of targets with a map under them. A target's score is the largest excess over those ranges
in units of the range's width (0 inside), plus 1 for an agent type or a frame rate (beyond 5 %) the training
never had (or ``unknown``: a format that cannot label its agents, such as Argoverse 1's OTHERS, gives pedestrians
and cars alike that type), 1 for a log recorded at a rate the training never had and resampled by ingest (the logs
table's ``resampled_from_hz``: its windows read as the resampled rate), and 1 for a target without a map when
fewer than ``UNSEEN_SHARE`` of the training targets lacked one (the network has learnt to forecast without a map
only if it saw enough targets without one). A target is flagged
when its score exceeds ``FLAG_SCORE`` (a quarter of a range beyond, or any unseen type or rate, or no map). The
reasons name the descriptors that put it there.

``OodCheck`` applies this in ``logpipe predict`` (``--out-of-distribution warn|fallback|refuse``); the fallback keeps
the K modes: mode 0 (the K = 1 forecast) is a constant-velocity Kalman filter whose noise was chosen on the training
targets (``tune_fallback``), the other modes a fixed spread of it, its heading and speed turned by multiples of a
heading and a speed step (``spread_modes``) chosen on the training targets by minFDE@6 (``tune_spread``); both are
stored in the ``ood`` record (a checkpoint trained before the spread gets ``FALLBACK_SPREAD``).
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa

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


def ood_scores(inputs: TargetInputs, ood: dict[str, Any], source_hz: NDArrayFloat | None = None
               ) -> tuple[NDArrayFloat, NDArrayBool, list[str]]:
    """(scores (N,), flags (N,), reasons (N,): the descriptors outside, ``""`` for none) of targets against a
    checkpoint's ``ood`` record; ``source_hz``: per target the rate its log was recorded at before ingest resampled
    it (NaN: not resampled), checked against the training rates as the window's own rate is."""
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
        elif kind == "unknown":  # e.g. Argoverse 1's OTHERS: pedestrians and cars alike, so training says nothing
            score[i] += 1.0
            reasons[i].append("agent type unknown: its format does not label it (a pedestrian or a car)")
        rate = float(inputs.rate_hz[i])
        if not len(rates) or np.min(np.abs(rates - rate) / rates) > RATE_TOLERANCE:
            score[i] += 1.0
            reasons[i].append(f"frame rate {rate:g} Hz not in training {rates.tolist()}")
        source = float(source_hz[i]) if source_hz is not None else float("nan")
        if np.isfinite(source) and (not len(rates) or np.min(np.abs(rates - source) / rates) > RATE_TOLERANCE):
            score[i] += 1.0
            reasons[i].append(f"recorded at {source:g} Hz and resampled to {rate:g} Hz; training recorded at "
                              f"{sorted(set(np.round(rates).tolist()))} Hz")
        if ood["map_share"] > 1.0 - UNSEEN_SHARE and not inputs.has_map[i]:
            score[i] += 1.0
            reasons[i].append("no map under the target")
    return score, score > FLAG_SCORE, ["; ".join(r) for r in reasons]


FALLBACK_GRID = tuple((q, r) for q in (0.003, 0.01, 0.03, 0.1, 0.3) for r in (0.01, 0.03, 0.1, 0.3, 1.0))
"""Candidate (accel_std m/step^2, meas_std m) of the fallback Kalman filter, chosen on the training targets."""


def _training_subset(inputs: TargetInputs, max_targets: int, seed: int) -> tuple[TargetInputs, NDArrayFloat]:
    """At most ``max_targets`` training targets (a seeded draw, in order) and their true futures in world metres."""
    assert inputs.truth is not None
    rows = np.arange(len(inputs))
    if len(rows) > max_targets:
        rows = np.sort(np.random.default_rng(seed).choice(rows, max_targets, replace=False))
    part = inputs.take(rows)
    assert part.truth is not None
    truth: NDArrayFloat = part.prior + np.einsum("nji,ntj->nti", part.rotation, part.truth * part.scale[:, None, None])
    return part, truth


def tune_fallback(inputs: TargetInputs, max_targets: int = 20_000, seed: int = 0) -> dict[str, float]:
    """The Kalman filter's noise with the lowest mean FDE on (at most ``max_targets`` of) the training targets."""
    part, truth = _training_subset(inputs, max_targets, seed)
    pred_len = truth.shape[1]

    def fde(q: float, r: float) -> float:
        forecast = KalmanCV(pred_len=pred_len, accel_std=q, meas_std=r).filter_tracks(part.observed)
        return float(np.nanmean(np.linalg.norm(forecast[:, -1] - truth[:, -1], axis=1)))

    q, r = min(FALLBACK_GRID, key=lambda g: fde(*g))
    return {"accel_std": q, "meas_std": r}


SPREAD_PATTERN = ((1, 0), (-1, 0), (0, 1), (0, -1), (1, 1), (-1, -1), (1, -1), (-1, 1))
"""(heading steps, speed steps) of modes 1, 2, ... of the fallback; further modes repeat it at 2x, 3x..."""
SPREAD_GRID = tuple((h, v) for h in (0.005, 0.01, 0.02, 0.04, 0.08, 0.16) for v in (0.025, 0.05, 0.1, 0.2, 0.4))
"""Candidate (heading step rad, relative speed step) of the fallback's spread: both steps above 0, so no two of
its modes coincide (a moving target's)."""
FALLBACK_SPREAD = {"heading_step_rad": 0.04, "speed_step_frac": 0.1}
"""The spread of a checkpoint whose ``ood`` record has none (trained before it existed)."""


def spread_modes(base: NDArrayFloat, current: NDArrayFloat, modes: int, heading_step_rad: float,
                 speed_step_frac: float) -> NDArrayFloat:
    """(N, modes, T, 2): mode 0 ``base`` (N, T, 2), mode i its displacement from ``current`` (N, 2) turned by
    a_i x ``heading_step_rad`` and stretched by 1 + b_i x ``speed_step_frac`` ((a_i, b_i) from ``SPREAD_PATTERN``):
    deterministic, so a target's forecasts do not depend on its batch."""
    out = np.repeat(base[:, None], max(modes, 1), axis=1)
    offset = base - current[:, None]
    for i in range(1, modes):
        a, b = SPREAD_PATTERN[(i - 1) % len(SPREAD_PATTERN)]
        times = 1 + (i - 1) // len(SPREAD_PATTERN)
        turn, stretch = a * times * heading_step_rad, max(1.0 + b * times * speed_step_frac, 0.0)
        c, s = np.cos(turn), np.sin(turn)
        out[:, i] = current[:, None] + stretch * np.stack([c * offset[..., 0] - s * offset[..., 1],
                                                           s * offset[..., 0] + c * offset[..., 1]], -1)
    return out[:, :modes]


def tune_spread(inputs: TargetInputs, kalman: dict[str, float], modes: int = 6, max_targets: int = 20_000,
                seed: int = 0) -> dict[str, float]:
    """The spread with the lowest minFDE@``modes`` of the Kalman fallback on (at most ``max_targets`` of) the
    training targets."""
    part, truth = _training_subset(inputs, max_targets, seed)
    base = KalmanCV(pred_len=truth.shape[1], accel_std=kalman["accel_std"],
                    meas_std=kalman["meas_std"]).filter_tracks(part.observed)

    def min_fde(h: float, v: float) -> float:
        paths = spread_modes(base, part.observed[:, -1], modes, h, v)
        return float(np.nanmean(np.linalg.norm(paths[:, :, -1] - truth[:, None, -1], axis=-1).min(axis=1)))

    h, v = min(SPREAD_GRID, key=lambda g: min_fde(*g))
    return {"heading_step_rad": h, "speed_step_frac": v}


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
    source_hz: dict[str, float] = field(default_factory=dict)
    """Log id -> the rate it was recorded at, for logs ingest resampled (the logs table's ``resampled_from_hz``)."""

    def __call__(self, samples: Sequence[SceneSample], futures: Sequence[Any]
                 ) -> tuple[list[Any], list[tuple[NDArrayFloat, NDArrayBool, NDArrayBool]]]:
        """(the forecasts to write, each sample's (scores, flags, fallback) per target)."""
        config = replace(self.config, environment=False)
        fallback = self.ood.get("fallback_kalman", {})
        kalman = KalmanCV(pred_len=config.pred_len, **fallback)
        spread = self.ood.get("fallback_spread", FALLBACK_SPREAD)
        out, rows = [], []
        for sample, given in zip(samples, futures, strict=True):
            inputs = target_inputs(sample, config)
            source = self.source_hz.get(sample.sample_id.rsplit(":", 1)[0], float("nan"))
            scores, flags, reasons = ood_scores(inputs, self.ood, np.full(len(inputs), source))
            if flags.any() and self.action == "refuse":
                first = int(np.flatnonzero(flags)[0])
                raise LogpipeError(f"{int(flags.sum())} targets of {sample.sample_id} are outside the checkpoint's "
                                   f"training data (--out-of-distribution refuse), e.g. "
                                   f"{sample.track_ids[int(np.flatnonzero(sample.target_mask)[first])]}: "
                                   f"{reasons[first]}")
            replaced = flags & (self.action == "fallback")
            future = np.array(given, np.float64, copy=True)
            if replaced.any():  # the K modes kept: the Kalman forecast and a spread of it
                base = kalman.filter_tracks(inputs.observed[replaced])[:, : future.shape[2]]
                future[replaced] = spread_modes(base, inputs.observed[replaced, -1], future.shape[1], **spread)
            out.append(future)
            rows.append((scores, flags, replaced))
        return out, rows


def ood_check_for(checkpoint: Path, action: str, logs: pa.Table | None = None) -> OodCheck:
    """The check of a residual checkpoint folder with ``--out-of-distribution`` ``action``; ``logs``: the logs
    table of the run (their ``attributes["resampled_from_hz"]``)."""
    from .meta import read_residual_meta  # here: the check is built only for residual checkpoints

    meta = read_residual_meta(checkpoint)
    source: dict[str, float] = {}
    if logs is not None:
        for log_id, text in zip(logs.column("log_id").to_pylist(), logs.column("attributes").to_pylist(), strict=True):
            hz = json.loads(text or "{}").get("resampled_from_hz") if text and "resampled_from_hz" in text else None
            if hz:
                source[str(log_id)] = float(hz)
    return OodCheck(meta.ood, meta.config, action, source)
