"""What the residual driving model reads of a scene, per target, in the target's own frame.

Each target gets a frame: origin at its prior's fitted current position (``model.kinematic.adaptive_prior``), x
along the prior's velocity (standing still: along its observed displacement, else the lane it stands on, else the
raster's up), and a length scale L = max(speed x ``horizon_scale_s``, ``min_scale_m``). In that frame:

* ``features``: its observed track (in units of L), the track minus the prior's line (how it turned and sped up),
  log(1 + speed in m/s), the prior's window and the track's jitter (how noisy the sensor is);
* ``neighbours``: the nearest agents observed now within ``neighbour_radius_m``: their last steps and velocity
  (of L, and L per second), with a mask (the max-pooled position features of the paper's eqs. 1-2, per target);
* ``crops``: the environment net's input, the map raster resampled into the target's frame (``crop_px`` cells of
  ``crop_res_m``): drivable area, lane centerlines, boundaries, crossings, and the lanes' travel direction as a
  vector field turned into the target's frame (two channels), so a lane heading the target's way reads the same
  whichever way the raster was drawn.

Forecasts are the prior's positions plus residuals the network gives in the target's frame in units of L
(``to_world``). Units: metres, world frame of the log, unless said.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, fields
from typing import Any

import cv2
import numpy as np

from logpipe.raster.rasteriser import DEFAULT_CHANNELS
from logpipe.types import NDArrayBool, NDArrayFloat, NDArrayFloat32, SceneSample

from ..kinematic.adaptive_prior import adaptive_fit
from .config import ResidualConfig

CROP_CHANNELS = ("drivable_area", "lane_centerline", "lane_boundary", "crossing", "lane_forward", "lane_left")
"""The crop's channels (the last two: the lanes' travel direction in the target's frame, x forward, y left)."""
INPUTS_VERSION = 4
"""Bumped whenever what ``target_inputs`` computes changes (cached inputs of an older version are not reused)."""
CROP_UNIT = 127.0
"""A crop value of 1 is stored as this (int8)."""
STILL_MPS = 0.5
"""Slower than this (m/s) the prior's velocity gives no direction."""
_FEATURES_TAIL = 3  # log speed, prior window, jitter


@dataclass
class TargetInputs:
    """Inputs of N targets (rows in the order of their samples' target masks).

    Attributes:
        features: (N, F) float32, see the module docstring; neighbours (N, K, F_n) float32; neighbour_mask (N, K).
        crops: (N, 6, P, P) int8, the crop's values (0..1, the direction channels -1..1) times 127, or None without
            the environment net (int8: a million targets' crops fit in 14 GB).
        origin: (N, 2) the frame's origin; rotation (N, 2, 2) world → target frame; scale (N,) L in metres.
        prior: (N, T_pred, 2) the prior's forecast; speed (N,) m/s; rate_hz (N,) the window's steps per second.
        truth: (N, T_pred, 2) float32 residual of the true future (frame, units of L), or None when unknown.
        has_map: (N,) whether the raster draws any map within ~5 m of the target (False: no raster, or off it
            or its map).
        window: (N,) the prior's fit window (steps).
        object_type: (N,) codes into ``OBJECT_TYPES``.
        motion: (N, 2) acceleration along the track (m/s^2) and yaw rate (rad/s) over the last 10 observed steps.
        observed: (N, T_obs, 2) the observed track, world metres (the Kalman fallback's input).
    """

    features: NDArrayFloat32
    neighbours: NDArrayFloat32
    neighbour_mask: NDArrayBool
    crops: np.ndarray | None
    origin: NDArrayFloat
    rotation: NDArrayFloat
    scale: NDArrayFloat
    prior: NDArrayFloat
    speed: NDArrayFloat
    rate_hz: NDArrayFloat
    truth: NDArrayFloat32 | None
    has_map: NDArrayBool
    window: np.ndarray
    object_type: np.ndarray
    motion: NDArrayFloat
    observed: NDArrayFloat

    def __len__(self) -> int:
        return len(self.features)

    def take(self, rows: np.ndarray) -> TargetInputs:
        """The inputs of ``rows``."""
        picked: dict[str, Any] = {f.name: None if getattr(self, f.name) is None else getattr(self, f.name)[rows]
                                  for f in fields(self)}
        return TargetInputs(**picked)


def concat(parts: Sequence[TargetInputs]) -> TargetInputs:
    """Several batches' inputs as one (crops and truth kept only where every part has them)."""
    out: dict[str, Any] = {}
    for f in fields(TargetInputs):
        values = [getattr(p, f.name) for p in parts]
        out[f.name] = None if any(v is None for v in values) else np.concatenate(values)
    return TargetInputs(**out)


