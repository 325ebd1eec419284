"""The residual driving model: target frames and inputs, the zero-initialised net equals the prior, training lowers
the error on real scenarios, checkpoints round-trip and refuse damage, out-of-distribution scores and actions."""

from __future__ import annotations

import dataclasses
import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch

from logpipe.dataset.reader import Dataset
from logpipe.errors import LogpipeError
from logpipe.maps import MapSource
from logpipe.model.checkpoint.format import CheckpointError
from logpipe.model.kinematic import best_baseline
from logpipe.model.kinematic.adaptive_prior import adaptive_fit
from logpipe.model.residual.checkpoint import load_residual, save_residual
from logpipe.model.residual.compare import compare, k1_source
from logpipe.model.residual.config import ResidualConfig, ResidualConfigError, load_residual_config
from logpipe.model.residual.fit import collect, evaluate, fit_residual, forecast
from logpipe.model.residual.inputs import CROP_CHANNELS, CROP_UNIT, target_inputs, world_truth
from logpipe.model.residual.meta import ResidualMeta
from logpipe.model.residual.net import ResidualNet
from logpipe.model.residual.ood import (
    MIN_EVIDENCE_TARGETS,
    NO_LOCATION,
    OodCheck,
    k1_evidence,
    ood_scores,
    training_distribution,
    tune_baselines,
)
from logpipe.model.residual.predictor import ResidualPredictor
from logpipe.raster.runs import find_raster_run
from logpipe.stages.ingest import IngestOptions, ingest
from logpipe.stages.rasterise import rasterise_dataset
from logpipe.stages.train import scene_samples
from logpipe.types import OBJECT_TYPES, SceneSample

DATA = Path(__file__).resolve().parents[1] / "data" / "commonroad"
SMALL = ResidualConfig(epochs=2, hidden=32, head_hidden=32, modes=3)


@pytest.fixture(scope="module")
def scenes(tmp_path_factory: pytest.TempPathFactory) -> list[SceneSample]:
    """The bundled CommonRoad scenarios ingested, rasterised from their own maps, cut into samples."""
    out = tmp_path_factory.mktemp("residual") / "ds"
    ingest([DATA], IngestOptions(out=out, write_mcap=False))
    rasterise_dataset(out, MapSource(), rotate=True)
    ds = Dataset.open(out)
    return scene_samples(ds, "all", rasters=find_raster_run(out, None, None))


def _straight(speed: float = 10.0) -> SceneSample:
    """A car driving north at ``speed`` m/s (10 Hz), a neighbour 20 m ahead of it, one 100 m away."""
    t = np.arange(50, dtype=np.float64) * 0.1
    car = np.stack([np.full(50, 5.0), 100.0 + speed * t], axis=1)
    positions = np.stack([car, car + np.array([0.0, 20.0]), car + np.array([100.0, 0.0])])
    return SceneSample("x:0", positions, (t * 1e9).astype(np.int64), ["a", "b", "c"], np.zeros(3, np.int64),
                       np.array([True, False, False]), -1, 20)


def test_a_target_is_read_in_its_own_frame() -> None:
    config = ResidualConfig(environment=False)
    inputs = target_inputs(_straight(), config, with_truth=True)
    np.testing.assert_allclose(inputs.origin[0], [5.0, 100.0 + 10.0 * 1.9])
    np.testing.assert_allclose(inputs.rotation[0] @ [0.0, 1.0], [1.0, 0.0], atol=1e-9)  # north is its forward
    assert inputs.scale[0] == pytest.approx(30.0) and inputs.speed[0] == pytest.approx(10.0)
    assert inputs.truth is not None and np.abs(inputs.truth).max() < 1e-9  # constant velocity: no residual
    assert inputs.neighbour_mask[0].tolist() == [True] + [False] * 15  # the far one is beyond 60 m
    np.testing.assert_allclose(inputs.neighbours[0, 0, 8:10] * 30.0, [20.0, 0.0], atol=1e-6)  # 20 m ahead, L = 30
    assert np.isfinite(inputs.features).all() and inputs.features.shape[1] == 4 * 20 + 3
    slow = target_inputs(_straight(0.5), config)
    assert slow.scale[0] == config.min_scale_m


