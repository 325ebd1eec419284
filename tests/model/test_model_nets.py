"""Whole-network properties: shapes, padding/batch invariance, ablation switches, ego plan."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from logpipe.model.synthetic import make_scene
from logpipe.model.zhu2020.batching import collate
from logpipe.model.zhu2020.config import Features, ModelConfig, preset
from logpipe.model.zhu2020.network import TrajectoryNet
from logpipe.model.zhu2020.predictor import NetPredictor
from logpipe.types import SceneSample

SMALL = {"embed_dim": 8, "gru_dim": 12, "lstm_dim": 8, "obs_len": 4, "pred_len": 3, "raster_channels": 2}


def _scene(seed: int, n: int, **kw: object) -> SceneSample:
    return make_scene(np.random.default_rng(seed), n, 4, 3, channels=2, size=64, **kw)  # type: ignore[arg-type]


def _net(features: Features | None = None, noise_dim: int = 0, frame: str = "world") -> TrajectoryNet:
    torch.manual_seed(0)
    features = Features() if features is None else features
    cfg = ModelConfig(features=features, noise_dim=noise_dim, frame=frame, **SMALL)  # type: ignore[arg-type]
    return TrajectoryNet(cfg).eval()


def _predict(net: TrajectoryNet, scenes: list[SceneSample], modes: int = 1) -> list[np.ndarray]:
    return NetPredictor(net).predict(scenes, modes, seed=0)


def test_output_shapes_per_sample() -> None:
    net = _net(noise_dim=3)
    scenes = [_scene(0, 5, with_ego=True, with_raster=True), _scene(1, 2), _scene(2, 7, with_ego=True)]
    out = _predict(net, scenes, modes=4)
    assert [o.shape for o in out] == [(4, 4, 3, 2), (2, 4, 3, 2), (6, 4, 3, 2)]
    assert all(np.isfinite(o).all() for o in out)
    # noise makes the modes differ
    assert np.abs(out[1][:, 0] - out[1][:, 1]).max() > 1e-6


def test_padding_and_batch_mates_never_change_outputs() -> None:
    net = _net()
    small = _scene(0, 3, with_ego=True, with_raster=True)
    alone = _predict(net, [small])[0]
    # batched with a bigger scene (more padding for the small one) and a map-less scene
    together = _predict(net, [_scene(5, 9, with_ego=True, with_raster=True), small, _scene(6, 4)])[1]
    np.testing.assert_allclose(together, alone, rtol=1e-5, atol=1e-5)
    # extra agents that are never observed are padding too
    padded = _scene(0, 3, with_ego=True, with_raster=True)
    ghosts = np.full((4, padded.positions.shape[1], 2), np.nan)
    padded.positions = np.concatenate((padded.positions, ghosts))
    padded.target_mask = np.concatenate((padded.target_mask, np.zeros(4, bool)))
    padded.track_ids = [*padded.track_ids, "g1", "g2", "g3", "g4"]
    padded.object_types = np.concatenate((padded.object_types, np.zeros(4, np.int64)))
    np.testing.assert_allclose(_predict(net, [padded])[0], alone, rtol=1e-5, atol=1e-5)


def test_world_predictions_do_not_depend_on_world_offset() -> None:
    net = _net(Features(True, True, False, False, False))
    s = _scene(3, 4)
    moved = _scene(3, 4)
    moved.positions = moved.positions + np.array([1000.0, -250.0])
    np.testing.assert_allclose(_predict(net, [moved])[0], _predict(net, [s])[0] + [1000.0, -250.0], atol=1e-3)


def _count(net: TrajectoryNet) -> int:
    return sum(p.numel() for p in net.parameters())


def test_ablation_presets_remove_parameters() -> None:
    counts = [_count(TrajectoryNet(preset(name, **SMALL))) for name in ("baseline", "v1", "v2", "v3", "v4", "full")]
    assert counts == sorted(counts) and len(set(counts)) == len(counts)
    assert _count(TrajectoryNet(preset("lstm", **SMALL))) < counts[0]  # no noise input to eq. 22
    full = TrajectoryNet(preset("full", **SMALL))
    assert full.env is not None and full.ain.gru is not None
    base = TrajectoryNet(preset("baseline", **SMALL))
    assert base.env is None and base.ain.gru is None and base.attention is None


def _moved_other_agent(s: SceneSample) -> SceneSample:
    out = _scene(0, 1)
    out.__dict__.update(s.__dict__)
    out.positions = s.positions.copy()
    out.positions[-1] += 3.0
    return out


def test_interaction_features_really_switch_off() -> None:
    s = _scene(4, 4)
    moved = _moved_other_agent(s)
    for feats, interacts in [
        (Features(False, False, False, False, False), False),
        (Features(True, False, False, False, False), True),
        (Features(False, True, False, False, False), True),
    ]:
        net = _net(feats)
        a, b = _predict(net, [s])[0][:-1], _predict(net, [moved])[0][:-1]
        assert (not np.allclose(a, b, atol=1e-6)) == interacts, feats


def test_environment_feature_reads_the_raster_only_when_on() -> None:
    s = _scene(7, 3, with_ego=True, with_raster=True)
    other = _scene(7, 3, with_ego=True, with_raster=True)
    assert other.raster is not None
    other.raster = np.ascontiguousarray(other.raster[:, ::-1])
    on = _net(Features(True, True, False, False, True))
    off = _net(Features(True, True, False, False, False))
    assert not np.allclose(_predict(on, [s])[0], _predict(on, [other])[0], atol=1e-6)
    np.testing.assert_array_equal(_predict(off, [s])[0], _predict(off, [other])[0])


def test_ego_plan_features_read_the_ego_future_only_when_on() -> None:
    s = _scene(8, 4, with_ego=True)
    replanned = _scene(8, 4, with_ego=True)
    replanned.positions = replanned.positions.copy()
    replanned.positions[0, 4:] += np.array([0.0, 2.0])  # the ego's future only
    for feats, reads in [
        (Features(True, True, False, False, False), False),
        (Features(True, True, True, False, False), True),
        (Features(True, True, False, True, False), True),
    ]:
        net = _net(feats)
        a, b = _predict(net, [s])[0], _predict(net, [replanned])[0]
        assert (not np.allclose(a, b, atol=1e-6)) == reads, feats


def test_ego_follows_its_plan_in_the_decoder() -> None:
    net = _net(Features(True, True, True, True, False))
    s = _scene(9, 3, with_ego=True)
    s.target_mask = np.ones(3, bool)  # ask for the ego too
    out = _predict(net, [s])[0]
    np.testing.assert_allclose(out[0, 0], s.positions[0, 4:], atol=1e-4)


def test_ego_frame_rotation_invariance() -> None:
    """In the ego frame, rotating the whole world rotates the predictions with it."""
    net = _net(Features(True, True, True, True, False), frame="ego")
    s = _scene(10, 4, with_ego=True)
    rot = np.array([[0.0, -1.0], [1.0, 0.0]])
    turned = _scene(10, 4, with_ego=True)
    turned.positions = s.positions @ rot.T
    np.testing.assert_allclose(_predict(net, [turned])[0], _predict(net, [s])[0] @ rot.T, atol=1e-3)


def test_collate_masks() -> None:
    cfg = ModelConfig(**SMALL)  # type: ignore[arg-type]
    s = _scene(11, 3, with_ego=True)
    s.positions = s.positions.copy()
    s.positions[2, 3] = np.nan  # not observed at the current step: not decoded, not a target
    b = collate([s, _scene(12, 2)], cfg)
    assert b.positions.shape == (5, 7, 2) and b.max_agents == 3
    assert b.active.tolist() == [True, True, False, True, True]
    assert b.target.tolist() == [False, True, False, True, True]
    assert b.ego.tolist() == [True, False, False, False, False]
    assert b.scene.tolist() == [0, 0, 0, 1, 1] and b.slot.tolist() == [0, 1, 2, 0, 1]
    assert b.raster is None
    assert float(b.positions[2, 3].abs().sum()) == 0.0


@pytest.mark.parametrize("step_output", ["displacement", "agent_velocity_change"])
def test_speed_unit_frame_sees_a_faster_scene_at_a_smaller_size(step_output: str) -> None:
    """With ``speed_unit_m`` a scene and its copy at twice the size (twice the speeds) give the same
    model-frame inputs and the same network output, mapped back to metres at twice the size; rasters keep
    pointing at the same pixels. With the per-agent output its speed floor is in model units, so it holds too."""
    from dataclasses import replace

    from logpipe.model.zhu2020.batching import _speed_scale

    cfg = ModelConfig(speed_unit_m=0.5, step_output=step_output, **SMALL)  # type: ignore[arg-type]
    s = _scene(21, 4, with_raster=True)
    big = replace(s, positions=s.positions * 2.0, world_to_raster=s.world_to_raster @ np.diag([0.5, 0.5, 1.0]))
    b, b2 = collate([s], cfg), collate([big], cfg)
    assert b2.scale[0] == b.scale[0] / 2 and b.scale[0] != 1.0
    torch.testing.assert_close(b.positions, b2.positions, rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(b.frame_to_px, b2.frame_to_px, rtol=1e-5, atol=1e-5)
    world = b.to_world(b.positions[:, :, None], b.scene)[:, :, 0]
    seen = np.isfinite(s.positions[:, : world.shape[1]])
    np.testing.assert_allclose(world[seen], s.positions[:, : world.shape[1]][seen], atol=1e-4)
    torch.testing.assert_close(b2.metres(b2.positions, b2.scene), 2 * b.metres(b.positions, b.scene))
    torch.manual_seed(0)
    net = TrajectoryNet(replace(cfg, features=Features(True, True, False, False, False))).eval()
    out, out_big = _predict(net, [s])[0], _predict(net, [big])[0]
    np.testing.assert_allclose(out_big, 2 * out, rtol=1e-4, atol=1e-4)
    from logpipe.model.zhu2020.evaluation import evaluate

    errors, errors_big = (evaluate(net, [scene], num_modes=1) for scene in (s, big))
    assert errors.count == errors_big.count > 0
    assert errors_big.ade == pytest.approx(2 * errors.ade, rel=1e-4)  # validation reports metres
    still = np.zeros((2, 4, 2))
    assert _speed_scale(still, 0.5) == 4.0  # nobody moves: the largest scale, no division by zero
    assert _speed_scale(np.full((1, 4, 2), np.nan), 0.5) == 4.0


def test_speed_unit_must_be_positive() -> None:
    from logpipe.model.zhu2020.config import ConfigError

    with pytest.raises(ConfigError, match="speed_unit_m"):
        ModelConfig(speed_unit_m=0.0)


def test_predictor_settings_compose() -> None:
    """with_noise_scale and with_constant_velocity_modes each keep the other setting; the held mode is the
    constant-velocity forecast in world metres, the others are the noise-scaled forecasts."""
    torch.manual_seed(0)
    net = TrajectoryNet(ModelConfig(noise_dim=3, step_output="agent_velocity_change", **SMALL)).eval()
    scenes = [_scene(0, 5), _scene(2, 7)]
    scaled = NetPredictor(net).with_noise_scale(0.5)
    both = scaled.with_constant_velocity_modes(1).with_noise_scale(0.5)
    assert (both.noise_scale, both.constant_velocity_modes) == (0.5, 1)
    ref, held = scaled.predict(scenes, 3, seed=0), both.predict(scenes, 3, seed=0)
    for s, r, h in zip(scenes, ref, held, strict=True):
        pos = s.positions[np.asarray(s.target_mask, bool)]
        step = pos[:, 3] - pos[:, 2]
        cv = pos[:, 3, None] + np.arange(1, 4)[None, :, None] * step[:, None]
        np.testing.assert_allclose(h[:, 0], cv, atol=1e-4)
        np.testing.assert_allclose(h[:, 1:], r[:, 1:], atol=1e-5)
