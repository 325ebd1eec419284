"""The Foxglove ``SceneUpdate`` of one prediction sample (predict's MCAPs): per target its observed history
(grey), the true future where the log has it (green), a sphere at its current position (its type's colour) and
the K modes (blue, more opaque the higher their score), living for the horizon. Positions are metres in the
log's world frame, snapped to ``foxglove.POSITION_QUANTUM``; times are ns on the log's clock.
"""

from __future__ import annotations

from functools import cache

import numpy as np
from foxglove_schemas_protobuf.Color_pb2 import Color
from foxglove_schemas_protobuf.KeyValuePair_pb2 import KeyValuePair
from foxglove_schemas_protobuf.LinePrimitive_pb2 import LinePrimitive
from foxglove_schemas_protobuf.Point3_pb2 import Point3
from foxglove_schemas_protobuf.Pose_pb2 import Pose
from foxglove_schemas_protobuf.Quaternion_pb2 import Quaternion
from foxglove_schemas_protobuf.SceneEntity_pb2 import SceneEntity
from foxglove_schemas_protobuf.SceneUpdate_pb2 import SceneUpdate
from foxglove_schemas_protobuf.SpherePrimitive_pb2 import SpherePrimitive
from foxglove_schemas_protobuf.Vector3_pb2 import Vector3
from google.protobuf.duration_pb2 import Duration

from logpipe.mcap.foxglove import AGENT_SHAPES, POSITION_QUANTUM, TYPE_COLOURS, rgba, snap, timestamp
from logpipe.mcap.protobuf_splice import Template, field_key, serialize, varint
from logpipe.types import OBJECT_TYPES, NDArrayFloat, NDArrayInt, SceneSample

HISTORY_RGBA = (0.6, 0.6, 0.6, 0.9)
"""Colour of a forecast target's observed history (RGBA 0..1)."""
TRUTH_RGBA = (0.1, 0.85, 0.25, 1.0)
"""Colour of its true future."""
MODE_RGB = (0.2, 0.45, 1.0)
"""Colour of its modes; opacity 0.25..1 by score relative to its best mode."""
_LINE_Z = 0.05  # metres above the ground, so lines are not hidden in a raster drawn at z = 0


@cache
def _point_template() -> Template:
    # A line's point record (z = 0 is not written); the line's pose lifts the whole line.
    return Template(lambda v: LinePrimitive(points=[Point3(x=v[0], y=v[1])]), 2)


@cache
def _line_head(thickness: float) -> bytes:
    return serialize(LinePrimitive(type=LinePrimitive.LINE_STRIP, thickness=thickness,
                                    pose=Pose(position=Vector3(z=_LINE_Z), orientation=Quaternion(w=1.0))))


@cache
def _line_colour(rgba: tuple[float, float, float, float]) -> bytes:
    return serialize(LinePrimitive(color=Color(r=rgba[0], g=rgba[1], b=rgba[2], a=rgba[3])))


def forecast_scene_update(frame: str, now_ns: int, lifetime_ns: int, sample: SceneSample, targets: NDArrayInt,
                          futures: NDArrayFloat, scores: NDArrayFloat) -> bytes:
    """A serialized ``foxglove.SceneUpdate`` of one sample's forecasts: an entity per target (id = track id, so
    the next sample's replaces it; living ``lifetime_ns``) in ``frame`` with its observed history, its true
    future where ``sample`` has one (finite positions after ``obs_len``), a sphere at its current position and
    one line per mode, more opaque the higher its score (relative to the target's best); metres.

    Args:
        targets: (N,) rows of ``sample.positions``; futures: (N, K, T, 2) metres; scores: (N, K).
    """
    obs = sample.obs_len
    n, k, t = futures.shape[:3]
    current = sample.positions[targets, obs - 1]  # (N, 2)
    modes = np.empty((n, k, t + 1, 2))
    modes[:, :, 0] = current[:, None]
    modes[:, :, 1:] = futures
    segments: list[NDArrayFloat] = []
    lines: list[tuple[int, bytes, bytes]] = []  # (points, head, colour) per line, in entity order
    history_style = (_line_head(0.05), _line_colour(HISTORY_RGBA))
    truth_style = (_line_head(0.1), _line_colour(TRUTH_RGBA))
    top = np.maximum(scores.max(axis=1, keepdims=True), 1e-12) if k else np.ones((n, 1))
    alpha = np.rint(100 * (0.25 + 0.75 * np.clip(scores / top, 0.0, 1.0))).astype(np.int64)  # 1% steps
    per_target: list[int] = []
    for j, row in enumerate(targets.tolist()):
        count = 0
        history = sample.positions[row, :obs]
        history = history[np.isfinite(history).all(axis=1)]
        if len(history) >= 2:
            segments.append(history)
            lines.append((len(history), *history_style))
            count += 1
        future = sample.positions[row, obs:]
        future = future[np.isfinite(future).all(axis=1)]
        if len(future):
            truth = np.concatenate([current[j : j + 1], future])
            segments.append(truth)
            lines.append((len(truth), *truth_style))
            count += 1
        segments.append(modes[j].reshape(k * (t + 1), 2))
        for m in range(k):
            lines.append((t + 1, _line_head(0.08), _line_colour((*MODE_RGB, alpha[j, m] / 100))))
        per_target.append(count + k)
    points = snap(np.concatenate(segments), POSITION_QUANTUM) if segments else np.zeros((0, 2))
    blob = _point_template().fill([points[:, 0], points[:, 1]]).tobytes()
    size = _point_template().size
    key_lines, key_entities = field_key(SceneEntity.LINES_FIELD_NUMBER), field_key(SceneUpdate.ENTITIES_FIELD_NUMBER)
    life = Duration(seconds=max(lifetime_ns, 0) // 1_000_000_000, nanos=max(lifetime_ns, 0) % 1_000_000_000)
    stamp = timestamp(now_ns)
    entities = []
    at, line = 0, 0
    for j, row in enumerate(targets.tolist()):
        object_type = OBJECT_TYPES[int(sample.object_types[row])]
        name = sample.track_ids[row]
        cx, cy = (float(v) for v in snap(current[j], POSITION_QUANTUM))
        diameter = max(0.6 * AGENT_SHAPES.get(object_type, AGENT_SHAPES["unknown"])[1], 0.5)
        parts = [serialize(SceneEntity(
            timestamp=stamp, frame_id=frame, id=name, lifetime=life,
            metadata=[KeyValuePair(key="sample_id", value=sample.sample_id), KeyValuePair(key="track_id", value=name),
                      KeyValuePair(key="object_type", value=object_type)],
            spheres=[SpherePrimitive(pose=Pose(position=Vector3(x=cx, y=cy, z=_LINE_Z), orientation=Quaternion(w=1)),
                                     size=Vector3(x=diameter, y=diameter, z=diameter),
                                     color=rgba(TYPE_COLOURS.get(object_type, TYPE_COLOURS["unknown"]), 1.0))]))]
        for _ in range(per_target[j]):
            count, head, colour = lines[line]
            body = head + blob[at * size : (at + count) * size] + colour
            parts += (key_lines, varint(len(body)), body)
            at += count
            line += 1
        entity = b"".join(parts)
        entities.append(key_entities + varint(len(entity)) + entity)
    return b"".join(entities)