def test_crops_show_the_lanes_running_the_targets_way(scenes: list[SceneSample]) -> None:
    config = ResidualConfig()
    forward = CROP_CHANNELS.index("lane_forward")
    ahead = []
    for sample in scenes:
        inputs = target_inputs(sample, config)
        assert inputs.crops is not None and inputs.crops.dtype == np.int8
        moving = inputs.speed > 2.0
        # the cells on the target's path: x 0..20 m ahead (columns 12..31), y within 2 m (rows 22..25)
        strip = inputs.crops[moving][:, forward, 22:26, 12:32].astype(np.float64) / CROP_UNIT
        ahead += strip.mean(axis=(1, 2)).tolist()
        assert inputs.has_map.all()
    # most moving cars have their own lane ahead (a few are between lanes or entering an intersection, where
    # crossing lanes dominate the strip); a mirrored or turned crop would make most of these negative
    assert len(ahead) > 10 and np.mean(np.asarray(ahead) > 0) > 0.75 and np.mean(ahead) > 0.05


def test_an_untrained_net_is_the_prior(scenes: list[SceneSample]) -> None:
    net = ResidualNet(SMALL).eval()
    inputs = target_inputs(scenes[0], SMALL)
    world = forecast(net, inputs, 4)
    observed = scenes[0].positions[np.asarray(scenes[0].target_mask, bool), :20]
    prior = adaptive_fit(observed).forecast(30)
    for mode in range(4):
        np.testing.assert_allclose(world[:, mode], prior, atol=1e-9)


def test_the_comparison_says_plainly_when_the_model_does_not_beat_the_baselines(scenes: list[SceneSample]) -> None:
    inputs, _ = collect(scenes, SMALL)
    # Untrained, the mean head is the adaptive prior (above): it cannot beat it, and the verdict must say so.
    result = compare(ResidualNet(SMALL).eval(), inputs, inputs, tune_baselines(inputs)["baselines"])
    assert result["targets"] == len(inputs) and result["k1"]["model"] == result["k1"]["model_prior"]
    # the prior with its constants chosen on these targets is at least as good as the model's fixed ones
    assert result["k1"]["adaptive_prior"]["fde"] <= result["k1"]["model_prior"]["fde"]
    assert not result["beats"]["adaptive_prior"] and "does NOT beat" in result["verdict"]
    assert "adaptive_prior (FDE" in result["verdict"]
    assert set(result["beats"]) == {"cv", "least_squares_cv", "kalman", "adaptive_prior", "cv_sampler"}
    assert k1_source(result)["source"] == "physics"  # predict keeps physics at K = 1 for such a model
    won = result | {"k1": result["k1"] | {"model": {"fde": 0.5 * result["k1"][result["best_kinematic"]]["fde"]}}}
    assert k1_source(won)["source"] == "model" and "beats the best kinematic" in k1_source(won)["reason"]
    assert result["min_fde_6"]["cv_sampler"] <= result["k1"]["cv"]["fde"]  # plain CV is one of the sampler's modes
    assert result["cv_sampler"]["chosen_on"] == "training targets" and result["best_kinematic"] in result["k1"]


