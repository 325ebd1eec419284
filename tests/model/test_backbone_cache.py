"""The frozen backbone's feature-map cache (``train.cache_backbone_features``): exact, hit after the first epoch,
never stale, bounded, and refused without a frozen backbone."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch
from torch import Tensor

from logpipe.model.synthetic import make_scenes
from logpipe.model.zhu2020.backbone import ResNet18Stages12
from logpipe.model.zhu2020.batching import collate
from logpipe.model.zhu2020.config import ConfigError, ModelConfig, TrainConfig, load_config
from logpipe.model.zhu2020.feature_cache import BackboneFeatureCache, scene_keys
from logpipe.model.zhu2020.fit import fit
from logpipe.model.zhu2020.network import TrajectoryNet
from logpipe.types import SceneSample

# The full model (ego + raster), small: 3-channel 64 x 64 rasters give 128 x 8 x 8 maps.
MODEL = ModelConfig(embed_dim=16, gru_dim=16, lstm_dim=16, noise_dim=2, obs_len=4, pred_len=3,
                    raster_channels=3, freeze_backbone=True)


def _data(n: int, seed: int) -> list[SceneSample]:
    scenes = make_scenes(n, seed=seed, min_agents=2, max_agents=4, obs_len=4, pred_len=3, with_ego=True,
                         with_raster=True, channels=3, size=64, extent_m=40.0)
    # The synthetic stripes are the same in every scene: shift them so each sample has its own raster and a map
    # served for the wrong sample would change the training.
    return [replace(s, raster=np.roll(s.raster, 5 * i, axis=2)) for i, s in enumerate(scenes)]


@pytest.fixture
def backbone_images(monkeypatch: pytest.MonkeyPatch) -> list[int]:
    """Images each backbone forward call processes, in call order."""
    calls: list[int] = []
    forward = ResNet18Stages12.forward

    def counting(self: ResNet18Stages12, x: Tensor) -> Tensor:
        calls.append(int(x.shape[0]))
        out: Tensor = forward(self, x)
        return out

    monkeypatch.setattr(ResNet18Stages12, "forward", counting)
    return calls


@pytest.mark.parametrize("augment_rotate", [False, True])
def test_cached_training_is_bit_identical_and_skips_the_backbone_after_epoch_one(
    tmp_path: Path, backbone_images: list[int], augment_rotate: bool
) -> None:
    train, val = _data(12, 0), _data(4, 1)
    steps, batch = 9, 4  # three epochs of three steps
    runs = {}
    for cached in (False, True):
        cfg = TrainConfig(model=MODEL, steps=steps, batch_size=batch, num_modes=3, val_modes=3, eval_every=100,
                          log_every=1, num_threads=1, augment_rotate=augment_rotate, cache_backbone_features=cached)
        backbone_images.clear()
        res = fit(train, val, cfg, tmp_path / str(cached), progress=False)
        log = [json.loads(line) for line in res.log_path.read_text().splitlines()]
        runs[cached] = res, log, sum(backbone_images)
    (plain, plain_log, plain_images), (fast, fast_log, fast_images) = runs[False], runs[True]
    assert fast.weights_sha256 == plain.weights_sha256
    losses = [[e["loss"] for e in log if e["event"] == "train"] for log in (plain_log, fast_log)]
    assert len(losses[0]) == steps and losses[0] == losses[1]  # bit for bit (JSON keeps a float's repr)
    assert fast.best_val_ade == plain.best_val_ade
    # Every training step runs the backbone without the cache; with it, only the first epoch does (one final
    # validation over the 4 validation samples runs it in both).
    assert plain_images == steps * batch + len(val)
    assert fast_images == len(train) + len(val)
    stats = next(e for e in fast_log if e["event"] == "end")["backbone_cache"]
    assert stats == {"hits": steps * batch - len(train), "misses": len(train), "computed": len(train),
                     "stored": len(train), "stored_bytes": len(train) * 128 * 8 * 8 * 4, "unstored": 0}
    assert "backbone_cache" not in next(e for e in plain_log if e["event"] == "end")


def test_changed_raster_is_a_miss_and_the_bound_holds(backbone_images: list[int]) -> None:
    torch.manual_seed(0)
    net = TrajectoryNet(MODEL).train()
    env = net.env
    assert env is not None
    data = _data(4, 2)
    one_map = 128 * 8 * 8 * 4
    cache = BackboneFeatureCache(max_bytes=3 * one_map)  # room for three of the four maps

    def maps(samples: list[SceneSample]) -> tuple[Tensor, Tensor]:
        batch = collate(samples, MODEL)
        keys = scene_keys(samples, batch)
        assert batch.raster is not None and keys is not None
        with torch.no_grad():
            return cache.feature_maps(env, batch.raster, keys), env.feature_map(batch.raster)

    got, want = maps(data)
    assert torch.equal(got, want)
    assert (cache.stats.misses, cache.stats.stored, cache.stats.unstored) == (4, 3, 1)
    backbone_images.clear()
    got, want = maps(data[:3][::-1])  # the three stored maps, in another order: hits
    assert torch.equal(got, want) and cache.stats.hits == 3
    assert backbone_images == [3]  # only the reference ``want`` ran the backbone
    got, want = maps(data[::-1])  # the unstored fourth: the whole batch is computed, as without the cache
    assert torch.equal(got, want) and cache.stats.hits == 3 and cache.stats.computed == 8
    # Same sample id, new raster content: a miss, and the new raster's map (not the stored one).
    assert data[1].raster is not None
    edited = [replace(data[1], raster=255 - data[1].raster), data[2]]
    assert edited[0].sample_id == data[1].sample_id
    got, want = maps(edited)
    assert torch.equal(got, want) and not torch.equal(got[0], maps(data[1:2])[0][0])
    assert cache.stats.misses == 4 + 1 + 1  # first pass, the unstored one, the edited raster


def test_cache_needs_a_frozen_backbone(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match=r"train\.cache_backbone_features.*model\.freeze_backbone"):
        TrainConfig(model=replace(MODEL, freeze_backbone=False), cache_backbone_features=True)
    path = tmp_path / "c.toml"
    path.write_text("[train]\ncache_backbone_features = true\n[model]\nfreeze_backbone = false\n")
    with pytest.raises(ConfigError, match=r"model\.freeze_backbone"):
        load_config(path)
    with pytest.raises(ConfigError, match="cache_backbone_max_mb"):
        TrainConfig(model=MODEL, cache_backbone_features=True, cache_backbone_max_mb=0)
    unfrozen = TrajectoryNet(replace(MODEL, freeze_backbone=False)).env
    assert unfrozen is not None
    data = _data(2, 3)
    batch = collate(data, MODEL)
    keys = scene_keys(data, batch)
    assert batch.raster is not None and keys is not None
    with pytest.raises(ValueError, match="frozen"):
        BackboneFeatureCache(10**6).feature_maps(unfrozen, batch.raster, keys)
