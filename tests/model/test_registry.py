"""``model.registry`` and the checkpoint's stored inference settings: shipped defaults, the settings in effect
(checkpoint, options, as trained), ``amend_meta``, and the training-data warning."""

from __future__ import annotations

import json
from pathlib import Path

import pyarrow as pa
import pytest

from logpipe.errors import LogpipeError
from logpipe.model.checkpoint.format import CheckpointError, InferenceSettings, TrainingData
from logpipe.model.registry import (
    COMPARISON_FOLDERS,
    ChosenPredictor,
    default_checkpoint,
    resolve_inference,
    seen_in_training,
    shipped_checkpoints,
)
from logpipe.model.zhu2020.checkpoint import load_checkpoint, save_checkpoint
from logpipe.model.zhu2020.config import Features, ModelConfig, TrainConfig
from logpipe.model.zhu2020.meta import amend_meta, read_meta
from logpipe.model.zhu2020.network import TrajectoryNet

STORED = InferenceSettings(num_modes=20, noise_scale=0.75, constant_velocity_modes=1, context_max_neighbours=13,
                           chosen_on="eth/val")


def test_shipped_defaults_are_the_papers_method_never_a_baseline() -> None:
    eth = shipped_checkpoints("ethucy")
    assert sorted(p.name for p in eth) == ["eth", "hotel", "univ", "zara1", "zara2"]
    # the baselines and the ablation are shipped beside, just not candidates
    assert all((eth[0] / name / "meta.json").is_file() for name in ("lstm", "noise_lstm", "no_position"))
    assert default_checkpoint("ethucy", "hotel/test").name == "hotel"
    apollo = default_checkpoint("apolloscape", None)
    assert apollo.name == "zhu2020" and not COMPARISON_FOLDERS & set(apollo.parts)


def test_shipped_checkpoints_carry_the_settings_their_results_used() -> None:
    """Each shipped network with K > 1 stores what docs/results chose on validation, and the data it saw."""
    results = json.loads((Path(__file__).parents[2] / "docs" / "results" / "ethucy.json").read_text())
    for folder in shipped_checkpoints("ethucy"):
        meta = read_meta(folder)
        chosen = results["scenes"][folder.name]["val"]["zhu2020"]
        assert meta.inference is not None and meta.inference.num_modes == 20
        assert (meta.inference.noise_scale, meta.inference.constant_velocity_modes,
                meta.inference.context_max_neighbours) == (chosen["noise_scale"], chosen["constant_velocity_modes"],
                                                           chosen["context_max_neighbours"])
        assert meta.inference.chosen_on.startswith(f"{folder.name}/val")
        assert meta.training_data is not None and meta.training_data.train_split == f"{folder.name}/train"
        assert len(meta.training_data.train_sources) >= 6 and meta.training_data.val_sources


def _chosen(stored: InferenceSettings | None = STORED) -> ChosenPredictor:
    return ChosenPredictor(None, "zhu2020", "abc", checkpoint=Path("ckpt"), weights_sha256="abc",
                           stored_settings=stored)


def test_stored_settings_are_the_defaults_and_options_replace_them_one_by_one() -> None:
    chosen = _chosen()
    got = resolve_inference(chosen, num_modes=20)
    assert (got.noise_scale, got.constant_velocity_modes, got.context_max_neighbours) == (0.75, 1, 13)
    assert got.source == "checkpoint" and got.chosen_on == "eth/val"
    assert chosen.checkpoint_id == "abc noise_scale=0.75 constant_velocity_modes=1 context_max_neighbours=13"

    chosen = _chosen()
    got = resolve_inference(chosen, num_modes=20, noise_scale=2.0)
    assert (got.noise_scale, got.constant_velocity_modes, got.context_max_neighbours) == (2.0, 1, 13)
    assert got.source == "checkpoint + options"

    chosen = _chosen()
    got = resolve_inference(chosen, num_modes=20, as_trained=True)
    assert (got.noise_scale, got.constant_velocity_modes, got.context_max_neighbours, got.source) == (
        1.0, None, None, "as trained")
    assert chosen.checkpoint_id == "abc"
    assert resolve_inference(_chosen(None), num_modes=6).source == "as trained"


