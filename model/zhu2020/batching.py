"""Turn ``SceneSample`` lists into padded tensors in the model frame, with masks.

Layout: agents of all scenes are flattened into N rows with scene offsets, so the LSTMs never run on
padding. The per-scene max-pools (eqs. 2, 4) scatter rows into a (B, A_max) grid whose empty cells and
unobserved agents are -inf, so padding never reaches an output (tested by adding padded agents).

Normalisation (recorded in checkpoints through ``ModelConfig``): model-frame positions are
``p = R (p_world - origin)`` in metres, where

* ``frame="world"``: ``origin`` is the mean current (step ``obs_len - 1``) position of the scene's targets
  that are observed then (else of all agents observed then) and ``R`` is the identity, i.e. world axes;
* ``frame="ego"``: ``origin`` is the ego's current position and ``R`` rotates the ego's last observed
  heading onto +x (the paper's ego-perspective "relative coordinate"). Scenes without an ego use their
  first target instead.

Rotation augmentation multiplies ``R`` by a further rotation. Scaling (``pos_scale_m``, ``disp_scale_m``)
happens inside the network so that ``Batch`` stays in metres, except with ``speed_unit_m``: then
``p = scale R (p_world - origin)`` with one ``scale`` per scene (see ``ModelConfig``), and ``Batch.to_world``
and ``Batch.metres`` undo it.
"""

from __future__ import annotations

import itertools
from collections.abc import Sequence
from dataclasses import dataclass, fields, replace
from typing import Any

import numpy as np
import torch
from torch import Tensor

from logpipe.errors import LogpipeError
from logpipe.types import NDArrayBool, NDArrayFloat, NDArrayFloat32, NDArrayInt, SceneSample

from .config import SPEED_SCALE_MAX, SPEED_SCALE_MIN, ModelConfig


class SampleError(LogpipeError):
    """A SceneSample does not fit the model (wrong obs_len, raster channels, no current position)."""


@dataclass
class Batch:
    """B scenes with N agents in total, flattened ("agents with scene offsets"), T = obs_len + pred_len.

    Per-agent tensors have N rows, scene by scene in sample order; ``scene``/``slot`` place a row in a
    (B, A_max) grid for the per-scene max-pools, which mask everything that is not a real observed agent.

    Attributes:
        positions: (N, T, 2) float32 model-frame metres (times ``scale``); 0 where ``valid`` is False.
        valid: (N, T) bool, observed (finite) positions.
        active: (N,) bool, observed at the current step ``obs_len - 1`` (only these are decoded).
        target: (N,) bool, the samples' targets that are active.
        ego: (N,) bool, the ego row of its scene (when it is active).
        scene: (N,) int64 scene index of each row.
        slot: (N,) int64 row index within its scene.
        max_agents: A_max, the largest agent count of a scene.
        raster: (B, C, H, W) float32 in [0, 1], or None when no scene has one / the model does not use it.
        has_raster: (B,) bool, whether the scene came with a raster (else its environment feature is 0).
        frame_to_px: (B, 2, 3) float32 affine from model-frame positions to raster pixels (col, row).
        px_per_m: (B,) float32 raster resolution, pixels per world metre.
        origin: (B, 2) float64 world metres of the model-frame origin.
        rotation: (B, 2, 2) float64, model = scale * rotation @ (world - origin).
        scale: (B,) float64 model-frame units per world metre (1 unless ``speed_unit_m`` is set).
        offsets: (B + 1,) row offsets of the scenes.
        obs_len: T_obs.
        sample_targets: per input sample, the rows of its targets in ``target_mask`` order. With
            ``ModelConfig.context_radius_m`` each target is its own scene (``context_scenes``), so the scenes
            are not the input samples.
        sample: (N,) int64 input sample of each row (``scene`` unless scenes are per target), so the noise of a
            sample's rows can be drawn from that sample's own generator (``TrajectoryNet.forward``).
    """

    positions: Tensor
    valid: Tensor
    active: Tensor
    target: Tensor
    ego: Tensor
    scene: Tensor
    slot: Tensor
    max_agents: int
    raster: Tensor | None
    has_raster: Tensor
    frame_to_px: Tensor
    px_per_m: Tensor
    origin: NDArrayFloat
    rotation: NDArrayFloat
    scale: NDArrayFloat
    offsets: NDArrayInt
    obs_len: int
    sample_targets: list[NDArrayInt]
    sample: NDArrayInt

    @property
    def size(self) -> int:
        """B."""
        return len(self.offsets) - 1

    def to(self, device: torch.device | str) -> Batch:
        """This batch with every tensor field on ``device``; the numpy fields (frames, offsets, sample rows) are
        host-side bookkeeping and stay."""
        moved: dict[str, Any] = {f.name: value.to(device) for f in fields(self)
                                 if isinstance(value := getattr(self, f.name), Tensor)}
        return replace(self, **moved)

    def to_world(self, points: Tensor, scene: Tensor) -> NDArrayFloat:
        """Model-frame points (N, ..., 2) of rows in scenes ``scene`` (N,) -> world metres (float64)."""
        p = points.detach().double().cpu().numpy()
        sc = scene.cpu().numpy()
        flat = p.reshape(p.shape[0], -1, 2)
        flat = flat / self.scale[sc][:, None, None]
        world: NDArrayFloat = np.einsum("nji,nkj->nki", self.rotation[sc], flat) + self.origin[sc][:, None, :]
        return world.reshape(p.shape)

    def metres(self, values: Tensor, scene: Tensor) -> Tensor:
        """Model-frame lengths or positions (R, ...) of rows in scenes ``scene`` (R,) in metres (the frame's
        axes and origin kept): what errors are measured in."""
        per_row = torch.from_numpy(self.scale).to(values.device, values.dtype)[scene]
        return values / per_row.view(-1, *([1] * (values.dim() - 1)))