def to_world(residual: NDArrayFloat, inputs: TargetInputs) -> NDArrayFloat:
    """Forecasts in world metres from residuals (N, ..., T_pred, 2) in the targets' frames, units of L."""
    extra = residual.ndim - 3
    scale = inputs.scale.reshape(-1, *([1] * (residual.ndim - 1)))
    turned = np.einsum("nji,n...tj->n...ti", inputs.rotation, residual * scale)
    prior = inputs.prior.reshape(len(inputs.prior), *([1] * extra), *inputs.prior.shape[1:])
    out: NDArrayFloat = prior + turned
    return out


def world_truth(inputs: TargetInputs) -> NDArrayFloat:
    """(N, T_pred, 2) the targets' true futures in world metres (inputs with their truth)."""
    assert inputs.truth is not None
    out: NDArrayFloat = inputs.prior + np.einsum("nji,ntj->nti", inputs.rotation,
                                                 inputs.truth * inputs.scale[:, None, None])
    return out


def target_inputs(sample: SceneSample, config: ResidualConfig, *, with_truth: bool = False) -> TargetInputs:
    """Every target of ``sample`` (its ``target_mask`` rows, in order) as the network's inputs."""
    targets = np.flatnonzero(np.asarray(sample.target_mask, bool))
    positions = np.asarray(sample.positions, np.float64)
    obs_len = sample.obs_len
    observed = positions[targets, :obs_len]
    fit = adaptive_fit(observed)
    rate = _rate_hz(sample)
    speed = np.linalg.norm(fit.velocity, axis=1) * rate
    theta = _headings(sample, observed, fit.velocity, speed)
    cos, sin = np.cos(theta), np.sin(theta)
    rotation = np.stack([np.stack([cos, sin], -1), np.stack([-sin, cos], -1)], 1)  # world -> target frame
    scale = np.maximum(speed * config.horizon_scale_s, config.min_scale_m)
    prior = fit.forecast(config.pred_len)
    features = _target_features(observed, fit.origin, fit.velocity, fit.window, rotation, scale, speed)
    neighbours, mask = _neighbours(positions, targets, obs_len, fit.origin, rotation, scale, rate, config)
    crops = _crops(sample, fit.origin, theta, config) if config.environment else None
    has_map = _map_under(sample, fit.origin)  # one definition with or without crops: the OOD check compares them
    truth = None
    if with_truth:
        future = positions[targets, obs_len:obs_len + config.pred_len]
        truth = (np.einsum("nij,ntj->nti", rotation, future - prior) / scale[:, None, None]).astype(np.float32)
    return TargetInputs(features, neighbours, mask, crops, fit.origin, rotation, scale, prior, speed,
                        np.full(len(targets), rate), truth, has_map, fit.window,
                        np.asarray(sample.object_types, np.int64)[targets], _motion(observed, rate), observed)


def _motion(observed: NDArrayFloat, rate: float) -> NDArrayFloat:
    """(N, 2): change of speed (m/s^2) and of direction (rad/s) between the line fits over steps -10..-6 and
    -5..-1 (direction only where both speeds are over 1 m/s; 0 for tracks shorter than 10 steps)."""
    n = len(observed)
    if observed.shape[1] < 10:
        return np.zeros((n, 2))
    half = 5 / rate
    t = np.arange(5, dtype=np.float64) - 2.0
    slopes = [((t[None, :, None]) * (np.nan_to_num(observed[:, a:b]) - np.nan_to_num(observed[:, a:b]).mean(1,
              keepdims=True))).sum(1) / (t**2).sum() * rate for a, b in ((-10, -5), (-5, None))]
    v1, v2 = (np.linalg.norm(v, axis=1) for v in slopes)
    turn = np.arctan2(slopes[1][:, 1], slopes[1][:, 0]) - np.arctan2(slopes[0][:, 1], slopes[0][:, 0])
    turn = (turn + np.pi) % (2 * np.pi) - np.pi
    return np.stack([(v2 - v1) / half, np.where((v1 > 1) & (v2 > 1), turn / half, 0.0)], axis=1)


def _rate_hz(sample: SceneSample) -> float:
    """Steps per second of the window (from its true times)."""
    dt = np.diff(np.asarray(sample.timestamps_ns, np.int64))
    return 1e9 / float(np.median(dt)) if len(dt) and np.median(dt) > 0 else 10.0


