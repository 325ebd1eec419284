"""Throughput of the predictor on synthetic ETH/UCY-like scenes (8-30 agents, 8 + 12 steps).

Measures, each as the median of repeats:

* training scenes/s (forward, best-of-H loss, backward, Adam step; batch 8, H = 20), without the
  environment net (the paper's ETH/UCY setting: PF + TF) and with it (all features, ego + raster), with
  the default select-then-backprop step and (no-env only) back-propagating through all H modes;
* inference scenes/s (batch 32, K = 20 modes), the same two settings;
* the cost of the environment net in training, per core, on Argoverse-shaped scenes (20 + 30 steps, 5-15 agents,
  ego, 7 x 224 x 224 raster): v4 (no EN) against the full model with the backbone trained, frozen, and frozen with
  its feature maps cached (``model.zhu2020.feature_cache``, timed in the second epoch: every map a hit), as ratios
  to v4;
* the ResNet18 stages 1-2 backbone alone (224 x 224, C = 4, batch 8, forward) in fp32 and in bf16
  autocast with channels_last, plus the bf16 accuracy cost (relative L2 error of the feature map and of
  the pooled environment feature v against fp32, same weights).

Run: ``.venv/bin/python benchmarks/bench_model.py [--quick]`` (prints JSON). Numbers depend on the other
load on the machine; ``load_avg_1m`` is recorded beside them.
"""

from __future__ import annotations

import json
import os
import statistics
import sys
import time
from collections.abc import Callable
from dataclasses import replace
from typing import Any

import numpy as np
import torch

from logpipe.model.synthetic import make_scenes
from logpipe.model.zhu2020.backbone import native_bf16
from logpipe.model.zhu2020.batching import Batch, collate
from logpipe.model.zhu2020.config import PRESETS, Features, ModelConfig
from logpipe.model.zhu2020.feature_cache import BackboneFeatureCache, scene_keys
from logpipe.model.zhu2020.network import TrajectoryNet
from logpipe.model.zhu2020.step_loss import best_of_h_step_loss
from logpipe.types import SceneSample

# Which clock _median_rate uses: "cpu" = CPU time of this process (robust on a shared machine when
# torch runs one thread), "wall" = elapsed time.
_CLOCK = {"kind": "cpu"}


def _median_rate(fn: Callable[[], int], repeats: int, warmup: int = 1) -> float:
    clock = time.process_time if _CLOCK["kind"] == "cpu" else time.perf_counter
    for _ in range(warmup):
        fn()
    rates = []
    for _ in range(repeats):
        t0 = clock()
        n = fn()
        rates.append(n / (clock() - t0))
    return statistics.median(rates)


def _train_rate(
    cfg: ModelConfig, scenes: list[SceneSample], steps: int, repeats: int, select: bool = True,
    cache: BackboneFeatureCache | None = None,
) -> float:
    """Training scenes/s over batches of 8 (windows ``scenes[8 i : 8 i + 8]``); with ``cache``, its backbone maps
    of every window are computed first (the first epoch), so the timed steps are later epochs'."""
    torch.manual_seed(0)
    net = TrajectoryNet(cfg).train()
    opt = torch.optim.Adam(net.parameters(), lr=5e-4)
    cursor = [0]

    def maps(chunk: list[SceneSample], batch: Batch) -> torch.Tensor | None:
        keys = scene_keys(chunk, batch) if cache is not None else None
        if cache is None or keys is None or net.env is None or batch.raster is None:
            return None
        fmap: torch.Tensor = cache.feature_maps(net.env, batch.raster, keys)
        return fmap

    for lo in range(0, len(scenes) - 8, 8) if cache is not None else ():
        maps(scenes[lo : lo + 8], collate(scenes[lo : lo + 8], cfg))

    def run() -> int:
        done = 0
        for _ in range(steps):
            lo = cursor[0] % (len(scenes) - 8)
            cursor[0] += 8
            batch = collate(scenes[lo : lo + 8], cfg)
            fmap = maps(scenes[lo : lo + 8], batch)
            loss = best_of_h_step_loss(net, batch, 20, torch.Generator().manual_seed(done), "scene", select, fmap)
            opt.zero_grad()
            loss.backward()  # type: ignore[no-untyped-call]
            opt.step()
            done += 8
        return done

    return _median_rate(run, repeats)