def _rot(theta: float) -> NDArrayFloat:
    c, s = np.cos(theta), np.sin(theta)
    return np.array([[c, -s], [s, c]])


def _padded(sample: SceneSample, steps: int) -> NDArrayFloat:
    """The sample's positions over its first ``steps`` steps, NaN (unobserved) beyond its own length."""
    pos = np.full((len(sample.positions), steps, 2), np.nan)
    have = min(steps, sample.positions.shape[1])
    pos[:, :have] = sample.positions[:, :have]
    return pos


def _window_frame(sample: SceneSample, observed: NDArrayFloat,
                  config: ModelConfig) -> tuple[NDArrayFloat, NDArrayFloat, float]:
    """(origin, R, scale) of the model frame for one sample whose observed positions are ``observed``
    (A, T_obs, 2) (see the module docstring)."""
    origin, rot = _frame(sample, observed, config)
    return origin, rot, _speed_scale(observed, config.speed_unit_m) if config.speed_unit_m else 1.0


def _frame(sample: SceneSample, observed: NDArrayFloat, config: ModelConfig) -> tuple[NDArrayFloat, NDArrayFloat]:
    """(origin, R) of the model frame for one sample whose observed positions are ``observed`` (A, T_obs, 2)."""
    cur = observed.shape[1] - 1
    now = observed[:, cur]
    seen: NDArrayBool = np.all(np.isfinite(now), axis=1)
    if config.frame == "world":
        pick = seen & sample.target_mask.astype(bool)
        if not pick.any():
            pick = seen
        origin = now[pick].mean(axis=0) if pick.any() else np.zeros(2)
        return origin, np.eye(2)
    anchor = sample.ego_index
    if anchor < 0 or not seen[anchor]:
        targets = np.flatnonzero(sample.target_mask.astype(bool) & seen)
        anchor = int(targets[0]) if targets.size else int(np.argmax(seen))
    if not seen[anchor]:
        return np.zeros(2), np.eye(2)
    track = observed[anchor]
    heading = 0.0
    for k in range(cur - 1, -1, -1):  # latest earlier observation that moved (> 1 cm) defines heading
        d = track[cur] - track[k]
        if np.isfinite(d).all() and np.hypot(d[0], d[1]) > 1e-2:
            heading = float(np.arctan2(d[1], d[0]))
            break
    return now[anchor].copy(), _rot(-heading)


def _current_distances(now: NDArrayFloat, seen: NDArrayBool, i: int) -> NDArrayFloat:
    """Distance (metres) from agent ``i`` to every agent at the current step ``now`` (A, 2); inf where unseen."""
    out: NDArrayFloat = np.linalg.norm(np.where(seen[:, None], now - now[i], np.inf), axis=1)
    return out


