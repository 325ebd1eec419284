"""The Foxglove ``SceneUpdate`` of one prediction sample (predict's MCAPs): per target its observed history
(grey), the true future where the log has it (orange; the raster's lanes are green), a sphere at its current
position (its type's colour) and the K modes (blue, more opaque the higher their score), living for the horizon.
Positions are metres in the log's world frame, snapped to ``foxglove.POSITION_QUANTUM``; times are ns on the
log's clock. ``legend_scene`` is the legend entity naming these colours.
"""

from __future__ import annotations

import itertools
from collections.abc import Sequence
from dataclasses import dataclass, replace
from functools import cache, lru_cache

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
from foxglove_schemas_protobuf.TextPrimitive_pb2 import TextPrimitive
from foxglove_schemas_protobuf.Vector3_pb2 import Vector3

from logpipe.mcap.foxglove import AGENT_SHAPES, POSITION_QUANTUM, TYPE_COLOURS, rgba, snap, stamp_table, timestamp
from logpipe.mcap.protobuf_splice import (
    ByteTable,
    Template,
    concatenated,
    field_key,
    put_doubles,
    serialize,
    timestamps,
    varint,
)
from logpipe.types import OBJECT_TYPES, NDArrayByte, NDArrayFloat, NDArrayInt, SceneSample

HISTORY_RGBA = (0.6, 0.6, 0.6, 0.9)
"""Colour of a forecast target's observed history (RGBA 0..1)."""
TRUTH_RGBA = (1.0, 0.5, 0.0, 1.0)
"""Colour of its true future: orange, apart from the raster's green lanes, red drivable area and blue boundaries."""
MODE_RGB = (0.2, 0.45, 1.0)
"""Colour of its modes; opacity 0.25..1 by score relative to its best mode."""
LANES_RGBA = (0.0, 1.0, 0.0, 1.0)
"""The raster's lane colour (``raster_image.raster_rgb``: green), as the legend shows it."""
LEGEND = (("history", HISTORY_RGBA), ("truth", TRUTH_RGBA), ("forecasts", (*MODE_RGB, 1.0)), ("lanes", LANES_RGBA))
"""The legend's lines: what each colour of a prediction scene means."""
_LINE_Z = 0.05  # metres above the ground, so lines are not hidden in a raster drawn at z = 0
_LINES_KEY = field_key(SceneEntity.LINES_FIELD_NUMBER)
_METADATA_KEY = field_key(SceneEntity.METADATA_FIELD_NUMBER)
_ENTITIES_KEY = field_key(SceneUpdate.ENTITIES_FIELD_NUMBER)
_STAMP_KEY = field_key(SceneEntity.TIMESTAMP_FIELD_NUMBER)
_LIFETIME_KEY = field_key(SceneEntity.LIFETIME_FIELD_NUMBER)
_varint = lru_cache(maxsize=1 << 12)(varint)  # record lengths recur


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


@dataclass(frozen=True)
class TargetForecasts:
    """Consecutive samples' predicted targets, what a prediction MCAP draws and records of them, concatenated
    sample by sample (metres in the log's world frame).

    Attributes:
        sample_ids: (S,) the samples' ids; ``bounds``: (S + 1,) sample s's targets are rows
            ``bounds[s]:bounds[s + 1]`` of the arrays below.
        track_ids, object_types: (N,) the targets' ids and class names.
        history: (N, T_obs, 2) observed positions (the last is the current one); ``truth``: (N, T_fut, 2) the
            window's positions after them; both NaN where unobserved.
        futures: (N, K, T_pred, 2) forecasts; ``scores``: (N, K) mode scores.
    """

    sample_ids: Sequence[str]
    bounds: Sequence[int]
    track_ids: Sequence[str]
    object_types: Sequence[str]
    history: NDArrayFloat
    truth: NDArrayFloat
    futures: NDArrayFloat
    scores: NDArrayFloat
    columns: dict[str, NDArrayFloat] | None = None
    """The ``logpipe.Predictions`` arrays (``current_x``, ``current_y``, ``score``, ``x``, ``y``) made C-contiguous
    once for all the samples (``with_columns``), so a sample's are row slices orjson takes as they are."""

    def with_columns(self) -> TargetForecasts:
        """These forecasts with ``columns`` filled."""
        return replace(self, columns=self.arrays())

    def arrays(self) -> dict[str, NDArrayFloat]:
        """``columns``, made now where they were not."""
        if self.columns is not None:
            return self.columns
        current = self.history[:, -1]
        columns = {"current_x": current[:, 0], "current_y": current[:, 1], "score": self.scores,
                   "x": self.futures[..., 0], "y": self.futures[..., 1]}
        return {k: _contiguous(v) for k, v in columns.items()}

    @classmethod
    def of_sample(cls, sample: SceneSample, targets: NDArrayInt, futures: NDArrayFloat,
                  scores: NDArrayFloat) -> TargetForecasts:
        """One sample's: the ``targets`` rows of ``sample.positions`` and their forecasts."""
        obs = sample.obs_len
        return cls([sample.sample_id], [0, len(targets)], [sample.track_ids[i] for i in targets],
                   [OBJECT_TYPES[int(sample.object_types[i])] for i in targets], sample.positions[targets, :obs],
                   sample.positions[targets, obs:], futures, scores)

    def part(self, first: int, stop: int) -> TargetForecasts:
        """Samples ``first`` .. ``stop - 1`` (views of the arrays)."""
        a, b = self.bounds[first], self.bounds[stop]
        return TargetForecasts(self.sample_ids[first:stop], [i - a for i in self.bounds[first : stop + 1]],
                               self.track_ids[a:b], self.object_types[a:b], self.history[a:b], self.truth[a:b],
                               self.futures[a:b], self.scores[a:b],
                               None if self.columns is None else {k: v[a:b] for k, v in self.columns.items()})


