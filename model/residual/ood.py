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
only if it saw enough targets without one), and 1 for a target on a road the model was never trained on: its log's
location (``logpipe.dataset.locations.log_location``: CommonRoad's location, else the map or city) is not among the
training windows' locations, or it has none while they had (a checkpoint whose training logs named no location
judges no road). A target is flagged
when its score exceeds ``FLAG_SCORE`` (a quarter of a range beyond, or any unseen type or rate, or no map). The
reasons name the descriptors that put it there.

``OodCheck`` applies this in ``logpipe predict`` (``--out-of-distribution auto|warn|fallback|refuse``). The fallback
keeps the K modes: mode 0 (the K = 1 forecast) becomes the best kinematic baseline chosen on the training targets
(``model.kinematic.best_baseline``, stored as ``fallback_k1``), and modes 1..K-1 are the model's mode heads as
``modes.spread_modes`` takes them around it, so best-of-K keeps what the model learnt while K = 1 is physics. The
mean head gives way: it is a forecast of the same kind as physics, and on the validation targets of all six
leave-one-location-out folds, physics + the five best-scored mode heads gave minFDE@6 0.756 m against 0.837 for
physics + the mean head + four mode heads (turning targets 3.90 against 4.03; every fold alike). ``auto``, the default,
falls back where the model has no evidence for a correction: on roads it was never trained on (the
leave-one-location-out run measured that its corrections do harm there: ``docs/results/driving_lolo.md``), and on
roads it trained on where its validation did not show its K = 1 beating that baseline on at least
``MIN_EVIDENCE_TARGETS`` targets (``k1_by_location``, recorded by training; a held-out Peachtree recording lost
1.10x to physics with a model trained on five others, and no Peachtree recording validated it:
``docs/results/driving_holdout.md``); other flags are only marked. ``fallback`` falls back on every flagged
target. A checkpoint whose training run could not show on its validation data that the model beats that baseline
at K = 1 (``k1_source`` ``physics``: ``logpipe train`` on driving data decides) falls back on every target, except
with ``warn``. A checkpoint trained before
``fallback_k1`` falls back to its Kalman filter (``fallback_kalman``).
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa

from logpipe.dataset.locations import log_locations
from logpipe.errors import LogpipeError
from logpipe.types import OBJECT_TYPES, NDArrayBool, NDArrayFloat, SceneSample

from ..kinematic import best_baseline
from .config import ResidualConfig
from .inputs import TargetInputs, target_inputs
from .modes import spread_modes

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


UNSEEN_LOCATION = "not trained on this road"
"""The reason's start for a target whose log's location the training never had."""


def training_distribution(inputs: TargetInputs, locations: dict[str, int] | None = None) -> dict[str, Any]:
    """The ``ood`` record of a checkpoint trained on ``inputs``; ``locations``: the training windows per location
    (``{}``: their logs name none)."""
    ranges = {name: [float(np.quantile(v, q)) for q in QUANTILES] for name, v in _numeric(inputs).items()}
    types, counts = np.unique(inputs.object_type, return_counts=True)
    return {"quantiles": list(QUANTILES), "ranges": ranges,
            "rates_hz": sorted({round(float(r), 3) for r in inputs.rate_hz}),
            "object_types": {OBJECT_TYPES[int(t)]: int(c) for t, c in zip(types, counts, strict=True)},
            "map_share": float(np.mean(inputs.has_map)) if len(inputs) else 0.0, "targets": len(inputs),
            "flag_score": FLAG_SCORE,
            **({"locations": dict(sorted(locations.items()))} if locations is not None else {})}


MIN_EVIDENCE_TARGETS = 30
"""Validation targets a location needs before its K = 1 comparison counts as evidence."""
NO_LOCATION = "(no location)"
"""The ``k1_by_location`` key of targets whose logs name no location."""