def neighbour_counts(sample: SceneSample, radius_m: float) -> NDArrayInt:
    """How many other agents observed at the current step are within ``radius_m`` metres of each target of
    ``sample`` observed then (``context_scenes``' neighbourhoods, the ego counted like anyone), in target order."""
    now = sample.positions[:, sample.obs_len - 1]
    seen: NDArrayBool = np.all(np.isfinite(now), axis=1)
    counts = [int(np.sum(_current_distances(now, seen, int(i)) <= radius_m)) - 1
              for i in np.flatnonzero(sample.target_mask & seen)]
    return np.array(counts, np.int64)


def context_scenes(sample: SceneSample, radius_m: float, max_neighbours: int | None = None) -> list[SceneSample]:
    """One scene per target of ``sample``, in ``target_mask`` order (``ModelConfig.context_radius_m``): the
    target (the scene's only target), the other agents observed at the current step within ``radius_m``
    metres of it (the ``max_neighbours`` nearest of them when given; ties by row), and the ego. A target
    unobserved at the current step gets a scene of its own alone."""
    now = sample.positions[:, sample.obs_len - 1]
    seen: NDArrayBool = np.all(np.isfinite(now), axis=1)
    ego = sample.ego_index if 0 <= sample.ego_index < len(now) else -1
    scenes = []
    for i in np.flatnonzero(sample.target_mask):
        keep = np.zeros(len(now), bool)
        if seen[i]:
            dist = _current_distances(now, seen, int(i))
            keep = dist <= radius_m
            keep[i] = False
            if max_neighbours is not None and keep.sum() > max_neighbours:
                near = np.flatnonzero(keep)[np.argsort(dist[keep], kind="stable")[:max_neighbours]]
                keep[:] = False
                keep[near] = True
            if ego >= 0:
                keep[ego] = True
        keep[i] = True
        rows = np.flatnonzero(keep)
        scenes.append(replace(
            sample, positions=sample.positions[rows], track_ids=[sample.track_ids[j] for j in rows],
            object_types=sample.object_types[rows], target_mask=rows == i,
            ego_index=int(np.searchsorted(rows, ego)) if ego >= 0 and keep[ego] else -1))
    return scenes


def collate(
    samples: Sequence[SceneSample],
    config: ModelConfig,
    *,
    rotations: Sequence[float] | None = None,
    with_raster: bool | None = None,
    frames: Sequence[tuple[NDArrayFloat, NDArrayFloat, float]] | None = None,
) -> Batch:
    """Pad and normalise ``samples`` into one ``Batch``.

    Args:
        samples: scenes with ``obs_len == config.obs_len``; positions beyond ``obs_len + pred_len`` steps
            are cut, missing steps are padded as unobserved.
        config: supplies obs/pred lengths, frame and raster channels.
        rotations: optional extra rotation (radians, counter-clockwise) per scene (augmentation).
        with_raster: build the raster tensor (default: when the environment feature is on).
        frames: (origin, R, scale) per sample instead of its own (``_window_frame``), before ``rotations``.
    """
    if not samples:
        raise SampleError("cannot build a batch from zero samples")
    for s in samples:
        if s.obs_len != config.obs_len:
            raise SampleError(f"{s.sample_id}: obs_len {s.obs_len} but the model expects {config.obs_len}")
    if config.pools_context:
        # Only the pools of eqs. 2 and 4 read other agents: without them the windows are collated as they are.
        return _collate_in_context(samples, config, rotations, with_raster)
    t_total = config.obs_len + config.pred_len
    counts = np.array([len(s.positions) for s in samples], np.int64)
    offsets = np.concatenate(([0], np.cumsum(counts)))
    use_raster = config.features.environment if with_raster is None else with_raster
    raster_shape = (len(samples), config.raster_channels, *_raster_hw(samples)) if use_raster else None
    buffers = _Buffers.zeros(int(offsets[-1]), len(samples), t_total, raster_shape)
    for i, s in enumerate(samples):
        lo, hi = int(offsets[i]), int(offsets[i + 1])
        pos = _padded(s, t_total)
        org, rot, k = _window_frame(s, pos[:, : config.obs_len], config) if frames is None else frames[i]
        if rotations is not None:
            rot = _rot(rotations[i]) @ rot
        buffers.put_agents(lo, hi, s, pos, (org, rot, k))
        buffers.put_frame(i, s, (org, rot, k))
        buffers.put_raster(i, s, config.raster_channels)
    return buffers.batch(samples, counts, offsets, config.obs_len)