def test_training_beats_the_prior_on_what_it_trained_on(scenes: list[SceneSample], tmp_path: Path) -> None:
    config = ResidualConfig(epochs=40, hidden=64, head_hidden=64, modes=3, lr=3e-3)
    inputs, windows = collect(scenes, config)
    before = evaluate(ResidualNet(config).eval(), inputs)
    half = len(inputs) // 2  # two made-up locations, to see the evidence recorded per location
    where = ["USA_Peach"] * half + ["USA_Lanker"] * (len(inputs) - half)
    result = fit_residual(inputs, windows, inputs, config, tmp_path / "run", dataset_kind="commonroad",
                          manifest_hash="h", val_locations=where)
    net, meta = load_residual(result.best_checkpoint)
    after = evaluate(net, inputs)
    evidence = meta.ood["k1_by_location"]
    assert set(evidence) == {"USA_Peach", "USA_Lanker"} and evidence["USA_Peach"]["targets"] == half
    physics = best_baseline.forecast(meta.ood["fallback_k1"], inputs.observed, 30)[:, -1]
    truth = world_truth(inputs)[:, -1]
    assert evidence["USA_Peach"]["baseline_fde"] == pytest.approx(
        np.linalg.norm(physics - truth, axis=-1)[:half].mean(), abs=1e-4)
    assert after["fde"] < 0.8 * before["fde"] and after["min_fde_4"] < after["fde"]
    assert meta.epoch == result.best_epoch and meta.metrics["val_fde"] == pytest.approx(after["fde"])
    lines = (tmp_path / "run" / "train_log.jsonl").read_text().splitlines()
    assert len(lines) == result.epochs and "val" in json.loads(lines[0])
    assert meta.ood["targets"] == len(inputs) and set(meta.ood["object_types"]) == {"vehicle"}


def test_k1_evidence_is_per_location_and_needs_enough_targets() -> None:
    model = np.r_[np.full(40, 1.0), np.full(40, 3.0), np.full(MIN_EVIDENCE_TARGETS - 1, 1.0)]
    physics = np.full(len(model), 2.0)
    where = ["A"] * 40 + ["B"] * 40 + ["C"] * (MIN_EVIDENCE_TARGETS - 1)
    evidence = k1_evidence(model, physics, where)
    assert {k: v["source"] for k, v in evidence.items()} == {"A": "model", "B": "physics", "C": "physics"}
    assert evidence["A"] == {"targets": 40, "model_fde": 1.0, "baseline_fde": 2.0, "source": "model"}
    assert list(k1_evidence(model[:3], physics[:3], [None] * 3)) == [NO_LOCATION]


def test_checkpoints_round_trip_and_refuse_damage(tmp_path: Path) -> None:
    net = ResidualNet(SMALL)
    meta = ResidualMeta(SMALL, "commonroad", "h", 1, {"val_fde": 1.0}, {"targets": 0})
    folder = save_residual(tmp_path / "ckpt", net, meta)
    loaded, read = load_residual(folder)
    assert read.config == SMALL and read.weights_sha256 == meta.weights_sha256
    for a, b in zip(net.state_dict().values(), loaded.state_dict().values(), strict=True):
        assert torch.equal(a, b)
    broken = tmp_path / "broken"
    shutil.copytree(folder, broken)
    data = bytearray((broken / "weights.safetensors").read_bytes())
    data[-1] ^= 1
    (broken / "weights.safetensors").write_bytes(bytes(data))
    with pytest.raises(CheckpointError, match="sha256"):
        load_residual(broken)
    absurd = json.loads((folder / "meta.json").read_text())
    absurd["residual"]["hidden"] = 200_000  # a 640 GB allocation if it were believed
    (broken / "meta.json").write_text(json.dumps(absurd))
    with pytest.raises(CheckpointError, match="4096"):
        load_residual(broken)
    edited = json.loads((folder / "meta.json").read_text())  # issue 56: all of meta.json is under its checksum
    edited["ood"] = {}
    (broken / "meta.json").write_text(json.dumps(edited))
    shutil.copy(folder / "weights.safetensors", broken / "weights.safetensors")
    with pytest.raises(CheckpointError, match="differs from its checksum"):
        load_residual(broken)


def test_config_files_refuse_typos(tmp_path: Path) -> None:
    good = tmp_path / "good.toml"
    good.write_text("[residual]\nmodes = 4\nenvironment = false\n")
    assert load_residual_config(good) == ResidualConfig(modes=4, environment=False)
    typo = tmp_path / "typo.toml"
    typo.write_text("[residual]\nmode = 4\n")
    with pytest.raises(ResidualConfigError, match="unknown residual settings"):
        load_residual_config(typo)