def k1_evidence(model_fde: NDArrayFloat, baseline_fde: NDArrayFloat, locations: Sequence[str | None]
                ) -> dict[str, dict[str, Any]]:
    """Per location of the validation targets (their K = 1 final errors, metres, of the model's mean head and of
    the best kinematic baseline): the targets, both mean FDEs and the K = 1 ``source``, ``model`` only where it beat
    the baseline on at least ``MIN_EVIDENCE_TARGETS`` targets (the checkpoint's ``ood["k1_by_location"]``)."""
    where = np.array([loc or NO_LOCATION for loc in locations], dtype=object)
    out = {}
    for loc in sorted(set(where.tolist())):
        m = where == loc
        mine, theirs = float(model_fde[m].mean()), float(baseline_fde[m].mean())
        source = "model" if m.sum() >= MIN_EVIDENCE_TARGETS and mine < theirs else "physics"
        out[str(loc)] = {"targets": int(m.sum()), "model_fde": round(mine, 4), "baseline_fde": round(theirs, 4),
                         "source": source}
    return out


def k1_evidenced(ood: dict[str, Any], location: str | None) -> bool:
    """Whether the checkpoint's validation showed its K = 1 beats the best kinematic baseline at ``location``
    (True for a checkpoint that predates the record: it cannot tell)."""
    evidence = ood.get("k1_by_location")
    if evidence is None:
        return True
    entry = evidence.get(location or NO_LOCATION)
    return bool(entry) and entry["source"] == "model"


def unseen_location(ood: dict[str, Any], location: str | None) -> bool:
    """Whether a log at ``location`` lies on roads the checkpoint never trained on (False when its training logs
    named no location, or it predates the record: it cannot judge)."""
    known = ood.get("locations") or {}
    return bool(known) and location not in known


def ood_scores(inputs: TargetInputs, ood: dict[str, Any], source_hz: NDArrayFloat | None = None,
               location: str | None = None) -> tuple[NDArrayFloat, NDArrayBool, list[str]]:
    """(scores (N,), flags (N,), reasons (N,): the descriptors outside, ``""`` for none) of targets against a
    checkpoint's ``ood`` record; ``source_hz``: per target the rate its log was recorded at before ingest resampled
    it (NaN: not resampled), checked against the training rates as the window's own rate is; ``location``: the
    targets' log's location."""
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
    if unseen_location(ood, location):
        score += 1.0
        for r in reasons:
            r.append(f"{UNSEEN_LOCATION} ({location or 'no location'}; trained on {', '.join(ood['locations'])})")
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


def tune_baselines(inputs: TargetInputs, max_targets: int = 20_000, seed: int = 0) -> dict[str, Any]:
    """The ``ood`` record's fallbacks, chosen on (at most ``max_targets`` of) the training targets: ``baselines``
    (each kinematic method's best setting, ``best_baseline.choose_per_method``), ``fallback_k1`` (the best of them)
    and ``fallback_kalman`` (the Kalman filter's noise, the record older readers know)."""
    part, truth = _training_subset(inputs, max_targets, seed)
    per_method = best_baseline.choose_per_method(part.observed, truth)
    kalman = per_method["kalman"]
    return {"baselines": per_method, "fallback_k1": best_baseline.choose(per_method),
            "fallback_kalman": {"accel_std": kalman["accel_std"], "meas_std": kalman["meas_std"]}}


def fallback_forecasts(ood: dict[str, Any], observed: NDArrayFloat, ranked: NDArrayFloat, num_modes: int
                       ) -> NDArrayFloat:
    """(N, num_modes, T, 2): mode 0 the checkpoint's K = 1 fallback for tracks ``observed`` (N, T_obs, 2), then the
    model's mode heads of ``ranked`` (N, 1 + heads, T, 2: ``fit.ranked_forecasts``) as ``modes.spread_modes`` takes
    them around it (see the module docstring)."""
    return spread_modes(physics_forecast(ood, observed, ranked.shape[2]), ranked[:, 1:], num_modes)


def physics_forecast(ood: dict[str, Any], observed: NDArrayFloat, pred_len: int) -> NDArrayFloat:
    """(N, T, 2): the checkpoint's K = 1 fallback (``fallback_k1``, else its Kalman filter) for ``observed``."""
    choice = ood.get("fallback_k1") or {"method": "kalman", **ood.get("fallback_kalman", {})}
    return best_baseline.forecast(choice, observed, pred_len)