@dataclass
class _Buffers:
    """The host-side arrays ``collate`` fills scene by scene before wrapping them as tensors (shapes, units and
    frames as the ``Batch`` fields of the same names; ``raster`` None when not built)."""

    positions: NDArrayFloat32
    valid: NDArrayBool
    target: NDArrayBool
    ego: NDArrayBool
    has_raster: NDArrayBool
    frame_to_px: NDArrayFloat32
    px_per_m: NDArrayFloat32
    origin: NDArrayFloat
    rotation: NDArrayFloat
    scale: NDArrayFloat
    raster: NDArrayFloat32 | None

    @classmethod
    def zeros(cls, n: int, b: int, t_total: int, raster_shape: tuple[int, int, int, int] | None) -> _Buffers:
        """Empty buffers for ``n`` agent rows of ``b`` scenes over ``t_total`` steps (unit scale and px/m)."""
        return cls(
            positions=np.zeros((n, t_total, 2), np.float32), valid=np.zeros((n, t_total), bool),
            target=np.zeros(n, bool), ego=np.zeros(n, bool), has_raster=np.zeros(b, bool),
            frame_to_px=np.zeros((b, 2, 3), np.float32), px_per_m=np.ones(b, np.float32),
            origin=np.zeros((b, 2)), rotation=np.zeros((b, 2, 2)), scale=np.ones(b),
            raster=None if raster_shape is None else np.zeros(raster_shape, np.float32),
        )

    def put_agents(self, lo: int, hi: int, s: SceneSample, pos: NDArrayFloat,
                   frame: tuple[NDArrayFloat, NDArrayFloat, float]) -> None:
        """Rows ``lo:hi``: the scene's world positions ``pos`` (A, T, 2, NaN unobserved) in the model frame
        ``frame`` (origin, R, scale), 0 where unobserved; its targets and ego."""
        org, rot, k = frame
        ok = np.isfinite(pos[..., 0]) & np.isfinite(pos[..., 1])
        local = k * np.einsum("ij,atj->ati", rot, np.nan_to_num(pos - org))
        self.positions[lo:hi] = np.where(ok[..., None], local, 0.0)
        self.valid[lo:hi] = ok
        self.target[lo:hi] = s.target_mask.astype(bool)
        if 0 <= s.ego_index < hi - lo:
            self.ego[lo + s.ego_index] = True

    def put_frame(self, i: int, s: SceneSample, frame: tuple[NDArrayFloat, NDArrayFloat, float]) -> None:
        """Scene ``i``'s model frame (origin, R, scale) and, with a raster transform, model frame → pixels."""
        org, rot, k = frame
        self.origin[i], self.rotation[i], self.scale[i] = org, rot, k
        if s.world_to_raster is not None:
            w2r = np.asarray(s.world_to_raster, np.float64)
            lin = w2r[:, :2]
            # px = lin (R^T p / k + origin) + offset
            self.frame_to_px[i, :, :2] = lin @ rot.T / k
            self.frame_to_px[i, :, 2] = lin @ org + w2r[:, 2]
            self.px_per_m[i] = np.sqrt(abs(np.linalg.det(lin)))

    def put_raster(self, i: int, s: SceneSample, channels: int) -> None:
        """Scene ``i``'s raster scaled to [0, 1], when rasters are built and the scene has one.

        Raises:
            SampleError: the raster has other than ``channels`` channels, or no ``world_to_raster``.
        """
        if self.raster is None or s.raster is None:
            return
        if s.raster.shape[0] != channels:
            raise SampleError(f"{s.sample_id}: raster has {s.raster.shape[0]} channels, model expects {channels}")
        if s.world_to_raster is None:
            raise SampleError(f"{s.sample_id}: raster without world_to_raster")
        self.raster[i] = s.raster.astype(np.float32) * (1.0 / 255.0)
        self.has_raster[i] = True

    def batch(self, samples: Sequence[SceneSample], counts: NDArrayInt, offsets: NDArrayInt, obs_len: int) -> Batch:
        """The filled buffers as a ``Batch`` of ``samples`` (``counts`` agents per scene, row ``offsets``)."""
        active = self.valid[:, obs_len - 1]
        # No scene has a map: skip the backbone, the environment feature is zero.
        raster = self.raster if self.raster is not None and self.has_raster.any() else None
        b, n = len(samples), int(offsets[-1])
        scene = np.repeat(np.arange(b), counts)
        slot = np.arange(n) - offsets[scene]
        return Batch(
            positions=torch.from_numpy(self.positions),
            valid=torch.from_numpy(self.valid),
            active=torch.from_numpy(active),
            target=torch.from_numpy(self.target & active),
            ego=torch.from_numpy(self.ego & active),
            scene=torch.from_numpy(scene),
            slot=torch.from_numpy(slot),
            max_agents=int(counts.max()),
            raster=None if raster is None else torch.from_numpy(raster),
            has_raster=torch.from_numpy(self.has_raster),
            frame_to_px=torch.from_numpy(self.frame_to_px),
            px_per_m=torch.from_numpy(self.px_per_m),
            origin=self.origin,
            rotation=self.rotation,
            scale=self.scale,
            offsets=offsets,
            obs_len=obs_len,
            sample_targets=[lo + np.flatnonzero(s.target_mask) for lo, s in zip(offsets[:-1], samples, strict=True)],
            sample=scene,
        )


