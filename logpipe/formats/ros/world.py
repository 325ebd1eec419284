"""Observations of every topic placed in the log's world frame, and the canonical track rows they give.

The world frame is the log's fixed frame (``map``/``odom``/``world``): the mapping's, else the ego's. Each
observation is moved from its header frame with the tf tree at its own stamp; rows are then resampled per track.
Units: metres, radians (CCW from +x), m/s, nanoseconds.
"""

from __future__ import annotations

from collections import defaultdict
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import pyarrow as pa

from logpipe.dataset.resample import ResampleSpec, resample_track
from logpipe.formats.base import conform_tracks
from logpipe.formats.ros.mapping import EgoSpec, Mapping
from logpipe.formats.ros.messages import NAN2, NAN3, Pose, TopicExtractor, clean_frame
from logpipe.formats.ros.tf import TfBuffer
from logpipe.geometry import normalize_quat, quat_mul, quat_rotate, quat_yaw
from logpipe.types import NDArrayFloat, NDArrayInt


@dataclass
class WorldTracks:
    """Observations of every source in the world frame, as flat arrays (one row per observation).

    Attributes:
        t: ns; x, y: m (world); heading: rad (world); vx, vy: m/s (world, NaN unknown); length, width: m.
        track, role, object_type, source_type: per-row identity.
        dropped: rows dropped per topic because their frame could not be placed in the world frame then.
    """

    t: NDArrayInt
    x: NDArrayFloat
    y: NDArrayFloat
    heading: NDArrayFloat
    vx: NDArrayFloat
    vy: NDArrayFloat
    length: NDArrayFloat
    width: NDArrayFloat
    track: list[str]
    role: list[str]
    object_type: list[str]
    source_type: list[str]
    dropped: dict[str, int]


class FrameError(ValueError):
    """A topic's frame cannot be placed in the world frame."""

    def __init__(self, topic: str, reason: str) -> None:
        self.topic = topic
        self.reason = reason
        super().__init__(reason)


def world_frame_for(mapping: Mapping, extractors: Sequence[TopicExtractor], tf: TfBuffer) -> str:
    """The world frame: the mapping's, else the ego's frame (tf parent / header frame), else the objects' root."""
    if mapping.world_frame:
        return clean_frame(mapping.world_frame)
    if mapping.ego is not None and mapping.ego.tf is not None:
        return clean_frame(mapping.ego.tf[0])
    for ex in extractors:
        if ex.role == "ego" and len(ex.obs):
            return ex.obs.frames[0]
    for ex in extractors:
        if len(ex.obs) and ex.obs.frames[0]:
            return tf.root(ex.obs.frames[0]) if ex.obs.frames[0] in tf.frames() else ex.obs.frames[0]
    return ""


def ego_from_tf(spec: EgoSpec, tf: TfBuffer, source_type: str) -> TopicExtractor:
    """An ego extractor filled from the tf pair ``spec.tf`` (sampled at the stamps of its moving edges)."""
    assert spec.tf is not None
    parent, child = (clean_frame(f) for f in spec.tf)
    if child not in tf.edges or not tf.can_transform(parent, child):
        known = ", ".join(f"{p}->{c}" for p, c in tf.dynamic_edges()) or "none"
        raise FrameError("/tf", f"no tf path from {parent!r} to {child!r} (moving edges: {known})")
    chain = tf.chain(child)
    moving = [c for c in chain[: chain.index(parent)] if not tf.edges[c].static] if parent in chain else []
    moving = moving or [c for c in chain[:-1] if not tf.edges[c].static]
    times = tf.edge_times(moving[0]) if moving else tf.edge_times(child)
    p, q = tf.lookup(parent, child, times)
    ex = TopicExtractor("/tf", source_type, "ego", spec, True, kind="tf_ego")
    ex.child_frames = {child}
    ex.messages = len(times)
    ok = np.isfinite(p[:, 0])
    for ti, pi, qi in zip(times[ok].tolist(), p[ok].tolist(), q[ok].tolist(), strict=True):
        pose = Pose(pi[0], pi[1], pi[2], qi[0], qi[1], qi[2], qi[3])
        ex.obs.add(ti, spec.track_id, parent, pose, NAN3, NAN2, spec.object_type, source_type)
    return ex


