"""Every dataset kind has a default predictor that runs: ``logpipe predict`` on a ROS-bag dataset (the bundled
``datmo/intersection.bag``) needs no flag, uses the best kinematic baseline and says which and why; a dataset of the
driving model's kinds gets the driving model, and says so. The baseline's claim to be the best is checked against
the result files it cites (``docs/results/*.json``)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from typer.testing import CliRunner

from logpipe.cli import app
from logpipe.model.registry import BASELINES, DEFAULT_BASELINE

runner = CliRunner()
RESULTS = Path(__file__).resolve().parents[2] / "docs" / "results"


def _ok(*args: str) -> dict[str, object]:
    result = runner.invoke(app, [*args, "--json"])
    assert result.exit_code == 0, result.output
    summary: dict[str, object] = json.loads(result.stdout)
    return summary


@pytest.fixture(scope="module")
def bag_dataset(bundled: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("bag") / "ros"
    _ok("ingest", str(bundled / "rosbags" / "datmo" / "intersection.bag"), "--out", str(out))
    return out


def test_predict_on_a_bag_dataset_runs_with_no_flags_and_says_why(bag_dataset: Path) -> None:
    out = bag_dataset.parent / "pred"
    result = runner.invoke(app, ["predict", str(bag_dataset), "--out", str(out)])
    assert result.exit_code == 0, result.output
    why = next(line for line in result.stderr.splitlines() if line.startswith("  predictor "))
    assert why.startswith(f"  predictor {DEFAULT_BASELINE}: the kinematic baseline with the lowest K=1 FDE")
    assert "dataset kind 'rosbag' (its tracks: unknown and vehicle agents, no map;" in why  # the bag's two poses
    summary = _ok("predict", str(bag_dataset), "--out", str(bag_dataset.parent / "pred-json"))
    assert summary["predictor"] == DEFAULT_BASELINE and summary["samples"] == summary["samples_selected"]
    assert isinstance(summary["samples"], int) and summary["samples"] > 0


def test_the_default_baseline_has_the_lowest_k1_fde_of_the_kinematic_baselines() -> None:
    """The figures the choice cites, on Argoverse 1 (all 69 sequences): Kalman CV 6.90 m, CV 7.57, linear 7.95."""
    argoverse = json.loads((RESULTS / "argoverse.json").read_text())["all"]
    fde = {n: argoverse[n]["k1"]["argo_fde"] for n in ("cv", "linear", "kalman")}
    assert min(fde, key=fde.__getitem__) == DEFAULT_BASELINE and BASELINES[DEFAULT_BASELINE] == "kalman_cv"


def test_a_driving_dataset_gets_the_driving_model_and_says_so(driving_rasterised: Path, tmp_path: Path) -> None:
    summary = _ok("predict", str(driving_rasterised), "--out", str(tmp_path / "pred"), "--no-mcap")
    assert summary["predictor"] == "residual"
    assert str(summary["predictor_reason"]).startswith("the driving model, shipped for dataset kind")
    named = _ok("predict", str(driving_rasterised), "--predictor", "cv", "--out", str(tmp_path / "cv"))
    assert named["predictor_reason"] == "--predictor cv"


def test_rerunning_a_finished_run_reports_its_totals_and_already_done(bag_dataset: Path) -> None:
    out = str(bag_dataset.parent / "twice")
    first = _ok("predict", str(bag_dataset), "--out", out)
    assert first["already_done"] is False and first["samples_total"] == first["samples"]
    again = _ok("predict", str(bag_dataset), "--out", out)
    assert again["already_done"] is True and again["samples"] == 0  # this invocation did nothing ...
    assert again["samples_total"] == first["samples"] and again["targets_total"] == first["targets"]  # ... the run
    human = runner.invoke(app, ["predict", str(bag_dataset), "--out", out])
    assert human.exit_code == 0
    heads = [line for line in human.stderr.splitlines() if line.startswith("predict: already done:")]
    assert len(heads) == 1 and heads[0].startswith(
        f"predict: already done: {first['samples']} samples, {first['targets']} agents")