def test_out_of_distribution_targets_are_flagged_and_handled(scenes: list[SceneSample]) -> None:
    inputs, _ = collect(scenes, SMALL)
    ood = training_distribution(inputs) | tune_baselines(inputs)
    _, flags, _ = ood_scores(inputs, ood)
    assert flags.mean() < 0.02  # the training targets themselves are inside
    fast = _straight(40.0)  # faster than any car of the samples
    fast.object_types = np.array([OBJECT_TYPES.index("pedestrian")] * 3)
    _, f_flags, reasons = ood_scores(target_inputs(fast, SMALL), ood)
    assert f_flags.all() and "speed_mps" in reasons[0] and "pedestrian" in reasons[0]
    predictor = ResidualPredictor(ResidualNet(SMALL), ResidualMeta(SMALL, "x", "h", 1, {}, ood))
    forecasts, ranked = predictor.predict([fast, scenes[0]], 3, 0), predictor.predict_ranked([fast, scenes[0]])
    checked, rows = OodCheck(ood, SMALL, "fallback", 3)([fast, scenes[0]], ranked)
    assert ood["fallback_k1"]["method"] in ("cv", "least_squares_cv", "kalman", "adaptive_prior")
    physics = best_baseline.forecast(ood["fallback_k1"], fast.positions[np.asarray(fast.target_mask, bool), :20], 30)
    assert rows[0][2].all() and not rows[1][2].any()
    np.testing.assert_allclose(checked[0][:, 0], physics)  # K = 1: the best kinematic baseline of training
    assert checked[0].shape[1] == 3  # fallback keeps the K modes: two of the model's mode heads follow
    heads = ranked[0][:, 1:]
    for mode in range(1, 3):
        assert np.all(np.any(np.all(checked[0][:, mode, None] == heads, axis=(2, 3)), axis=1))
    np.testing.assert_array_equal(checked[1], forecasts[1])  # inside: the network's forecast, untouched
    warned, rows = OodCheck(ood, SMALL, "warn", 3)([fast], ranked[:1])
    assert rows[0][1].all() and not rows[0][2].any()
    np.testing.assert_array_equal(warned[0], forecasts[0])
    auto, rows = OodCheck(ood, SMALL, "auto", 3)([fast], ranked[:1])  # flagged, but on no unknown road: marked only
    assert rows[0][1].all() and not rows[0][2].any()
    np.testing.assert_array_equal(auto[0], forecasts[0])
    with pytest.raises(LogpipeError, match="outside the checkpoint's training data"):
        OodCheck(ood, SMALL, "refuse", 3)([fast], ranked[:1])


