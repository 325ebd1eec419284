"""``logpipe train`` on driving data without ``--config``: the shipped driving model's recipe, validated on data it
picks itself (``logpipe.dataset.holdout``) and compared with the kinematic baselines on exactly that data.

Real NGSIM recordings from ``../shared/data/commonroad`` (CommonRoad scenario XML): US-101 scenarios that share
tracks (whole recordings held out, shared ones on one side) and one Peachtree scenario long enough to be cut in
time (its later part validates)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pyarrow.compute as pc
import pyarrow.parquet as pq
import pytest
from typer.testing import CliRunner

from logpipe import api
from logpipe.cli import app
from logpipe.dataset.holdout import VAL_SHARE, choose_holdout, log_groups
from logpipe.dataset.reader import Dataset
from logpipe.model.residual.meta import read_residual_meta

pytestmark = pytest.mark.shared
runner = CliRunner()
LONG = "USA_Peach-4_2_T-1.xml"  # nine windows: the only scenario here long enough to cut in time
US101 = [f"USA_US101-{n}_1_T-1.xml" for n in range(10, 20)]  # ten scenarios, several of them sharing tracks


@pytest.fixture(scope="module")
def us101(shared: Path, tmp_path_factory: pytest.TempPathFactory) -> Dataset:
    out = tmp_path_factory.mktemp("us101") / "ds"
    api.ingest([shared / "commonroad" / "ngsim" / "USA_US101" / name for name in US101], out=out, mcap=False)
    return Dataset.open(out)


def test_recordings_that_share_tracks_stay_on_one_side(us101: Dataset) -> None:
    logs, samples = us101.logs(), us101.samples()
    pairs = [(later, earlier) for later, text in zip(logs.column("log_id").to_pylist(),
                                                     logs.column("attributes").to_pylist(), strict=True)
             for earlier in json.loads(text or "{}").get("shared_tracks", {})]
    assert pairs, "the US-101 sample must have scenarios that share tracks for this test to mean anything"
    holdout = choose_holdout([logs], [samples])
    assert holdout.how == "recordings" and holdout.groups == len(log_groups([logs])) < len(US101)
    val = set(holdout.val_logs[0])
    assert all((a in val) == (b in val) for a, b in pairs)
    val_windows = {s for s, log in zip(samples.column("sample_id").to_pylist(), samples.column("log_id").to_pylist(),
                                       strict=True) if log in val}
    assert set(holdout.val_ids[0]) == val_windows and not val_windows & set(holdout.train_ids[0])
    assert 0 < len(val_windows) <= 1.5 * VAL_SHARE * samples.num_rows + 1


@pytest.fixture(scope="module")
def fleet_run(shared: Path, tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, dict]:
    work = tmp_path_factory.mktemp("fleet")
    api.ingest(shared / "commonroad" / "ngsim" / "USA_Peach" / LONG, out=work / "ds", mcap=False)
    api.rasterise(work / "ds", rotate=True)
    result = runner.invoke(app, ["train", str(work / "ds"), "--out", str(work / "run"), "--json"])
    assert result.exit_code == 0, result.output
    return work, json.loads(result.stdout)


@pytest.mark.slow
def test_no_config_trains_the_driving_recipe_and_compares_on_held_out_windows(fleet_run: tuple[Path, dict]) -> None:
    work, summary = fleet_run
    samples = Dataset.open(work / "ds").samples()
    validation = summary["validation"]
    assert validation["how"] == "later_part"  # one recording: its later part validates
    ((log,),) = validation["val_logs"]  # one dataset, one log
    rows = samples.filter(pc.equal(samples.column("log_id"), log))
    start, end = rows.column("start_step").to_numpy(), rows.column("end_step").to_numpy()
    cut = validation["cut_steps"][log]
    val_rows, train_rows = start >= cut, end < cut
    # Disjoint in time: every training window ends before the first validation window starts.
    assert val_rows.any() and train_rows.any() and end[train_rows].max() < start[val_rows].min()
    assert summary["val_samples"] == int(val_rows.sum()) and summary["train_samples"] == int(train_rows.sum())
    targets = rows.column("target_track_ids").to_pylist()
    val_targets = sum(len(t) for t, v in zip(targets, val_rows, strict=True) if v)
    comparison = summary["comparison"]
    assert comparison["targets"] == summary["val_targets"] == val_targets  # computed on the validation targets only
    for name in ("cv", "kalman", "adaptive_prior", "model"):
        assert np.isfinite(comparison["k1"][name]["fde"]) and comparison["k1"][name]["fde"] > 0
    assert comparison["min_fde_6"]["model"] <= comparison["k1"]["model"]["fde"]  # mode 0 is among the six
    assert comparison["min_fde_6"]["cv_sampler"] <= comparison["k1"]["cv"]["fde"] + 1e-9  # CV is one of its modes
    assert comparison["cv_sampler"]["includes_cv"] and comparison["best_kinematic"] in ("cv", "kalman",
                                                                                         "adaptive_prior")
    beaten = all(comparison["beats"].values())
    assert ("does NOT beat" not in comparison["verdict"]) == beaten
    assert set(summary["start"]["validation_scores"]) == {"scratch", "finetune"}  # the shipped model's inputs fit
    assert summary["start"]["chosen"] in ("scratch", "finetune")
    card = Path(summary["model_card"]).read_text()
    assert comparison["verdict"] in card and "kinematic baselines" in card
    assert read_residual_meta(work / "run" / "best").config == read_residual_meta(
        work / "run" / "candidates" / summary["start"]["chosen"] / "best").config


@pytest.mark.slow
def test_predict_uses_the_trained_run(fleet_run: tuple[Path, dict], tmp_path: Path) -> None:
    work, summary = fleet_run
    run = api.predict(work / "ds", out=tmp_path / "pred", checkpoint=Path(summary["best_checkpoint"]), mcap=False)
    table = pq.read_table(tmp_path / "pred" / "predictions")
    assert table.num_rows > 0 and "ood_flag" in table.column_names  # the residual model scored each target
    assert run["checkpoint"] == str(work / "run" / "best")


def test_ros_vehicles_get_the_recipe_and_a_too_short_recording_trains_with_physics_at_k1(tmp_path: Path) -> None:
    bag = Path(__file__).resolve().parents[1] / "data" / "rosbags" / "datmo" / "intersection.bag"
    api.ingest(bag, out=tmp_path / "ros", mcap=False)
    assert Dataset.open(tmp_path / "ros").kind == "rosbag"
    short = runner.invoke(app, ["train", str(tmp_path / "ros"), "--out", str(tmp_path / "run"), "--json"])
    assert short.exit_code == 0, short.output
    summary = json.loads(short.stdout)
    assert summary["validation"]["how"] == "none" and summary["val_targets"] == 0
    assert "too short to hold out a later part" in summary["validation"]["description"]
    assert summary["k1"]["source"] == "physics" and "no validation data" in summary["comparison"]["verdict"]
    ood = read_residual_meta(tmp_path / "run" / "best").ood
    assert ood["k1_source"] == "physics" and "K = 1 in `logpipe predict`" in (tmp_path / "run" / "MODEL_CARD.md"
                                                                            ).read_text()
    pred = api.predict(tmp_path / "ros", out=tmp_path / "pred", checkpoint=tmp_path / "run" / "best", mcap=False)
    assert pred["targets"] > 0 and pred["targets_fallback"] == pred["targets"]  # physics at K = 1 everywhere
    paper = runner.invoke(app, ["train", str(tmp_path / "ros"), "--out", str(tmp_path / "run2"), "--steps", "3"])
    assert paper.exit_code == 2 and "--steps: only for the paper's network" in paper.output
    unvalidated = runner.invoke(app, ["train", str(tmp_path / "ros"), "--out", str(tmp_path / "run2"),
                                      "--train-split", "all"])
    assert unvalidated.exit_code == 2 and "give --val-split too" in unvalidated.output