def _contiguous(values: NDArrayFloat) -> NDArrayFloat:
    """``values`` C-contiguous; except forecasts whose K modes are one mode broadcast (constant velocity's), which
    stay broadcast over a contiguous copy of that mode, so the ``logpipe.Predictions`` JSON formats it once
    (``prediction.mcap_logs.array_json``) instead of copying and formatting it K times."""
    if values.ndim == 3 and values.shape[1] > 1 and values.strides[1] == 0:
        one: NDArrayFloat = np.broadcast_to(np.ascontiguousarray(values[:, :1]), values.shape)
        return one
    return np.ascontiguousarray(values)


def forecast_scene_updates(forecasts: TargetForecasts, frames: Sequence[str], now_ns: Sequence[int],
                           lifetimes_ns: Sequence[int]) -> list[bytes]:
    """A serialized ``foxglove.SceneUpdate`` per sample of ``forecasts`` (in ``frames``, at ``now_ns``, living
    ``lifetimes_ns``: one each per sample): an entity per target (id = track id, so the next sample's replaces it)
    with its observed history, its true future where it has one (finite positions), a sphere at its current
    position (the last observed step) and one line per mode, more opaque the higher its score (relative to the
    target's best); metres.

    Built from parts (``logpipe.mcap.protobuf_splice``) by numpy for all the samples at once: what a sample's
    entities share and what a track's share encoded once, every target's sphere, observed lines and K mode lines
    filled in blocks of equal-width rows, each entity cut out as one bytes object (``concatenated``): no Python
    per target.
    """
    f = forecasts
    n, samples = len(f.futures), len(f.sample_ids)
    if n == 0:
        return [b""] * samples
    bounds = np.asarray(f.bounds, np.int64)
    sample_of = np.repeat(np.arange(samples), np.diff(bounds))
    current = f.history[:, -1]  # (N, 2)
    # What a sample's entities share: timestamp and frame, lifetime, its id (metadata); numpy-encoded times.
    frame_codes: dict[str, int] = {}
    frame_of = np.array([frame_codes.setdefault(name, len(frame_codes)) for name in frames], np.int64)
    each = np.arange(samples)
    stamp_frame = concatenated([
        (concatenated([(stamp_table(np.asarray(now_ns, np.int64)), each)], _STAMP_KEY), each),
        (ByteTable.of_items([_string_field(SceneEntity.FRAME_ID_FIELD_NUMBER, name) for name in frame_codes]),
         frame_of)])
    # A Duration is serialized as a Timestamp is (seconds 1, nanos 2); lifetimes are clipped at 0.
    lives = np.maximum(np.asarray(lifetimes_ns, np.int64), 0)
    lifetime = concatenated([(timestamps(lives), each)], _LIFETIME_KEY)
    sample_pairs = ByteTable.of_items([_uncached_pair("sample_id", sample_id) for sample_id in f.sample_ids])
    # Per target: its id and track_id pair (per distinct id), type pair, sphere, lines.
    names, name_of = np.unique(np.asarray(list(f.track_ids), object), return_inverse=True)
    types, type_of = np.unique(np.asarray(list(f.object_types), object), return_inverse=True)
    history, truth = _observed_lines(f.history, f.truth, current)
    entities, _ = concatenated([
        (stamp_frame, sample_of),
        (ByteTable.of_items([_string_field(SceneEntity.ID_FIELD_NUMBER, str(t)) for t in names]), name_of),
        (lifetime, sample_of), (sample_pairs, sample_of),
        (ByteTable.of_items([_pair("track_id", str(t)) for t in names]), name_of),
        (ByteTable.of_items([_pair("object_type", str(t)) for t in types]), type_of),
        (_spheres(types, type_of, snap(current, POSITION_QUANTUM)), np.arange(n)),
        (history, np.arange(n)), (truth, np.arange(n)),
        (ByteTable.of_rows(n, [(np.arange(n), _mode_lines(current, f.futures, f.scores))]), np.arange(n)),
    ], _ENTITIES_KEY).objects()
    # A join per sample of its entities (joining all and cutting would copy every byte twice).
    rows = entities.tolist()
    return [b"".join(rows[a:b]) for a, b in itertools.pairwise(bounds.tolist())]