def _collate_in_context(samples: Sequence[SceneSample], config: ModelConfig, rotations: Sequence[float] | None,
                        with_raster: bool | None) -> Batch:
    """``collate`` with each target in its own scene (``context_scenes``) seen in its sample's model frame (origin,
    axes, speed scale and rotation), so only the agents the interaction features pool differ."""
    assert config.context_radius_m is not None
    plain = replace(config, context_radius_m=None)
    parts = [context_scenes(s, config.context_radius_m, config.context_max_neighbours) for s in samples]
    scenes = [scene for part in parts for scene in part]
    if not scenes:  # nothing to predict: the samples as they are
        return collate(samples, plain, rotations=rotations, with_raster=with_raster)
    frames = [_window_frame(s, _padded(s, config.obs_len), config) for s in samples]
    turns = None if rotations is None else [r for r, part in zip(rotations, parts, strict=True) for _ in part]
    scene_frames = [f for f, part in zip(frames, parts, strict=True) for _ in part]
    if config.context_origin == "target":  # the window's axes and scale about the target's current position
        now = config.obs_len - 1
        here = [sc.positions[int(np.argmax(sc.target_mask)), now] for sc in scenes]
        scene_frames = [
            (p if np.isfinite(p).all() else org, rot, k)  # a target unseen now keeps the window's origin
            for p, (org, rot, k) in zip(here, scene_frames, strict=True)
        ]
    batch = collate(scenes, plain, rotations=turns, with_raster=with_raster, frames=scene_frames)
    own = [int(rows[0]) for rows in batch.sample_targets]  # a target's scene has that one target
    firsts = np.cumsum([0] + [len(part) for part in parts])
    batch.sample_targets = [np.array(own[lo:hi], np.int64) for lo, hi in itertools.pairwise(firsts)]
    batch.sample = np.repeat(np.arange(len(parts)), [len(part) for part in parts])[batch.scene.numpy()]
    return batch


def _speed_scale(observed: NDArrayFloat, unit_m: float) -> float:
    """``clip(unit_m / u, SPEED_SCALE_MIN, SPEED_SCALE_MAX)``, u the mean length (metres) of the one-step
    displacements in ``observed`` (A, T_obs, 2, NaN where unobserved); the largest scale without any."""
    steps = np.linalg.norm(np.diff(observed, axis=1), axis=-1)
    steps = steps[np.isfinite(steps)]
    mean = float(steps.mean()) if steps.size else 0.0
    return float(np.clip(unit_m / mean, SPEED_SCALE_MIN, SPEED_SCALE_MAX)) if mean > 0 else SPEED_SCALE_MAX


def _raster_hw(samples: Sequence[SceneSample]) -> tuple[int, int]:
    shapes = {tuple(s.raster.shape[1:]) for s in samples if s.raster is not None}
    if len(shapes) > 1:
        raise SampleError(f"rasters of different sizes in one batch: {sorted(shapes)}")
    if not shapes:
        return (1, 1)  # no scene has a map; collate drops the raster
    h, w = shapes.pop()
    return int(h), int(w)
