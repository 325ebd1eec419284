"""``logpipe train`` with a residual config and ``logpipe predict`` with its checkpoint: the out-of-distribution
columns and the Kalman fallback on a scenario three times as fast as the one it trained on."""

from __future__ import annotations

import json
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest

from logpipe import api
from logpipe.dataset.reader import Dataset
from logpipe.errors import LogpipeError
from logpipe.model.kinematic import best_baseline
from logpipe.model.residual.meta import read_residual_meta
from logpipe.model.residual.ood import MIN_EVIDENCE_TARGETS

DATA = Path(__file__).resolve().parents[1] / "data" / "commonroad"
SCENARIO = DATA / "USA_Peach-4_8_T-1.xml"
FAST = "USA_Peach-9_9_T-1"
SLOW = "USA_Peach-9_8_T-1"
ELSEWHERE = "DEU_Elsewhere-1_1_T-1"


def _faster_copy(target: Path, factor: float = 3.0) -> None:
    """The scenario with every position (cars and lanes) scaled by ``factor`` about the origin, speeds with them:
    the same traffic three times as fast on a three times larger road."""
    tree = ET.parse(SCENARIO)
    root = tree.getroot()
    root.set("benchmarkID", FAST)
    for point in root.iter("point"):
        for axis in ("x", "y"):
            el = point.find(axis)
            assert el is not None and el.text is not None
            el.text = repr(float(el.text) * factor)
    for velocity in root.iter("velocity"):
        exact = velocity.find("exact")
        if exact is not None and exact.text is not None:
            exact.text = repr(float(exact.text) * factor)
    tree.write(target)


def _five_hz_copy(target: Path) -> None:
    """The scenario's states as if recorded every 0.2 s: ingest resamples it to 10 Hz (``resampled_from_hz`` 5)."""
    tree = ET.parse(SCENARIO)
    root = tree.getroot()
    root.set("benchmarkID", SLOW)
    root.set("timeStepSize", "0.2")
    tree.write(target)


def _renamed_copy(target: Path, benchmark_id: str) -> None:
    """The scenario under another benchmark id: the same traffic, recorded (by its id) at another location."""
    tree = ET.parse(SCENARIO)
    tree.getroot().set("benchmarkID", benchmark_id)
    tree.write(target)