def _infer_rate(cfg: ModelConfig, scenes: list[SceneSample], repeats: int) -> float:
    torch.manual_seed(0)
    net = TrajectoryNet(cfg).eval()

    @torch.no_grad()
    def run() -> int:
        for lo in range(0, len(scenes), 32):
            net(collate(scenes[lo : lo + 32], cfg), 20)
        return len(scenes)

    return _median_rate(run, repeats)


def _train_env_cost(quick: bool) -> dict[str, Any]:
    """Training samples/s per core (1 thread, CPU time) of v4 and of the full model with the backbone trained,
    frozen, and frozen + cached (second epoch), each as a median of repeats and as a ratio to v4."""
    repeats, steps, n_scenes = (3, 1, 24) if quick else (5, 2, 48)
    scenes = make_scenes(n_scenes, seed=4, min_agents=5, max_agents=15, obs_len=20, pred_len=30, with_ego=True,
                         with_raster=True, channels=7)
    # Each sample its own raster (the synthetic stripes are the same in every scene), as on real data.
    scenes = [replace(s, raster=None if s.raster is None else np.roll(s.raster, 3 * i, axis=2))
              for i, s in enumerate(scenes)]
    base = ModelConfig(obs_len=20, pred_len=30, raster_channels=7, backbone_bf16=False)
    frozen = replace(base, freeze_backbone=True)
    cache = BackboneFeatureCache(max_bytes=10**10)
    rates = {
        "v4_no_env": _train_rate(replace(base, features=PRESETS["v4"]), scenes, steps, repeats),
        "full_env_trained": _train_rate(base, scenes, steps, repeats),
        "full_backbone_frozen": _train_rate(frozen, scenes, steps, repeats),
        "full_backbone_frozen_cached": _train_rate(frozen, scenes, steps, repeats, cache=cache),
    }
    out: dict[str, Any] = {
        "scenes": f"{n_scenes} synthetic, 5-15 agents with ego, 20 + 30 steps, 7 x 224 x 224 raster; batch 8, H = 20",
        "load_avg_1m_at_start": os.getloadavg()[0],
    }
    out.update({f"train_samples_per_s_{k}_per_core": v for k, v in rates.items()})
    out.update({f"ratio_{k}_to_v4": v / rates["v4_no_env"] for k, v in rates.items() if k != "v4_no_env"})
    # The cached run's timed steps must all have been hits: the first epoch (pre-fill) computed each sample once.
    out["cached_run_backbone_images"] = cache.stats.computed
    out["cached_run_hits"] = cache.stats.hits
    out["load_avg_1m_at_end"] = os.getloadavg()[0]
    return out