def legend_scene(frame: str, now_ns: int, at: tuple[float, float]) -> bytes:
    """A serialized ``SceneUpdate`` with one ``legend`` entity (living until replaced): a line of text per colour
    of the prediction scenes, in that colour, a few metres above ``at`` (x, y metres in ``frame``)."""
    x, y = (float(v) for v in snap(np.asarray(at, np.float64), POSITION_QUANTUM))
    texts = [TextPrimitive(pose=Pose(position=Vector3(x=x, y=y + 8.0 - 1.5 * i, z=1.0), orientation=Quaternion(w=1)),
                           billboard=True, font_size=14.0, scale_invariant=True, text=name,
                           color=Color(r=c[0], g=c[1], b=c[2], a=c[3]))
             for i, (name, c) in enumerate(LEGEND)]
    return serialize(SceneUpdate(entities=[SceneEntity(timestamp=timestamp(now_ns), frame_id=frame, id="legend",
                                                       texts=texts)]))


@lru_cache(maxsize=1 << 16)  # track ids recur in the samples of a log's sliding windows
def _string_field(number: int, text: str) -> bytes:
    """A proto3 string field (left out when empty, as the classes do)."""
    data = text.encode()
    return field_key(number) + _varint(len(data)) + data if data else b""


def _uncached_pair(key: str, value: str) -> bytes:
    """A ``SceneEntity.metadata`` record of one ``KeyValuePair``."""
    data = value.encode()
    pair = _string_field(KeyValuePair.KEY_FIELD_NUMBER, key) + (
        field_key(KeyValuePair.VALUE_FIELD_NUMBER) + _varint(len(data)) + data if data else b"")
    return _METADATA_KEY + _varint(len(pair)) + pair


_pair = lru_cache(maxsize=1 << 16)(_uncached_pair)  # track ids recur in the samples of a log's sliding windows


@cache
def _sphere_template(object_type: str) -> Template:
    # A target's marker: its type's size and colour; the position's x and y vary.
    diameter = max(0.6 * AGENT_SHAPES.get(object_type, AGENT_SHAPES["unknown"])[1], 0.5)
    colour = rgba(TYPE_COLOURS.get(object_type, TYPE_COLOURS["unknown"]), 1.0)
    return Template(lambda v: SceneEntity(spheres=[SpherePrimitive(
        pose=Pose(position=Vector3(x=v[0], y=v[1], z=_LINE_Z), orientation=Quaternion(w=1)),
        size=Vector3(x=diameter, y=diameter, z=diameter), color=colour)]), 2)


def _spheres(types: np.ndarray, type_of: NDArrayInt, at: NDArrayFloat) -> ByteTable:
    """Each target's sphere record at ``at`` (N, 2) metres, its type ``types[type_of]``."""
    blocks = []
    for code, object_type in enumerate(types.tolist()):
        rows = np.flatnonzero(type_of == code)
        blocks.append((rows, _sphere_template(str(object_type)).fill([at[rows, 0], at[rows, 1]])))
    return ByteTable.of_rows(len(type_of), blocks)