@pytest.fixture(scope="module")
def trained(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    work = tmp_path_factory.mktemp("residual_predict")
    inputs = work / "in"
    inputs.mkdir()
    (inputs / SCENARIO.name).write_bytes(SCENARIO.read_bytes())
    _faster_copy(inputs / "fast.xml")
    _five_hz_copy(inputs / "slow.xml")
    _renamed_copy(inputs / "elsewhere.xml", ELSEWHERE)
    api.ingest(inputs, out=work / "ds", mcap=False)
    api.rasterise(work / "ds", rotate=True)
    config = work / "residual.toml"
    config.write_text("[residual]\nepochs = 3\nhidden = 32\nhead_hidden = 32\nmodes = 3\n")
    summary = api.train(work / "ds", train_split="USA_Peach-4_8_T-1", val_split="USA_Peach-4_8_T-1",
                        config=config, out=work / "run")
    assert summary["steps"] > 0 and summary["environment_net"] and summary["best_val_min_fde"] > 0
    return work / "ds", work / "run" / "best"


def test_fast_targets_get_the_physics_fallback_and_say_so(trained: tuple[Path, Path], tmp_path: Path) -> None:
    dataset, checkpoint = trained
    summary = api.predict(dataset, out=tmp_path / "pred", checkpoint=checkpoint, filters=[f"log={FAST}"],
                          mcap=False, modes=4, out_of_distribution="fallback")
    table = pq.read_table(tmp_path / "pred" / "predictions").to_pandas()
    assert {"ood_score", "ood_flag", "fallback"} <= set(table.columns)
    per_target = table.groupby(["sample_id", "track_id"]).agg(flag=("ood_flag", "first"), fell=("fallback", "first"))
    flagged = int(per_target.flag.sum())
    assert flagged > 0 and summary["targets_out_of_distribution"] == flagged == summary["targets_fallback"]
    assert any("outside the checkpoint's training data" in w for w in summary["warnings"])
    ood = read_residual_meta(checkpoint).ood
    assert set(ood["fallback_kalman"]) == {"accel_std", "meas_std"}
    assert ood["fallback_k1"] == best_baseline.choose(ood["baselines"]) and set(ood["locations"]) == {"USA_Peach"}
    api.predict(dataset, out=tmp_path / "warned", checkpoint=checkpoint, filters=[f"log={FAST}"], mcap=False,
                modes=4, out_of_distribution="warn")
    model = pq.read_table(tmp_path / "warned" / "predictions").to_pandas().set_index(["sample_id", "track_id", "mode"])
    fell = table[table.fallback]
    for (sample, track), rows in fell.groupby(["sample_id", "track_id"]):
        ordered = rows.sort_values("mode")
        assert ordered["mode"].tolist() == [0, 1, 2, 3]  # the K modes kept, never one
        for mode in (1, 2, 3):  # after physics, its mode heads by score (its mean head, mode 0, gives way)
            theirs = model.loc[(sample, track, mode)]
            np.testing.assert_array_equal(ordered.x.iloc[mode], theirs.x)
        assert not np.array_equal(ordered.x.iloc[0], model.loc[(sample, track, 0)].x)  # mode 0: physics
    settings = json.loads((tmp_path / "pred" / "manifest.json").read_text())["settings"]
    assert settings["out_of_distribution"] == "fallback"
    with pytest.raises(LogpipeError, match="outside the checkpoint's training data"):
        api.predict(dataset, out=tmp_path / "refused", checkpoint=checkpoint, filters=[f"log={FAST}"], mcap=False,
                    out_of_distribution="refuse")
    inside = api.predict(dataset, out=tmp_path / "inside", checkpoint=checkpoint,
                         filters=["log=USA_Peach-4_8_T-1"], mcap=False, out_of_distribution="refuse")
    assert inside["targets_out_of_distribution"] == 0 and inside["targets"] > 0


def test_input_resampled_from_a_rate_training_never_had_is_flagged(trained: tuple[Path, Path], tmp_path: Path) -> None:
    dataset, checkpoint = trained
    logs = Dataset.open(dataset).logs().to_pylist()
    assert [json.loads(r["attributes"])["resampled_from_hz"] for r in logs if r["log_id"] == SLOW] == [5.0]
    summary = api.predict(dataset, out=tmp_path / "pred", checkpoint=checkpoint, filters=[f"log={SLOW}"],
                          mcap=False, modes=4)
    table = pq.read_table(tmp_path / "pred" / "predictions").to_pandas()
    per_target = table.groupby(["sample_id", "track_id"]).ood_flag.first()
    # Its windows read as 10 Hz, the training rate: only the recorded rate tells them apart.
    assert summary["targets"] > 0 and per_target.all() and summary["targets_out_of_distribution"] == len(per_target)
    same_rate = api.predict(dataset, out=tmp_path / "own", checkpoint=checkpoint,
                            filters=["log=USA_Peach-4_8_T-1"], mcap=False)
    assert same_rate["targets_out_of_distribution"] == 0


def test_a_road_the_model_never_trained_on_gets_physics_at_k1_by_default(trained: tuple[Path, Path],
                                                                        tmp_path: Path) -> None:
    dataset, checkpoint = trained
    ood = read_residual_meta(checkpoint).ood
    assert "DEU_Elsewhere" not in ood["locations"]
    summary = api.predict(dataset, out=tmp_path / "auto", checkpoint=checkpoint, filters=[f"log={ELSEWHERE}"],
                          mcap=False, modes=4)  # the default: --out-of-distribution auto
    api.predict(dataset, out=tmp_path / "warn", checkpoint=checkpoint, filters=[f"log={ELSEWHERE}"], mcap=False,
                modes=4, out_of_distribution="warn")
    auto = pq.read_table(tmp_path / "auto" / "predictions").to_pandas().sort_values(["sample_id", "track_id", "mode"])
    warn = pq.read_table(tmp_path / "warn" / "predictions").to_pandas().sort_values(["sample_id", "track_id", "mode"])
    assert summary["targets"] > 0 and summary["targets_fallback"] == summary["targets"] and auto.fallback.all()
    assert any("best kinematic baseline" in w for w in summary["warnings"])
    # the same traffic as the training log, so only the road's name tells them apart
    own = api.predict(dataset, out=tmp_path / "own", checkpoint=checkpoint, filters=["log=USA_Peach-4_8_T-1"],
                      mcap=False, modes=4, out_of_distribution="warn")
    assert own["targets_fallback"] == 0
    # its own road, but three epochs on ten validation targets showed no K = 1 win: physics there too by default
    evidence = ood["k1_by_location"]["USA_Peach"]
    assert evidence["source"] == "physics" and evidence["targets"] < MIN_EVIDENCE_TARGETS
    by_default = api.predict(dataset, out=tmp_path / "own_auto", checkpoint=checkpoint,
                             filters=["log=USA_Peach-4_8_T-1"], mcap=False, modes=4)
    assert by_default["targets_fallback"] == by_default["targets"] > 0
    same = pq.read_table(tmp_path / "own" / "predictions").to_pandas().sort_values(["sample_id", "track_id", "mode"])
    for (sample, track), rows in auto.groupby(["sample_id", "track_id"]):
        theirs = warn[(warn.sample_id == sample) & (warn.track_id == track)]
        for mode in (1, 2, 3):  # after physics, its mode heads by score
            np.testing.assert_array_equal(rows.x.iloc[mode], theirs.x.iloc[mode])
        assert not np.array_equal(rows.x.iloc[0], theirs.x.iloc[0])  # mode 0: physics (checked exactly in
        # tests/model/test_residual.py), not the mean head
    assert len(same) == len(auto)  # the same traffic, the same number of forecasts
