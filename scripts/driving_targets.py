"""Every real driving target we hold, under one protocol, with what the leave-one-location-out evaluation needs
(issue 57): the residual model's inputs, the six locations, the recordings to resample, the turning targets, and
the classical baselines' forecasts of the same targets.

Data (``build_datasets``; ingest and rasterise skip finished work): the 69 Argoverse 1 sequences (``AV1_MIA``,
``AV1_PIT``: the window of each; every agent but the AV observed at all 50 steps is a target, AV1 labels no other
classes), the AV2 scenario and sensor logs (``AV2``: sliding windows, stride 10; every vehicle observed throughout,
the AV excepted) and the 51 NGSIM CommonRoad scenarios (``USA_US101``, ``USA_Lanker``, ``USA_Peach``: sliding
windows, stride 10, every car observed throughout). 20 observed + 30 predicted steps at 10 Hz; rasters 224 x 224
over 100 m from each log's own map, turned to the centre agent's heading.

Recordings: the bootstrap resamples clusters of logs that may show the same vehicles (CommonRoad files flagged
with shared tracks are joined into one cluster; every other log is its own). Turning: the direction of the last
0.5 s of the true future differs by more than 20 degrees from that of the last 0.4 s observed (both over 0.5 m).
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Sequence
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any

import numpy as np

from logpipe.api import ingest, rasterise
from logpipe.dataset.locations import track_sharing_groups
from logpipe.dataset.reader import Dataset, hash_fraction
from logpipe.model.residual.config import ResidualConfig
from logpipe.model.residual.fit import at_most, collect
from logpipe.model.residual.inputs import INPUTS_VERSION, TargetInputs, concat
from logpipe.raster.runs import find_raster_run
from logpipe.stages.train import scene_samples
from logpipe.types import NDArrayFloat, SceneSample

LOCATIONS = ("AV1_MIA", "AV1_PIT", "AV2", "USA_US101", "USA_Lanker", "USA_Peach")
TURN_DEG = 20.0
VAL_SHARE = 0.15
"""Share of each training location's recording clusters held out for validation (by hash of the cluster)."""


def build_datasets(shared: Path, work: Path) -> dict[str, Dataset]:
    """The three real driving datasets, ingested and rasterised into ``work`` (nothing redone that is done)."""
    av1, av2, ngsim = work / "av1", work / "av2", work / "ngsim"
    ingest([shared / "argoverse1" / "data"], out=av1, protocol="argoverse", targets="fully_observed_no_ego",
           mcap=False, workers=1)
    ingest([shared / "av2"], out=av2, protocol="argoverse2", obs=20, pred=30, window="sliding", stride=10,
           targets="fully_observed_no_ego", target_types="vehicle,bus_truck", mcap=False, workers=1)
    ingest([shared / "commonroad" / "ngsim"], out=ngsim, mcap=False, workers=1)
    rasterise(av1, maps=[shared / "argoverse1" / "maps"], rotate=True, workers=1)
    rasterise(av2, maps=[shared / "av2"], rotate=True, workers=1)
    rasterise(ngsim, rotate=True, workers=1)
    return {"av1": Dataset.open(av1), "av2": Dataset.open(av2), "ngsim": Dataset.open(ngsim)}


@dataclass
class Targets:
    """Targets of one or more datasets, in sample order then target-mask order.

    Attributes:
        inputs: the residual model's inputs, with the true futures.
        future: (N, T, 2) true futures, world metres; ``location``, ``log``, ``cluster``, ``sample`` per target.
        window: (N,) window number (unique over all datasets); ``turning`` (N,) bool.
        samples: the windows' ``SceneSample``s (for the classical baselines), in order.
    """

    inputs: TargetInputs
    future: NDArrayFloat
    location: np.ndarray
    log: np.ndarray
    cluster: np.ndarray
    sample: np.ndarray
    window: np.ndarray
    turning: np.ndarray
    samples: list[SceneSample]

    def rows(self, mask: np.ndarray) -> np.ndarray:
        """Row indices of a boolean mask."""
        return np.flatnonzero(mask)

    def validation(self) -> np.ndarray:
        """(N,) True for targets of the validation clusters (``VAL_SHARE`` of each location's, by hash)."""
        return np.array([hash_fraction(f"val:{c}") < VAL_SHARE for c in self.cluster])


def _location(kind: str, attributes: dict[str, Any], map_id: str | None) -> str:
    if kind == "av1":
        return f"AV1_{map_id}"
    if kind == "av2":
        return "AV2"
    return str(attributes.get("location"))


