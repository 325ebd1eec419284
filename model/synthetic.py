"""Synthetic ``SceneSample``s for tests and benchmarks (ETH/UCY-like walkers, optional ego and raster).

Agents walk with a random constant velocity plus a slow random turn; the raster is an ego-centred
``size x size`` image over ``extent_m`` metres whose channels are simple stripes (a stand-in for drivable
area / centerlines), with the same world-to-pixel convention as the rasteriser: integer pixel
coordinates are pixel centres, x -> columns, y -> rows (flipped so +y is up).
"""

from __future__ import annotations

import numpy as np

from logpipe.types import OBJECT_TYPES, SceneSample


def world_to_raster_affine(centre: np.ndarray, size: int = 224, extent_m: float = 100.0) -> np.ndarray:
    """(2, 3) affine mapping world metres to pixel (col, row) for a raster centred on ``centre``."""
    s = size / extent_m
    c0 = (size - 1) / 2.0
    return np.array([[s, 0.0, c0 - s * centre[0]], [0.0, -s, c0 + s * centre[1]]])


def make_scene(  # noqa: PLR0913  scene factory for tests: independent knobs, all defaulted
    rng: np.random.Generator,
    num_agents: int = 10,
    obs_len: int = 8,
    pred_len: int = 12,
    *,
    with_ego: bool = False,
    with_raster: bool = False,
    channels: int = 4,
    size: int = 224,
    extent_m: float = 100.0,
    speed: float = 0.5,
    sample_id: str = "synthetic:0",
) -> SceneSample:
    """One scene; every agent is observed at every step and is a target (except the ego)."""
    t = obs_len + pred_len
    start = rng.uniform(-10, 10, size=(num_agents, 2))
    heading = rng.uniform(-np.pi, np.pi, size=num_agents)
    turn = rng.normal(0.0, 0.05, size=num_agents)
    vel = rng.uniform(0.5, 1.5, size=num_agents) * speed
    angles = heading[:, None] + turn[:, None] * np.arange(t)
    steps = vel[:, None, None] * np.stack((np.cos(angles), np.sin(angles)), axis=-1)
    positions = start[:, None] + np.cumsum(steps, axis=1) - steps[:, :1]
    target = np.ones(num_agents, bool)
    ego_index = -1
    if with_ego:
        ego_index = 0
        target[0] = False
    raster = w2r = None
    if with_raster:
        centre = positions[max(ego_index, 0), obs_len - 1]
        w2r = world_to_raster_affine(centre, size, extent_m)
        yy, xx = np.mgrid[0:size, 0:size]
        img = np.zeros((channels, size, size), np.uint8)
        for ch in range(channels):
            period = 12 + 5 * ch
            img[ch] = np.where(((xx + 3 * yy * (ch % 2)) // period) % 2 == 0, 255, 0)
        raster = img
    return SceneSample(
        sample_id=sample_id,
        positions=positions,
        timestamps_ns=np.arange(t, dtype=np.int64) * 400_000_000,
        track_ids=[str(i) for i in range(num_agents)],
        object_types=np.full(num_agents, OBJECT_TYPES.index("pedestrian"), np.int64),
        target_mask=target,
        ego_index=ego_index,
        obs_len=obs_len,
        raster=raster,
        world_to_raster=w2r,
    )


def make_scenes(
    count: int,
    seed: int = 0,
    min_agents: int = 8,
    max_agents: int = 30,
    **kwargs: object,
) -> list[SceneSample]:
    """``count`` scenes with uniformly random agent counts in [min_agents, max_agents]."""
    rng = np.random.default_rng(seed)
    return [
        make_scene(rng, int(rng.integers(min_agents, max_agents + 1)), sample_id=f"synthetic:{i}", **kwargs)  # type: ignore[arg-type]
        for i in range(count)
    ]
