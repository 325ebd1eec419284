"""``ModelConfig.context_radius_m``: each target predicted in a scene of its own neighbourhood."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch

from logpipe.dataset.reader import Dataset
from logpipe.errors import LogpipeError
from logpipe.model.synthetic import make_scene, make_scenes
from logpipe.model.zhu2020.batching import Batch, collate, context_scenes, neighbour_counts
from logpipe.model.zhu2020.config import ConfigError, Features, ModelConfig, TrainConfig
from logpipe.model.zhu2020.fit import fit
from logpipe.model.zhu2020.network import TrajectoryNet
from logpipe.model.zhu2020.predictor import NetPredictor
from logpipe.stages.ingest import IngestOptions, ingest
from logpipe.stages.train import scene_samples

BUNDLED = Path(__file__).resolve().parents[1] / "data"
MODEL = ModelConfig(features=Features(True, True, False, False, False), embed_dim=16, gru_dim=16, lstm_dim=16,
                    noise_dim=2, obs_len=8, pred_len=12, step_output="agent_velocity_change", speed_unit_m=0.3)


@pytest.fixture(scope="module")
def eth_windows(tmp_path_factory: pytest.TempPathFactory) -> list:  # type: ignore[type-arg]
    """Real windows (bundled ETH sample) with several pedestrians each."""
    out = tmp_path_factory.mktemp("ethucy")
    ingest([BUNDLED / "ethucy"], IngestOptions(out=out, write_mcap=False))
    windows = [s for s in scene_samples(Dataset.open(out), "eth/train") if len(s.track_ids) >= 3]
    assert len(windows) >= 5
    return windows


def test_each_target_gets_its_neighbourhood(eth_windows: list) -> None:  # type: ignore[type-arg]
    radius = 2.0
    for sample in eth_windows[:40]:
        scenes = context_scenes(sample, radius)
        targets = np.flatnonzero(sample.target_mask)
        assert len(scenes) == len(targets)
        now = sample.positions[:, sample.obs_len - 1]
        seen = np.isfinite(now).all(axis=1)
        for i, scene in zip(targets, scenes, strict=True):
            assert scene.target_mask.sum() == 1
            assert scene.track_ids[int(np.flatnonzero(scene.target_mask)[0])] == sample.track_ids[i]
            near = {sample.track_ids[j] for j in np.flatnonzero(seen)
                    if np.linalg.norm(now[j] - now[i]) <= radius}
            assert set(scene.track_ids) == near | {sample.track_ids[i]}
            rows = [sample.track_ids.index(t) for t in scene.track_ids]
            np.testing.assert_array_equal(scene.positions, sample.positions[rows])


def test_max_neighbours_keeps_the_nearest(eth_windows: list) -> None:  # type: ignore[type-arg]
    radius, cap = 4.0, 2
    capped_some = False
    for sample in eth_windows[:40]:
        now = sample.positions[:, sample.obs_len - 1]
        seen = np.isfinite(now).all(axis=1)
        for i, full, capped in zip(np.flatnonzero(sample.target_mask), context_scenes(sample, radius),
                                   context_scenes(sample, radius, cap), strict=True):
            others = [t for t in full.track_ids if t != sample.track_ids[i]]
            kept = [t for t in capped.track_ids if t != sample.track_ids[i]]
            assert set(kept) <= set(others) and len(kept) == min(cap, len(others))
            capped_some |= len(others) > cap
            if len(others) > cap:  # nobody left out is nearer than someone kept
                dist = {sample.track_ids[j]: float(np.linalg.norm(now[j] - now[i])) for j in np.flatnonzero(seen)}
                assert max(dist[t] for t in kept) <= min(dist[t] for t in set(others) - set(kept))
        assert context_scenes(sample, radius, 0)[0].track_ids == [sample.track_ids[np.argmax(sample.target_mask)]]
    assert capped_some, "the bundled windows should have a target with more than two neighbours within 4 m"


def test_max_neighbours_must_not_be_negative() -> None:
    with pytest.raises(ConfigError, match="context_max_neighbours"):
        replace(MODEL, context_max_neighbours=-1)


def test_the_ego_stays_in_every_neighbourhood() -> None:
    sample = make_scene(np.random.default_rng(3), 6, 8, 12, with_ego=True)
    far = sample.positions.copy()
    far[sample.ego_index] += 1000.0  # the ego far from everyone
    scenes = context_scenes(replace(sample, positions=far), 2.0)
    assert scenes
    for scene in scenes:
        assert scene.ego_index >= 0 and scene.track_ids[scene.ego_index] == sample.track_ids[sample.ego_index]


def _deterministic(config: ModelConfig) -> NetPredictor:
    torch.manual_seed(0)
    return NetPredictor(TrajectoryNet(replace(config, noise_dim=0)), batch_size=4)


def test_targets_are_seen_in_their_window_frame(eth_windows: list) -> None:  # type: ignore[type-arg]
    windows = eth_windows[:12]
    plain = collate(windows, MODEL, rotations=[0.3 * i for i in range(12)])
    batch = collate(windows, replace(MODEL, context_radius_m=2.0), rotations=[0.3 * i for i in range(12)])
    mine, theirs = np.concatenate(batch.sample_targets), np.concatenate(plain.sample_targets)
    # origin, axes, rotation and speed scale are the window's: the same model-frame tracks
    np.testing.assert_allclose(batch.positions[mine].numpy(), plain.positions[theirs].numpy(), atol=1e-6)
    np.testing.assert_allclose(batch.scale[batch.scene[mine].numpy()], plain.scale[plain.scene[theirs].numpy()])


def test_target_origin_moves_only_the_origin(eth_windows: list) -> None:  # type: ignore[type-arg]
    windows = eth_windows[:12]
    turns = [0.3 * i for i in range(12)]
    window = collate(windows, replace(MODEL, context_radius_m=2.0), rotations=turns)
    centred = collate(windows, replace(MODEL, context_radius_m=2.0, context_origin="target"), rotations=turns)
    mine = np.concatenate(centred.sample_targets)
    now = MODEL.obs_len - 1
    assert np.abs(centred.positions[mine, now].numpy()).max() == 0.0  # each target at its scene's origin
    # same axes, rotation and scale, so the same tracks up to a shift and the same points in the world
    np.testing.assert_array_equal(centred.rotation, window.rotation)
    np.testing.assert_array_equal(centred.scale, window.scale)
    shift = window.positions[:, now : now + 1] - centred.positions[:, now : now + 1]
    valid = window.valid.numpy()
    np.testing.assert_allclose((centred.positions + shift).numpy()[valid], window.positions.numpy()[valid], atol=1e-5)

    def world(batch: Batch, rows: np.ndarray) -> np.ndarray:
        scene = batch.scene.numpy()[rows]
        local = batch.positions.numpy()[rows] / batch.scale[scene][:, None, None]
        return np.asarray(np.einsum("nji,ntj->nti", batch.rotation[scene], local) + batch.origin[scene][:, None])

    np.testing.assert_allclose(world(centred, mine)[:, :now + 1], np.concatenate(
        [w.positions[w.target_mask.astype(bool), :now + 1] for w in windows]), atol=1e-4)
    with pytest.raises(ConfigError, match="context_origin"):
        replace(MODEL, context_origin="agent")


def test_without_interaction_features_the_option_changes_nothing(eth_windows: list) -> None:  # type: ignore[type-arg]
    no_pools = replace(MODEL, features=Features(False, False, False, False, False))
    plain = collate(eth_windows[:12], no_pools)
    batch = collate(eth_windows[:12], replace(no_pools, context_radius_m=2.0))
    assert batch.size == plain.size == 12
    torch.testing.assert_close(batch.positions, plain.positions)


def test_agents_beyond_the_radius_do_not_reach_a_forecast() -> None:
    sample = make_scene(np.random.default_rng(5), 8, 8, 12)
    mask = sample.target_mask.copy()
    mask[7] = False  # a context agent: moving it leaves the frame (origin = mean target, scale = mean step) alone
    beside_0 = sample.positions.copy()
    beside_0[7] = beside_0[0] + [1.0, 0.0]  # walking 1 m beside agent 0
    sample = replace(sample, target_mask=mask, positions=beside_0)
    moved = sample.positions.copy()
    moved[7] += 100.0
    far_off = replace(sample, positions=moved)
    now = sample.positions[:, sample.obs_len - 1]
    apart = np.linalg.norm(now[:7] - now[7], axis=1) > 2.0  # targets that never had agent 7 as a neighbour
    assert apart.any() and not apart.all()
    plain = _deterministic(MODEL)
    in_context = _deterministic(replace(MODEL, context_radius_m=2.0))
    in_context.net.load_state_dict(plain.net.state_dict())
    before, after = in_context.predict([sample], 1, 0)[0], in_context.predict([far_off], 1, 0)[0]
    np.testing.assert_allclose(before[apart], after[apart], rtol=1e-5, atol=1e-5)
    assert not np.allclose(before[~apart], after[~apart])
    # the paper's global pools feel it everywhere
    assert not np.allclose(plain.predict([sample], 1, 0)[0][apart], plain.predict([far_off], 1, 0)[0][apart])


def test_collate_maps_each_sample_to_its_target_rows(eth_windows: list) -> None:  # type: ignore[type-arg]
    cfg = replace(MODEL, context_radius_m=2.0)
    windows = eth_windows[:6]
    batch = collate(windows, cfg)
    assert batch.size == sum(int(s.target_mask.sum()) for s in windows)
    assert [len(rows) for rows in batch.sample_targets] == [int(s.target_mask.sum()) for s in windows]
    every = np.concatenate(batch.sample_targets)
    assert batch.target[torch.from_numpy(every)].all() and int(batch.target.sum()) == len(every)
    plain = collate(windows, MODEL)
    assert [len(r) for r in plain.sample_targets] == [len(r) for r in batch.sample_targets]


def test_fit_trains_on_target_scenes(tmp_path: Path) -> None:
    data = make_scenes(6, seed=4, min_agents=3, max_agents=4, obs_len=8, pred_len=12)
    cfg = TrainConfig(model=replace(MODEL, context_radius_m=3.0), steps=4, batch_size=4, num_modes=3, val_modes=3,
                      eval_every=2, log_every=2, num_threads=1)
    res = fit(data, data[:2], cfg, tmp_path, progress=False)
    assert res.steps == 4 and np.isfinite(res.best_val_ade)
    loaded = NetPredictor.from_checkpoint(res.best_checkpoint)  # type: ignore[arg-type]
    assert loaded.config.context_radius_m == 3.0


@pytest.mark.parametrize("radius", [0.0, -1.0, float("nan"), float("inf")])
def test_radius_must_be_positive_and_finite(radius: float) -> None:
    with pytest.raises(ConfigError, match="context_radius_m"):
        ModelConfig(context_radius_m=radius)


def test_neighbour_counts_are_the_context_sizes(eth_windows: list) -> None:  # type: ignore[type-arg]
    for sample in eth_windows[:40]:
        seen = np.isfinite(sample.positions[:, sample.obs_len - 1]).all(axis=1)
        sizes = [len(scene.track_ids) - 1 for scene, i in
                 zip(context_scenes(sample, 3.0), np.flatnonzero(sample.target_mask), strict=True) if seen[i]]
        np.testing.assert_array_equal(neighbour_counts(sample, 3.0), sizes)


def test_a_neighbour_cap_at_inference_changes_only_capped_targets(eth_windows: list) -> None:  # type: ignore[type-arg]
    """The override reaches collate: a cap above every count gives the plain forecasts to the bit, a cap of 0 the
    forecasts of a radius nobody is within; a network without a context radius refuses it."""
    config = replace(MODEL, context_radius_m=4.0)
    plain = _deterministic(config)
    windows = eth_windows[:12]
    most = int(max(neighbour_counts(s, 4.0).max(initial=0) for s in windows))
    assert most >= 1
    base = np.concatenate(plain.predict(windows, 1, 0))
    np.testing.assert_array_equal(np.concatenate(plain.with_context_max_neighbours(most).predict(windows, 1, 0)), base)
    alone = np.concatenate(plain.with_context_max_neighbours(0).predict(windows, 1, 0))
    tiny = _deterministic(replace(MODEL, context_radius_m=1e-6))  # same weights, nobody within reach
    np.testing.assert_array_equal(alone, np.concatenate(tiny.predict(windows, 1, 0)))
    assert not np.allclose(alone, base, atol=1e-4)
    assert plain.with_context_max_neighbours(3).with_noise_scale(0.5).config.context_max_neighbours == 3
    with pytest.raises(LogpipeError, match="context_radius_m"):
        NetPredictor(TrajectoryNet(MODEL), context_max_neighbours=2)