def _observed_lines(history: NDArrayFloat, truth: NDArrayFloat, current: NDArrayFloat) -> tuple[ByteTable, ByteTable]:
    """Each target's history line (its finite observed points, when there are 2) and true-future line (the
    current point and the finite future ones, when there are any), as ``SceneEntity.lines`` records."""
    seen = np.asarray(np.isfinite(history).all(axis=2), bool)
    seen &= (seen.sum(axis=1) >= 2)[:, None]
    ahead = np.asarray(np.isfinite(truth).all(axis=2), bool)
    future = np.concatenate([np.asarray(ahead.any(axis=1), bool)[:, None], ahead], axis=1)
    drawn = np.concatenate([current[:, None], truth], axis=1)
    return (_line_records(history[seen], seen.sum(axis=1), 0.05, HISTORY_RGBA),
            _line_records(drawn[future], future.sum(axis=1), 0.1, TRUTH_RGBA))


def _line_records(points: NDArrayFloat, counts: NDArrayInt, thickness: float,
                  colour: tuple[float, float, float, float]) -> ByteTable:
    """A ``SceneEntity.lines`` record per target of its ``counts`` points (consecutive in ``points``; b"" where
    it has none): the records of targets with as many points are one numpy block."""
    snapped = snap(points, POSITION_QUANTUM)
    filled, size = _point_template().fill([snapped[:, 0], snapped[:, 1]]), _point_template().size
    head, tail = np.frombuffer(_line_head(thickness), np.uint8), np.frombuffer(_line_colour(colour), np.uint8)
    starts = np.cumsum(counts) - counts
    blocks = []
    for count in np.unique(counts).tolist():
        rows = np.flatnonzero(counts == count)
        if count == 0:
            blocks.append((rows, np.zeros((len(rows), 0), np.uint8)))
            continue
        key = np.frombuffer(_LINES_KEY + varint(len(head) + count * size + len(tail)), np.uint8)
        block = np.empty((len(rows), len(key) + len(head) + count * size + len(tail)), np.uint8)
        block[:, : len(key)], block[:, len(key) : len(key) + len(head)], block[:, -len(tail) :] = key, head, tail
        block[:, len(key) + len(head) : -len(tail)] = filled[starts[rows][:, None] + np.arange(count)].reshape(
            len(rows), count * size)
        blocks.append((rows, block))
    return ByteTable.of_rows(len(counts), blocks)


def _mode_lines(current: NDArrayFloat, futures: NDArrayFloat, scores: NDArrayFloat) -> NDArrayByte:
    """(N, width) the ``SceneEntity.lines`` records of every target's K modes (each from the current point):
    records of equal length (one head, T + 1 points, a colour of fixed size), so numpy lays them out."""
    n, k, t = futures.shape[:3]
    if n * k == 0:
        return np.zeros((n, 0), np.uint8)
    top = np.maximum(scores.max(axis=1, keepdims=True), 1e-12)
    alpha = np.rint(100 * (0.25 + 0.75 * np.clip(scores / top, 0.0, 1.0))).astype(np.int64)  # 1% steps
    levels, which = np.unique(alpha, return_inverse=True)
    colours = [_line_colour((*MODE_RGB, a / 100)) for a in levels.tolist()]
    if len({len(c) for c in colours}) != 1:  # every channel is nonzero, so every colour has the same fields
        raise RuntimeError("mode colours differ in size")
    template = _point_template()
    head, points_size, colour_size = _line_head(0.08), (t + 1) * template.size, len(colours[0])
    prefix = np.frombuffer(_LINES_KEY + varint(len(head) + points_size + colour_size) + head, np.uint8)
    # The records are written in place (no per-point array filled and then copied in): prefix, points, colour.
    records = np.empty((n * k, len(prefix) + points_size + colour_size), np.uint8)
    records[:, : len(prefix)] = prefix
    points = records[:, len(prefix) : len(prefix) + points_size]
    points.shape = (n * k, t + 1, template.size)  # a view of the records (assigning a shape never copies)
    points[:] = np.frombuffer(template.data, np.uint8)
    for axis, offsets in enumerate(template.offsets):
        values = np.empty((n, k, t + 1))
        values[:, :, 0] = current[:, None, axis]
        values[:, :, 1:] = futures[..., axis]
        raw = snap(values, POSITION_QUANTUM).astype("<f8").reshape(n * k, t + 1, 1)
        for at in offsets:
            put_doubles(points[:, :, at : at + 8], raw)
    records[:, len(prefix) + points_size :] = np.frombuffer(b"".join(colours), np.uint8).reshape(
        len(colours), -1)[which.ravel()]
    return records.reshape(n, -1)