def _backbone(repeats: int) -> dict[str, float]:
    torch.manual_seed(0)
    cfg = ModelConfig()
    net = TrajectoryNet(cfg).eval()
    env = net.env
    assert env is not None
    scenes = make_scenes(8, seed=3, with_ego=True, with_raster=True)
    batch = collate(scenes, cfg)
    assert batch.raster is not None
    raster = batch.raster
    out: dict[str, float] = {}
    with torch.no_grad():
        env.backbone.use_bf16 = False
        ref = env.feature_map(raster)
        out["backbone_fp32_images_per_s"] = _median_rate(lambda: env.feature_map(raster).shape[0], repeats)
        rows = torch.arange(batch.positions.shape[0])
        pos = batch.positions[:, : cfg.obs_len].transpose(0, 1)
        v_ref = env(env.project(ref), pos, batch, rows)
        env.backbone.use_bf16 = True
        low = env.feature_map(raster)
        out["backbone_bf16_images_per_s"] = _median_rate(lambda: env.feature_map(raster).shape[0], repeats)
        # Without native bf16 the model runs its backbone in fp32 whatever the config says
        # (logpipe.model.zhu2020.backbone).
        out["cpu_has_native_bf16"] = native_bf16()
        v_low = env(env.project(low), pos, batch, rows)
    out["bf16_feature_map_rel_l2_error"] = float((low - ref).norm() / ref.norm())
    out["bf16_feature_map_max_abs_error"] = float((low - ref).abs().max())
    out["bf16_feature_map_max_abs_value"] = float(ref.abs().max())
    out["bf16_env_feature_v_rel_l2_error"] = float((v_low - v_ref).norm() / v_ref.norm())
    return out


def run(quick: bool = False) -> dict[str, Any]:
    """Measure and return a JSON-able dict of throughput figures (scenes/s, images/s).

    ``*_per_core`` figures use one torch thread and CPU time (robust to other load on the machine);
    ``*_wall_2threads`` figures use two threads and wall-clock time (what a run sees, load permitting).
    """
    repeats = 3 if quick else 5
    steps = 2 if quick else 6
    n_scenes = 48 if quick else 96
    eth = ModelConfig(features=Features(True, True, False, False, False))
    full = ModelConfig(backbone_bf16=False)
    full_bf16 = ModelConfig(backbone_bf16=True)
    plain = make_scenes(n_scenes, seed=0, min_agents=8, max_agents=30)
    mapped = make_scenes(n_scenes, seed=1, min_agents=8, max_agents=30, with_ego=True, with_raster=True)
    result: dict[str, Any] = {
        "torch": torch.__version__,
        "load_avg_1m_at_start": os.getloadavg()[0],
        "repeats": repeats,
        "scenes": "synthetic, 8-30 agents, 8 observed + 12 predicted steps; 224x224x4 raster when mapped",
        "train_batch": 8,
        "train_modes_H": 20,
        "train_steps_per_repeat": steps,
        "infer_batch": 32,
        "infer_modes_K": 20,
    }
    torch.set_num_threads(1)
    _CLOCK["kind"] = "cpu"
    result["train_env_cost"] = _train_env_cost(quick)
    result["train_samples_per_s_no_env_per_core"] = _train_rate(eth, plain, steps, repeats)
    result["train_samples_per_s_no_env_full_backprop_per_core"] = _train_rate(eth, plain, steps, repeats, False)
    result["train_samples_per_s_env_per_core"] = _train_rate(full, mapped, max(1, steps // 2), repeats)
    result["train_samples_per_s_env_bf16_backbone_per_core"] = _train_rate(
        full_bf16, mapped, max(1, steps // 2), repeats
    )
    result["infer_samples_per_s_no_env_per_core"] = _infer_rate(eth, plain, repeats)
    result["infer_samples_per_s_env_per_core"] = _infer_rate(full, mapped, repeats)
    result["infer_samples_per_s_env_bf16_backbone_per_core"] = _infer_rate(full_bf16, mapped, repeats)
    result.update({f"{k}_per_core": v for k, v in _backbone(repeats).items() if k.endswith("per_s")})
    result.update({k: v for k, v in _backbone(1).items() if not k.endswith("per_s")})
    torch.set_num_threads(2)
    _CLOCK["kind"] = "wall"
    result["train_samples_per_s_no_env_wall_2threads"] = _train_rate(eth, plain, steps, repeats)
    result["infer_samples_per_s_no_env_wall_2threads"] = _infer_rate(eth, plain, repeats)
    result["load_avg_1m_at_end"] = os.getloadavg()[0]
    return result


if __name__ == "__main__":
    print(json.dumps(run(quick="--quick" in sys.argv), indent=2))