def test_roads_the_model_never_trained_on_get_physics_at_k1(scenes: list[SceneSample]) -> None:
    inputs, _ = collect(scenes, SMALL)
    ood = training_distribution(inputs, {"USA_Peach": len(scenes)}) | tune_baselines(inputs)
    predictor = ResidualPredictor(ResidualNet(SMALL), ResidualMeta(SMALL, "x", "h", 1, {}, ood))
    forecasts, ranked = predictor.predict(scenes[:2], 4, 0), predictor.predict_ranked(scenes[:2])
    log_a, log_b = scenes[0].log_id, scenes[1].log_id
    check = OodCheck(ood, SMALL, "auto", 4, locations={log_a: "USA_Peach", log_b: "DEU_Unseen"})
    checked, rows = check(scenes[:2], ranked)
    np.testing.assert_array_equal(checked[0], forecasts[0])  # a road it trained on: the model, untouched
    assert not rows[0][2].any() and rows[1][2].all() and rows[1][1].all()
    observed = scenes[1].positions[np.asarray(scenes[1].target_mask, bool), :20]
    np.testing.assert_allclose(checked[1][:, 0], best_baseline.forecast(ood["fallback_k1"], observed, 30))
    _, _, reasons = ood_scores(target_inputs(scenes[1], SMALL), ood, location="DEU_Unseen")
    assert "not trained on this road (DEU_Unseen; trained on USA_Peach)" in reasons[0]
    # a road it trained on but whose validation never showed its K = 1 beating physics: physics at K = 1 too
    evidenced = ood | {"k1_by_location": {"USA_Peach": {"source": "model"}, "USA_Lanker": {"source": "physics"}}}
    both = {"USA_Peach": 5, "USA_Lanker": 5}
    check = OodCheck(evidenced | {"locations": both}, SMALL, "auto", 4,
                     locations={log_a: "USA_Peach", log_b: "USA_Lanker"})
    checked, rows = check(scenes[:2], ranked)
    np.testing.assert_array_equal(checked[0], forecasts[0])
    assert rows[1][2].all() and not rows[1][1].any()  # replaced, though not flagged: the road is a training one
    np.testing.assert_allclose(checked[1][:, 0], best_baseline.forecast(ood["fallback_k1"], observed, 30))
    checked, _ = OodCheck(evidenced | {"locations": both}, SMALL, "warn", 4,
                          locations={log_a: "USA_Peach", log_b: "USA_Lanker"})(scenes[:2], ranked)
    np.testing.assert_array_equal(checked[1], forecasts[1])  # warn only marks
    no_record = training_distribution(inputs) | tune_baselines(inputs)  # older checkpoints: no road judged
    _, flags, _ = ood_scores(target_inputs(scenes[1], SMALL), no_record, location="DEU_Unseen")
    assert flags.mean() < 0.5


def test_unlabelled_types_and_resampled_input_are_flagged(scenes: list[SceneSample]) -> None:
    inputs, _ = collect(scenes, SMALL)
    ood = training_distribution(inputs)
    assert ood["rates_hz"] == [10.0]
    _, flags, _ = ood_scores(inputs, ood, np.full(len(inputs), np.nan))
    assert flags.mean() < 0.02  # recorded at the training rate, not resampled: inside
    _, flags, reasons = ood_scores(inputs, ood, np.full(len(inputs), 5.0))  # read as 10 Hz, recorded at 5
    assert flags.all() and "recorded at 5 Hz and resampled to 10 Hz" in reasons[0]
    _, flags, _ = ood_scores(inputs, ood, np.full(len(inputs), 10.0))  # resampled from a training rate: inside
    assert flags.mean() < 0.02
    unknown = dataclasses.replace(inputs, object_type=np.full(len(inputs), OBJECT_TYPES.index("unknown")))
    ood_unknown = training_distribution(unknown)
    assert "unknown" in ood_unknown["object_types"]  # trained on it, still no evidence of what it is
    _, flags, reasons = ood_scores(unknown, ood_unknown)
    assert flags.all() and "its format does not label it" in reasons[0]


def test_a_target_off_the_map_is_flagged_only_where_training_never_had_one(scenes: list[SceneSample]) -> None:
    sample = scenes[0]
    # one definition of "a map under the target", with crops (training) or without (the OOD check)
    with_crops = target_inputs(sample, dataclasses.replace(SMALL, environment=True))
    without = target_inputs(sample, dataclasses.replace(SMALL, environment=False))
    np.testing.assert_array_equal(with_crops.has_map, without.has_map)
    assert with_crops.has_map.all()
    off_map = target_inputs(dataclasses.replace(sample, raster=None), SMALL)
    assert not off_map.has_map.any()
    ood = training_distribution(with_crops)
    assert ood["map_share"] == 1.0
    assert ood_scores(off_map, ood)[1].all()  # never trained without a map: flagged
    assert "no map under the target" in ood_scores(off_map, ood)[2][0]
    assert not ood_scores(off_map, ood | {"map_share": 0.9})[1].any()  # 10 % of training had none: inside