def _headings(sample: SceneSample, observed: NDArrayFloat, velocity: NDArrayFloat, speed: NDArrayFloat
              ) -> NDArrayFloat:
    """Each target's frame direction (rad, world): the prior's velocity; standing still, its observed
    displacement (over 1 m), else the lane under it (the raster's direction channels), else the raster's up."""
    theta = np.arctan2(velocity[:, 1], velocity[:, 0])
    span = observed[:, -1] - observed[:, 0]
    moved = np.linalg.norm(span, axis=1) > 1.0
    still = speed < STILL_MPS
    theta = np.where(still & moved, np.arctan2(span[:, 1], span[:, 0]), theta)
    rest = np.flatnonzero(still & ~moved)
    if len(rest) and sample.raster is not None and sample.world_to_raster is not None:
        theta[rest] = [_lane_heading(sample, observed[i, -1]) for i in rest]
    elif len(rest):
        theta[rest] = 0.0
    return np.where(np.isfinite(theta), theta, 0.0)


def _direction_field(raster: np.ndarray, rows: slice, cols: slice) -> tuple[NDArrayFloat, NDArrayFloat, NDArrayFloat]:
    """(du, dv, strength) of the lanes' direction in the image frame over a window of the raster (default
    channels: up/left/down/right quadrants)."""
    index = {name: i for i, name in enumerate(DEFAULT_CHANNELS)}
    part = {k: raster[index[k], rows, cols].astype(np.float64) / 255.0
            for k in ("lane_up", "lane_left", "lane_down", "lane_right")}
    du, dv = part["lane_right"] - part["lane_left"], part["lane_down"] - part["lane_up"]
    return du, dv, np.maximum.reduce(list(part.values()))


def _lane_heading(sample: SceneSample, xy: NDArrayFloat) -> float:
    """Travel direction (rad, world) of the lanes within 2 m of ``xy`` on the raster; the raster's up without."""
    affine = np.asarray(sample.world_to_raster, np.float64)
    inverse = np.linalg.inv(affine[:, :2])
    raster = np.asarray(sample.raster)
    u, v = affine[:, :2] @ xy + affine[:, 2]
    r = 5  # pixels (~2 m at 0.45 m/px)
    rows = slice(max(int(v) - r, 0), max(int(v) + r + 1, 0))
    cols = slice(max(int(u) - r, 0), max(int(u) + r + 1, 0))
    du, dv, strength = _direction_field(raster, rows, cols)
    world = inverse @ np.array([(du * strength).sum(), (dv * strength).sum()])
    if not np.hypot(*world) > 1e-6:
        world = inverse @ np.array([0.0, -1.0])  # the raster's up: its centre agent's heading
    return float(np.arctan2(world[1], world[0]))


def _target_features(observed: NDArrayFloat, origin: NDArrayFloat, velocity: NDArrayFloat, window: np.ndarray,
                     rotation: NDArrayFloat, scale: NDArrayFloat, speed: NDArrayFloat) -> NDArrayFloat32:
    """(N, 4 T_obs + 3): the track in units of L, the track minus the prior's line (of 2 m), and log(1 + speed),
    window / 12, log jitter (mean |track - line| over the last 8 steps). Speed is given once, as a number: every
    length is in units of L, so what the network learns of a manoeuvre carries over to speeds it has not seen (the
    track also in metres made the held-out US-101's K = 1 FDE 2.83 m against 2.50 without, leave-one-location-out
    on the real data)."""
    n, t_obs = observed.shape[:2]
    track = np.einsum("nij,ntj->nti", rotation, np.nan_to_num(observed - origin[:, None]))
    line = origin[:, None] + velocity[:, None] * (np.arange(t_obs) - (t_obs - 1.0))[None, :, None]
    off = np.einsum("nij,ntj->nti", rotation, np.nan_to_num(observed - line))
    jitter = np.log(np.abs(off[:, -8:]).mean(axis=(1, 2)) + 1e-3)
    parts = [(track / scale[:, None, None]).reshape(n, -1), (off / 2.0).reshape(n, -1),
             np.log1p(speed)[:, None], window[:, None] / 12.0, jitter[:, None]]
    return np.concatenate(parts, axis=1).astype(np.float32)


def feature_width(config: ResidualConfig) -> int:
    """F of ``TargetInputs.features``."""
    return 4 * config.obs_len + _FEATURES_TAIL


def neighbour_width(config: ResidualConfig) -> int:
    """F_n of ``TargetInputs.neighbours``."""
    return 2 * config.neighbour_steps + 2