def turning(observed: NDArrayFloat, future: NDArrayFloat) -> np.ndarray:
    """(N,) whether each target's future turns by more than ``TURN_DEG`` (see the module docstring)."""
    before = observed[:, -1] - observed[:, -5]
    after = future[:, -1] - future[:, -6]
    moving = (np.linalg.norm(before, axis=1) > 0.5) & (np.linalg.norm(after, axis=1) > 0.5)
    turn = np.arctan2(after[:, 1], after[:, 0]) - np.arctan2(before[:, 1], before[:, 0])
    degrees = np.degrees(np.abs((turn + np.pi) % (2 * np.pi) - np.pi))
    turns: np.ndarray = moving & (degrees > TURN_DEG)
    return turns


def dataset_targets(kind: str, ds: Dataset, config: ResidualConfig, window_offset: int, per_window: int = 0
                    ) -> Targets:
    """Every target of a dataset (its only raster run feeds the environment net's crops), or at most ``per_window``
    of each window (``model.residual.fit.at_most``)."""
    run = find_raster_run(ds.root, None, None)
    logs = ds.logs().to_pylist()
    meta = {r["log_id"]: (json.loads(r["attributes"] or "{}"), r["map_id"]) for r in logs}
    clusters = track_sharing_groups([r["log_id"] for r in logs], [r["attributes"] for r in logs])
    samples = [at_most(s, per_window, 0, n) for n, s in enumerate(scene_samples(ds, "all", rasters=run))]
    inputs, windows = collect(samples, config)
    per = [int(np.sum(s.target_mask)) for s in samples]
    log = np.repeat([s.log_id for s in samples], per)
    future = np.concatenate([s.positions[np.asarray(s.target_mask, bool), s.obs_len:] for s in samples])
    observed = np.concatenate([s.positions[np.asarray(s.target_mask, bool), :s.obs_len] for s in samples])
    return Targets(inputs, future, np.array([_location(kind, *meta[g]) for g in log]), log,
                   np.array([f"{kind}:{clusters[g]}" for g in log]), np.repeat([s.sample_id for s in samples], per),
                   windows + window_offset, turning(observed, future), samples)


def join(parts: Sequence[Targets]) -> Targets:
    """Several datasets' targets as one."""
    def cat(name: str) -> np.ndarray:
        return np.concatenate([getattr(p, name) for p in parts])

    return Targets(concat([p.inputs for p in parts]), cat("future"), cat("location"), cat("log"), cat("cluster"),
                   cat("sample"), cat("window"), cat("turning"), [s for p in parts for s in p.samples])


def config_key(config: ResidualConfig) -> str:
    """Short hash of the settings the inputs depend on (the cache key)."""
    keys = ("obs_len", "pred_len", "environment", "crop_px", "crop_res_m", "crop_behind_m", "neighbours",
            "neighbour_radius_m", "neighbour_steps", "min_scale_m", "horizon_scale_s")
    blob = json.dumps({k: getattr(config, k) for k in keys} | {"inputs_version": INPUTS_VERSION},
                      sort_keys=True).encode()
    return hashlib.sha256(blob).hexdigest()[:12]


_ARRAYS = ("future", "location", "log", "cluster", "sample", "window", "turning")


def save_targets(targets: Targets, extra: dict[str, NDArrayFloat], path: Path) -> None:
    """Cache the targets (without their samples) and ``extra`` per-target arrays in one ``.npz``."""
    arrays = {f"inputs.{f.name}": getattr(targets.inputs, f.name) for f in fields(TargetInputs)
              if getattr(targets.inputs, f.name) is not None}
    arrays |= {k: getattr(targets, k) for k in _ARRAYS} | {f"extra.{k}": v for k, v in extra.items()}
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp.npz")
    np.savez(tmp, **arrays)
    tmp.replace(path)


def load_targets(path: Path) -> tuple[Targets, dict[str, NDArrayFloat]]:
    """What ``save_targets`` cached (``samples`` empty)."""
    with np.load(path, allow_pickle=False) as data:
        got = {k: data[k] for k in data.files}
    stored: dict[str, Any] = {f.name: got.get(f"inputs.{f.name}") for f in fields(TargetInputs)}
    inputs = TargetInputs(**stored)
    extra = {k.removeprefix("extra."): v for k, v in got.items() if k.startswith("extra.")}
    return Targets(inputs, got["future"], got["location"], got["log"], got["cluster"], got["sample"], got["window"],
                   got["turning"], []), extra


def real_targets(datasets: dict[str, Dataset], config: ResidualConfig) -> Targets:
    """Every real target of the three datasets, windows numbered across them."""
    parts, offset = [], 0
    for kind in ("av1", "av2", "ngsim"):
        part = dataset_targets(kind, datasets[kind], config, offset)
        offset = int(part.window.max()) + 1
        parts.append(part)
    return join(parts)