def test_bad_settings_name_their_origin() -> None:
    with pytest.raises(LogpipeError, match=r"0\.\.6 \(--modes\), got 7 from the checkpoint"):
        resolve_inference(_chosen(InferenceSettings(num_modes=20, constant_velocity_modes=7)), num_modes=6)
    with pytest.raises(LogpipeError, match=r"got 8 from --constant-velocity-modes"):
        resolve_inference(_chosen(), num_modes=6, constant_velocity_modes=8)
    with pytest.raises(LogpipeError, match="--noise-scale must be > 0"):
        resolve_inference(_chosen(), num_modes=20, noise_scale=0.0)
    baseline = ChosenPredictor(None, "cv", "cv:{}")
    with pytest.raises(LogpipeError, match="not to a --predictor baseline"):
        resolve_inference(baseline, num_modes=6, as_trained=True)


def test_predicting_over_training_or_validation_recordings_warns() -> None:
    chosen = _chosen()
    chosen.training_data = TrainingData("a/train", "a/val", ("sha-t1", "sha-t2"), ("sha-v",))
    logs = pa.table({"log_id": ["t1", "v", "new", "copy_of_t2"], "source_sha256": ["sha-t1", "sha-v", "x", "sha-t2"]})
    warnings = seen_in_training(chosen, logs)
    assert len(warnings) == 2
    assert warnings[0].startswith("2 of the 4 selected logs") and "trained on (split a/train): t1, copy_of_t2" in (
        warnings[0])
    assert warnings[1].startswith("1 of the 4") and "validated on (split a/val): v" in warnings[1]
    assert seen_in_training(chosen, logs.slice(2, 1)) == []
    assert seen_in_training(_chosen(), logs) == []  # nothing recorded: nothing claimed


def _tiny_checkpoint(folder: Path) -> Path:
    cfg = ModelConfig(embed_dim=8, gru_dim=8, lstm_dim=8, noise_dim=2, features=Features(True, True, False, False,
                                                                                         False))
    data = TrainingData("s/train", None, ("aa",), ())
    return save_checkpoint(folder, TrajectoryNet(cfg), TrainConfig(model=cfg), dataset_kind="ethucy",
                           manifest_hash="m", step=3, training_data=data)


def test_amend_meta_changes_only_the_settings(tmp_path: Path) -> None:
    folder = _tiny_checkpoint(tmp_path / "ck")
    before = read_meta(folder)
    assert before.training_data == TrainingData("s/train", None, ("aa",), ()) and before.inference is None
    weights = (folder / "weights.safetensors").read_bytes()
    after = amend_meta(folder, inference=STORED)
    assert read_meta(folder) == after and after.inference == STORED
    assert after.weights_sha256 == before.weights_sha256 and (folder / "weights.safetensors").read_bytes() == weights
    load_checkpoint(folder)  # still verifies and loads
    assert amend_meta(folder, inference=None).inference is None
    assert sorted(p.name for p in folder.iterdir()) == ["meta.json", "weights.safetensors"]
    with pytest.raises(CheckpointError, match=r"only .* may be amended"):
        amend_meta(folder, step=4)  # type: ignore[arg-type]


def test_malformed_settings_name_the_file(tmp_path: Path) -> None:
    folder = _tiny_checkpoint(tmp_path / "ck")
    raw = json.loads((folder / "meta.json").read_text())
    raw["inference"] = {"num_modes": 6, "constant_velocity_modes": 9}
    (folder / "meta.json").write_text(json.dumps(raw))
    with pytest.raises(CheckpointError, match=r"meta\.json: 'inference' values out of range"):
        read_meta(folder)
    raw["inference"] = {"noise_scale": 1.0}
    (folder / "meta.json").write_text(json.dumps(raw))
    with pytest.raises(CheckpointError, match=r"meta\.json: malformed 'inference' block"):
        read_meta(folder)
