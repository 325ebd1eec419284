"""scripts.reproduce_driving: its scoring rules on hand-made forecasts, and a run over the real logs."""

from __future__ import annotations

import json
import math
import shutil
from pathlib import Path

import numpy as np
import pytest

from scripts.locations import REPO
from scripts.reproduce_driving import interval, main, scores


def _straight(n_steps: int, offset_m: float) -> np.ndarray:
    """(T, 2) a path along +x shifted sideways by ``offset_m``."""
    return np.stack([np.arange(1, n_steps + 1, dtype=np.float64), np.full(n_steps, offset_m)], axis=-1)


def test_joint_picks_one_mode_per_window_and_per_agent_one_per_target() -> None:
    t = 5
    truth = np.stack([_straight(t, 0.0), _straight(t, 0.0)])
    pred = np.zeros((2, 6, t, 2))
    for k in range(6):  # every mode 3 m off, but mode 1 is exact for agent 0 and mode 2 for agent 1
        pred[:, k] = _straight(t, 3.0)
    pred[0, 1], pred[1, 2] = truth[0], truth[1]
    window = np.array([0, 0])
    s = scores(pred, truth, window)
    assert s["k6"]["ade"] == 0.0 and s["k6"]["fde"] == 0.0  # each target's own best mode
    assert s["k6"]["ade_joint"] == pytest.approx(1.5) and s["k6"]["fde_joint"] == pytest.approx(1.5)
    assert s["k1"]["ade"] == pytest.approx(3.0) and s["k1"]["miss_rate"] == 1.0  # K=1 is mode 0 only
    assert s["k6"]["miss_rate"] == 0.0
    np.testing.assert_array_equal(s["agent_fde"], [0.0, 0.0])


def test_interval_is_the_student_t_half_width_over_seeds() -> None:
    mean, half = interval([1.0, 2.0, 3.0])
    assert mean == 2.0 and half == pytest.approx(4.303 * 1.0 / math.sqrt(3))
    assert math.isnan(interval([1.0])[1])


@pytest.mark.shared
def test_scoring_run_over_the_real_logs_counts_windows_by_log_split(shared: Path, tmp_path: Path) -> None:
    code = main(["--av1", str(shared / "argoverse1" / "data"), "--av1-maps", str(shared / "argoverse1" / "maps"),
                 "--av2", str(shared / "av2"), "--work", str(tmp_path / "work"), "--runs", str(tmp_path / "none"),
                 "--results", str(tmp_path / "results"), "--no-train", "--seeds", "0"])
    assert code == 0
    result = json.loads((tmp_path / "results" / "argoverse_logs.json").read_text())
    windows = result["counts"]["windows"]
    assert sum(windows["argoverse1"].values()) == 69  # one window per AV1 sequence
    assert sum(windows["argoverse2"].values()) == 51  # sliding 20 + 30 steps at stride 10 over the AV2 logs
    assert result["counts"]["test_windows"] == windows["argoverse1"]["hash/test"] + windows["argoverse2"]["hash/test"]
    assert set(result["methods"]) == {"cv", "kalman", "cv_sampler"}  # no run folder: learned rows not run
    cv = result["methods"]["cv"]
    assert cv["k1"] == cv["k6"]  # one deterministic forecast repeated
    sampler = result["methods"]["cv_sampler"]["k6"]
    assert sampler["ade"] <= sampler["ade_joint"] and sampler["argo_fde"] >= sampler["fde"]
    assert "not run" in (tmp_path / "results" / "argoverse_logs.md").read_text()


@pytest.mark.shared
def test_learned_rows_name_the_seeds_that_finished(shared: Path, tmp_path: Path) -> None:
    # A finished run for seed 1 only (the shipped full model stands in for it); seed 0 never ran.
    run = tmp_path / "runs" / "full"
    shutil.copytree(REPO / "model" / "checkpoints" / "argoverse" / "paper", run / "seed1" / "best")
    (run / "seed1.json").write_text(json.dumps({"seconds": 30.0, "seconds_total": 90.0}))
    code = main(["--av1", str(shared / "argoverse1" / "data"), "--av1-maps", str(shared / "argoverse1" / "maps"),
                 "--av2", str(shared / "av2"), "--work", str(tmp_path / "work"), "--runs", str(tmp_path / "runs"),
                 "--results", str(tmp_path / "results"), "--no-train", "--seeds", "0", "1"])
    assert code == 0
    result = json.loads((tmp_path / "results" / "argoverse_logs.json").read_text())
    assert result["methods"]["full"]["seeds"] == [1]
    assert result["train_minutes"] == {"full/seed1": 1.5}  # all sessions of a resumed run
    row = next(line for line in (tmp_path / "results" / "argoverse_logs.md").read_text().splitlines()
               if line.startswith("| The paper's method, full"))
    assert row.split(" | ")[1] == "1"