def to_world(extractors: Sequence[TopicExtractor], tf: TfBuffer, world: str, ego_frame: str | None) -> WorldTracks:
    """Every extractor's observations in ``world`` (frame ``""`` counts as the world frame).

    The ego track (if any) is added to ``tf`` as the edge ``world → ego_frame`` first, so that objects given in
    the vehicle frame are placed with the ego pose at their own timestamps.

    Raises:
        FrameError: a topic's frame has no path to the world frame.
    """
    ego = next((ex for ex in extractors if ex.role == "ego" and len(ex.obs)), None)
    if ego is not None and ego_frame and ego.obs.frames[0] in ("", world):
        tf.add_track(
            world, ego_frame, np.asarray(ego.obs.t, dtype=np.int64),
            np.asarray(ego.obs.pos, dtype=np.float64), np.asarray(ego.obs.quat, dtype=np.float64),
        )  # fmt: skip
    cols: dict[str, list[Any]] = defaultdict(list)
    dropped: dict[str, int] = {}
    for ex in extractors:
        o = ex.obs
        n = len(o)
        if not n:
            continue
        t = np.asarray(o.t, dtype=np.int64)
        pos = np.asarray(o.pos, dtype=np.float64)
        quat = normalize_quat(np.asarray(o.quat, dtype=np.float64))
        vel = np.asarray(o.vel, dtype=np.float64)
        frames = np.asarray(o.frames, dtype=object)
        ok = np.ones(n, dtype=bool)
        for frame in set(o.frames):
            if frame in ("", world):
                continue
            if not tf.can_transform(world, frame):
                raise FrameError(
                    ex.topic,
                    f"frame {frame!r} cannot be placed in the world frame {world!r}: no tf path"
                    + (f" and it is not the ego frame {ego_frame!r}" if ego_frame else "")
                    + " (set world_frame or ego in the mapping)",
                )
            rows = np.flatnonzero(frames == frame)
            tp, tq = tf.lookup(world, frame, t[rows])
            pos[rows] = quat_rotate(tq, pos[rows]) + tp
            if not o.v_body:
                vel[rows] = quat_rotate(tq, vel[rows])
            quat[rows] = quat_mul(tq, quat[rows])
            ok[rows] &= np.isfinite(tp[:, 0])
        if o.v_body:
            vel = quat_rotate(quat, vel)
        if not ok.all():
            dropped[ex.topic] = dropped.get(ex.topic, 0) + int((~ok).sum())
        idx = np.flatnonzero(ok)
        sizes = np.asarray(o.size, dtype=np.float64)[idx]
        cols["t"].append(t[idx])
        cols["x"].append(pos[idx, 0])
        cols["y"].append(pos[idx, 1])
        cols["heading"].append(quat_yaw(quat[idx]))
        cols["vx"].append(vel[idx, 0])
        cols["vy"].append(vel[idx, 1])
        cols["length"].append(sizes[:, 0])
        cols["width"].append(sizes[:, 1])
        sel = idx.tolist()
        cols["track"].extend(o.track[i] for i in sel)
        cols["role"].extend([ex.role] * len(sel))
        cols["object_type"].extend(o.object_type[i] for i in sel)
        cols["source_type"].extend(o.source_type[i] for i in sel)

    def cat(name: str, dtype: type) -> Any:
        return np.concatenate(cols[name]).astype(dtype) if cols[name] else np.zeros(0, dtype=dtype)

    return WorldTracks(
        t=cat("t", np.int64), x=cat("x", np.float64), y=cat("y", np.float64),
        heading=cat("heading", np.float64), vx=cat("vx", np.float64), vy=cat("vy", np.float64),
        length=cat("length", np.float64), width=cat("width", np.float64),
        track=list(cols["track"]), role=list(cols["role"]), object_type=list(cols["object_type"]),
        source_type=list(cols["source_type"]), dropped=dropped,
    )  # fmt: skip


# --- track table ---------------------------------------------------------------------------------------


def world_to_table(log_id: str, wt: WorldTracks, spec: ResampleSpec | None) -> pa.Table:
    """Rows of the canonical track table (without ``step``) for one log, resampled per track when ``spec``."""
    n = len(wt.t)
    if spec is None or n == 0:
        table = pa.table(
            {
                "log_id": pa.array([log_id] * n, pa.string()),
                "timestamp_ns": wt.t, "track_id": wt.track, "object_type": wt.object_type, "role": wt.role,
                "x": wt.x, "y": wt.y, "heading": _nulls(wt.heading), "vx": _nulls(wt.vx), "vy": _nulls(wt.vy),
                "length": _nulls(wt.length), "width": _nulls(wt.width), "source_type": wt.source_type,
            }
        )  # fmt: skip
        return conform_tracks(table)
    track = np.asarray(wt.track, dtype=object)
    order = np.argsort(track, kind="stable")
    bounds = np.flatnonzero(track[order][1:] != track[order][:-1]) + 1
    parts: dict[str, list[Any]] = defaultdict(list)
    for rows in np.split(order, bounds):
        values = {
            "x": wt.x[rows], "y": wt.y[rows], "heading": wt.heading[rows], "vx": wt.vx[rows],
            "vy": wt.vy[rows], "length": wt.length[rows], "width": wt.width[rows],
        }  # fmt: skip
        grid, res = resample_track(wt.t[rows], values, spec)
        if not len(grid):
            continue
        # class/role/source type of the nearest source sample at or before each grid time
        src_t = np.sort(wt.t[rows], kind="stable")
        src_rows = rows[np.argsort(wt.t[rows], kind="stable")]
        at = src_rows[np.clip(np.searchsorted(src_t, grid, side="right") - 1, 0, len(rows) - 1)]
        parts["timestamp_ns"].append(grid)
        for k, v in res.items():
            parts[k].append(v)
        for k, src in (("track_id", wt.track), ("role", wt.role), ("object_type", wt.object_type),
                       ("source_type", wt.source_type)):  # fmt: skip
            parts[k].extend(src[i] for i in at.tolist())
    if not parts:
        return world_to_table(log_id, _empty_world(), None)
    total = sum(len(g) for g in parts["timestamp_ns"])
    table = pa.table(
        {
            "log_id": pa.array([log_id] * total, pa.string()),
            "timestamp_ns": np.concatenate(parts["timestamp_ns"]),
            "track_id": parts["track_id"], "object_type": parts["object_type"], "role": parts["role"],
            **{k: _nulls(np.concatenate(parts[k])) for k in ("x", "y", "heading", "vx", "vy", "length", "width")},
            "source_type": parts["source_type"],
        }
    )  # fmt: skip
    return conform_tracks(table)


def _nulls(v: NDArrayFloat) -> pa.Array:
    """Float column with NaN as null."""
    return pa.array(v, type=pa.float64(), from_pandas=True)


def _empty_world() -> WorldTracks:
    z = np.zeros(0)
    return WorldTracks(np.zeros(0, dtype=np.int64), z, z, z, z, z, z, z, [], [], [], [], {})