@dataclass(frozen=True)
class OodCheck:
    """``logpipe predict``'s out-of-distribution check for a residual checkpoint (picklable: shard workers run it).

    Attributes:
        ood: the checkpoint's ``ood`` record; ``config``: its ``ResidualConfig`` (the inputs are computed as the
            network's, without crops); ``action``: one of ``OUT_OF_DISTRIBUTION_ACTIONS`` (see the module docstring);
            ``num_modes``: K, the modes it writes.
    """

    ood: dict[str, Any]
    config: ResidualConfig
    action: str
    num_modes: int
    source_hz: dict[str, float] = field(default_factory=dict)
    """Log id -> the rate it was recorded at, for logs ingest resampled (the logs table's ``resampled_from_hz``)."""
    locations: dict[str, str | None] = field(default_factory=dict)
    """Log id -> its location (``logpipe.dataset.locations.log_location``)."""

    def __call__(self, samples: Sequence[SceneSample], ranked: Sequence[Any]
                 ) -> tuple[list[Any], list[tuple[NDArrayFloat, NDArrayBool, NDArrayBool]]]:
        """(the K forecasts to write, each sample's (scores, flags, fallback) per target), given each sample's
        ``ResidualPredictor.predict_ranked`` forecasts."""
        config = replace(self.config, environment=False)
        out, rows = [], []
        for sample, given in zip(samples, ranked, strict=True):
            inputs = target_inputs(sample, config)
            log_id = sample.sample_id.rsplit(":", 1)[0]
            location = self.locations.get(log_id)
            source = self.source_hz.get(log_id, float("nan"))
            scores, flags, reasons = ood_scores(inputs, self.ood, np.full(len(inputs), source), location)
            if flags.any() and self.action == "refuse":
                first = int(np.flatnonzero(flags)[0])
                raise LogpipeError(f"{int(flags.sum())} targets of {sample.sample_id} are outside the checkpoint's "
                                   f"training data (--out-of-distribution refuse), e.g. "
                                   f"{sample.track_ids[int(np.flatnonzero(sample.target_mask)[first])]}: "
                                   f"{reasons[first]}")
            physics_k1 = self.ood.get("k1_source") == "physics" and self.action != "warn"
            if self.action == "fallback":
                replaced = flags | physics_k1
            elif self.action == "auto":
                replaced = np.full(len(flags), unseen_location(self.ood, location) or physics_k1
                                   or not k1_evidenced(self.ood, location))
            else:
                replaced = np.zeros(len(flags), bool)
            modes = np.asarray(given, np.float64)
            mode0 = modes[:, 0].copy()
            if replaced.any():
                mode0[replaced] = physics_forecast(self.ood, inputs.observed[replaced], modes.shape[2])
            out.append(spread_modes(mode0, modes[:, 1:], self.num_modes))
            rows.append((scores, flags, replaced))
        return out, rows


def ood_check_for(checkpoint: Path, action: str, num_modes: int, logs: pa.Table | None = None) -> OodCheck:
    """The check of a residual checkpoint folder with ``--out-of-distribution`` ``action``, writing ``num_modes``
    modes; ``logs``: the logs table of the run (each log's location and ``attributes["resampled_from_hz"]``)."""
    from .meta import read_residual_meta  # here: the check is built only for residual checkpoints

    meta = read_residual_meta(checkpoint)
    source: dict[str, float] = {}
    locations: dict[str, str | None] = {}
    if logs is not None:
        locations = log_locations(logs)
        for log_id, text in zip(logs.column("log_id").to_pylist(), logs.column("attributes").to_pylist(), strict=True):
            hz = json.loads(text or "{}").get("resampled_from_hz") if text and "resampled_from_hz" in text else None
            if hz:
                source[str(log_id)] = float(hz)
    return OodCheck(meta.ood, meta.config, action, num_modes, source, locations)