def _neighbours(positions: NDArrayFloat, targets: np.ndarray, obs_len: int, origin: NDArrayFloat,
                rotation: NDArrayFloat, scale: NDArrayFloat, rate: float, config: ResidualConfig
                ) -> tuple[NDArrayFloat32, NDArrayBool]:
    """(N, K, F_n) nearest agents observed over their last ``neighbour_steps`` steps, in each target's frame."""
    k, steps = config.neighbours, config.neighbour_steps
    n = len(targets)
    out = np.zeros((n, k, neighbour_width(config)), np.float32)
    mask = np.zeros((n, k), bool)
    if k == 0:
        return out, mask
    recent = positions[:, obs_len - steps:obs_len]
    seen = np.all(np.isfinite(recent), axis=(1, 2))
    now = positions[:, obs_len - 1]
    for row, agent in enumerate(targets):
        dist = np.linalg.norm(now - now[agent], axis=1)
        dist[~seen | (np.arange(len(now)) == agent) | ~(dist <= config.neighbour_radius_m)] = np.inf
        near = np.argsort(dist, kind="stable")[:k]
        near = near[np.isfinite(dist[near])]
        if not len(near):
            continue
        rel = np.einsum("ij,ktj->kti", rotation[row], recent[near] - origin[row]) / scale[row]
        vel = (rel[:, -1] - rel[:, -2]) * rate
        out[row, :len(near)] = np.concatenate([rel.reshape(len(near), -1), vel], axis=1)
        mask[row, :len(near)] = True
    return out, mask


def _map_under(sample: SceneSample, xy: NDArrayFloat) -> NDArrayBool:
    """(N,) whether the raster (every channel is map) draws anything within ~5 m of each point (False without a
    raster, or off it)."""
    if sample.raster is None or sample.world_to_raster is None:
        return np.zeros(len(xy), bool)
    raster = np.asarray(sample.raster)
    affine = np.asarray(sample.world_to_raster, np.float64)
    uv = np.rint(xy @ affine[:, :2].T + affine[:, 2]).astype(np.int64)
    r = 11  # pixels (~5 m at 0.45 m/px)
    size = raster.shape[1:]
    return np.array([bool(raster[:, max(v - r, 0):max(v + r + 1, 0), max(u - r, 0):max(u + r + 1, 0)].any())
                     if -r <= u < size[1] + r and -r <= v < size[0] + r else False for u, v in uv.tolist()])


def _crops(sample: SceneSample, origin: NDArrayFloat, theta: NDArrayFloat, config: ResidualConfig) -> np.ndarray:
    """(N, 6, P, P) int8 crops of the sample's raster in each target's frame (``TargetInputs.crops``; zeros
    without a raster)."""
    p = config.crop_px
    n = len(origin)
    crops = np.zeros((n, len(CROP_CHANNELS), p, p), np.int8)
    if sample.raster is None or sample.world_to_raster is None:
        return crops
    raster = np.asarray(sample.raster)
    affine = np.asarray(sample.world_to_raster, np.float64)
    inverse = np.linalg.inv(affine[:, :2])
    index = {name: i for i, name in enumerate(DEFAULT_CHANNELS)}
    planes = raster.astype(np.float32) / 255.0
    du, dv, strength = _direction_field(raster, slice(None), slice(None))
    wx, wy = inverse @ np.stack([du.ravel(), dv.ravel()])  # the lanes' direction in the world frame
    norm = np.hypot(wx, wy) + 1e-6
    world_dir = np.stack([wx / norm, wy / norm]).reshape(2, *du.shape) * strength
    xs = -config.crop_behind_m + (np.arange(p) + 0.5) * config.crop_res_m
    ys = (np.arange(p)[::-1] - p / 2 + 0.5) * config.crop_res_m  # row 0 is the target's far left
    gx, gy = np.meshgrid(xs, ys)
    stacked = np.concatenate([planes[[index["drivable_area"]]], strength[None].astype(np.float32),
                              planes[[index["lane_boundary"], index["crossing"]]],
                              world_dir.astype(np.float32)])
    # Anti-aliasing: 1-pixel lines sampled every crop_res_m would be hit or missed by chance; blur to the crop's
    # cell size first (sigma half a cell, in raster pixels).
    sigma = 0.5 * config.crop_res_m * float(np.sqrt(abs(np.linalg.det(affine[:, :2]))))
    if sigma > 0.5:
        stacked = np.stack([cv2.GaussianBlur(plane, (0, 0), sigma) for plane in stacked])
    for row in range(n):
        c, s = np.cos(theta[row]), np.sin(theta[row])
        wxg, wyg = origin[row, 0] + c * gx - s * gy, origin[row, 1] + s * gx + c * gy
        u = (affine[0, 0] * wxg + affine[0, 1] * wyg + affine[0, 2]).astype(np.float32)
        v = (affine[1, 0] * wxg + affine[1, 1] * wyg + affine[1, 2]).astype(np.float32)
        got = np.stack([cv2.remap(plane, u, v, cv2.INTER_LINEAR, borderValue=0.0) for plane in stacked])
        fx, fy = got[4], got[5]  # world direction → the target's frame (x forward, y left)
        got[4], got[5] = c * fx + s * fy, -s * fx + c * fy
        crops[row] = np.rint(np.clip(got, -1.0, 1.0) * CROP_UNIT).astype(np.int8)
    return crops
