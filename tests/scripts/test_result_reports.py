"""The reports of ``scripts/highway_speeds.py``, ``scripts/shipped_holdout.py`` and ``scripts/ethucy_baselines.py``:
the results files in ``docs/results`` are what the scripts write from their JSON, and the figures they compute say
what the numbers do."""

from __future__ import annotations

import copy
import json
from pathlib import Path
from typing import Any

import numpy as np

from scripts import ethucy_baselines, highway_speeds, shipped_holdout

RESULTS = Path(__file__).resolve().parents[2] / "docs" / "results"


def test_the_results_files_are_the_scripts_rendering_of_their_json() -> None:
    highway = json.loads((RESULTS / "highway_speeds.json").read_text())
    assert highway_speeds.markdown(highway) == (RESULTS / "highway_speeds.md").read_text()
    holdout = json.loads((RESULTS / "driving_holdout.json").read_text())
    assert shipped_holdout.markdown(holdout) == (RESULTS / "driving_holdout.md").read_text()
    kinematic = json.loads((RESULTS / "ethucy_baselines.json").read_text())
    assert ethucy_baselines.markdown(kinematic) == (RESULTS / "ethucy_baselines.md").read_text()


def _arm(k1: float, k6: float, hours: float = 0.05) -> dict[str, Any]:
    band = {"targets": 1, "fde": 1.0, "best_kinematic_fde": 1.0}
    return {"fde_ratio": k1, "min_fde_ratio": k6, "core_hours": hours, "synthetic_targets": 10,
            "by_speed": {"0-10": band}}


def test_an_arm_helps_only_beyond_every_seed_of_the_real_only_fold() -> None:
    runs = {"0": {"real only": _arm(1.5, 0.8), "a": _arm(1.1, 0.6, 0.15), "b": _arm(1.1, 0.9)},
            "1": {"real only": _arm(1.2, 0.7), "a": _arm(1.0, 0.6, 0.15), "b": _arm(1.0, 0.5)}}
    lines = highway_speeds._reading(runs, ["0", "1"], ["real only", "a", "b"])
    assert "spans 1.20-1.50 (mean 1.35)" in lines[0]
    a, b = (next(line for line in lines if line.startswith(f"- {name} ")) for name in "ab")
    assert "better than every real-only seed on both" in a and "+0.100 core-hours" in a
    assert "no held-out gain shown" in b  # K = 1 beyond, minFDE@6 mean 0.70 not below the real-only 0.70


def test_the_holdout_summary_pools_and_splits_by_location() -> None:
    def part(where: str, shipped: float, best: float, n: int) -> dict[str, Any]:
        rows = {name: {"fde": np.full(n, best), "min_fde": np.full(n, best)} for name in
                ("mean head", "best kinematic baseline", "cv", "least_squares_cv", "kalman", "adaptive_prior",
                 "cv sampler")}
        rows["as predict runs it"] = {"fde": np.full(n, shipped), "min_fde": np.full(n, shipped / 2)}
        return {"location": np.array([where] * n), "errors": rows, "windows": 1}

    groups = shipped_holdout.summarise([part("ngsim A", 1.0, 2.0, 3), part("ngsim B", 3.0, 3.0, 1)])
    assert groups["pooled"]["targets"] == 4 and groups["pooled"]["as predict runs it"] == 1.5
    assert groups["ngsim A"]["best kinematic baseline"] == 2.0 and groups["ngsim B"]["min_fde@6"] == 1.5
    result: dict[str, Any] = {"checkpoint": "c", "train_split": "hash/train", "windows": 2, "groups": groups}
    assert "Worst ratio of the default to the best kinematic baseline: 1.000" in shipped_holdout.markdown(result)
    worse = copy.deepcopy(result)
    worse["groups"]["ngsim B"]["as predict runs it"] = 3.3
    assert "baseline: 1.100" in shipped_holdout.markdown(worse)
