"""Foxglove messages for logpipe's MCAPs, Protobuf-encoded with Foxglove's own classes
(``foxglove-schemas-protobuf``), so Foxglove and other viewers (Rerun reads Foxglove schemas as Protobuf only)
can open them.

What the files show (``logpipe.mcapio`` writes ingest's MCAP, ``logpipe.stages.predict`` adds predictions):

* agents: one ``foxglove.SceneUpdate`` per step, one entity per agent (id = track id, so an agent keeps its
  entity from step to step), a cube sized and coloured by object type (``AGENT_SHAPES``, ``TYPE_COLOURS``) and
  an arrow along the heading where the log gives one or the agent's motion shows one; an agent that leaves is
  deleted in the next step's message. Metadata: track id, object type, role.
* forecasts: one ``SceneUpdate`` per prediction sample, per target its observed history (grey), the true
  future where the log has it (green), a sphere at its current position (its type's colour) and the K modes
  (blue, more opaque the higher their score), living for the horizon.
* rasters: the sample's map raster as a ``foxglove.CompressedImage`` (PNG) and, because the 3D panel draws
  an image only through a camera calibration (its image layer projects through a pinhole camera model;
  without one an image shows only in the Image panel), also as a ``foxglove.Grid`` with ``red``/``green``/
  ``blue``/``alpha`` fields, which the 3D panel draws as a coloured layer under the scene. Both are in the
  raster frame (``raster_transform``).

Frames (``foxglove.FrameTransform``; a transform's translation/rotation is the child frame's origin/axes in
its parent). The 3D panel shows the scene in its display frame, which by default is the ``followTf`` of a
saved layout, else the first of ``base_link``, ``odom``, ``map``, ``earth`` (REP-105 names) that exists, else
the root of the transform tree with the most frames (``defaultFrameId`` of open-source Foxglove Studio's 3D
renderer); the camera starts at that frame's origin. Ingest's tree is therefore ``log_centre`` (root, no
REP-105 name) → ``world`` (the tracks' frame, translated by minus the centre of the log's positions) →
``ego`` (the ego's pose at each step, where the log has an ego): the panel opens on the middle of the log, not
at a world origin kilometres away (Argoverse cities), and "follow ego" is one click. ROS logs keep their own
tree (``map``/``odom`` win the default), and logpipe's frames hang off their world frame.

The raster frame is the image's own frame scaled to metres: origin at the image's top-left corner, x along
columns, y down the rows, z into the ground (the camera-frame convention of ``CompressedImage``: a camera
looking straight down), so pixel ``(u, v)`` covers x in ``[u, u + 1] * res`` and y in ``[v, v + 1] * res``.

Speed: ingest writes a message per step for every log, predict one per sample with thousands of line points,
and building a Protobuf object per agent or per point costs ~30 us in Python (seconds per dataset). So each
message is built from parts the Protobuf classes serialize once (a step's timestamp, a track's id and
metadata, the fixed part of a cube or a line) plus fixed-size parts whose doubles numpy writes into
Protobuf-serialized templates (``_Template``), concatenated per the wire format: a serialized message is
its fields' records in any order, the concatenation of two serializations of one type parses as their merge
(repeated fields append), and a length-delimited field is its key, the varint length and the payload. Parts
are joined in field-number order, so the bytes equal the class's own serialization except that a double
that is exactly 0 is written rather than left out (both parse to the same message).

Size: drawn positions and rotations are snapped to ``POSITION_QUANTUM`` / ``ROTATION_QUANTUM`` (about a
millimetre and a hundredth of a degree) so that zstd can compress their doubles; the exact numbers are in the
JSON channels and the Parquet tables.
"""

from __future__ import annotations

import itertools
import math
import struct
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from functools import cache
from typing import Any

import numpy as np
from foxglove_schemas_protobuf.ArrowPrimitive_pb2 import ArrowPrimitive
from foxglove_schemas_protobuf.Color_pb2 import Color
from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage
from foxglove_schemas_protobuf.CubePrimitive_pb2 import CubePrimitive
from foxglove_schemas_protobuf.FrameTransform_pb2 import FrameTransform
from foxglove_schemas_protobuf.Grid_pb2 import Grid
from foxglove_schemas_protobuf.KeyValuePair_pb2 import KeyValuePair
from foxglove_schemas_protobuf.LinePrimitive_pb2 import LinePrimitive
from foxglove_schemas_protobuf.PackedElementField_pb2 import PackedElementField
from foxglove_schemas_protobuf.Point3_pb2 import Point3
from foxglove_schemas_protobuf.Pose_pb2 import Pose
from foxglove_schemas_protobuf.PoseInFrame_pb2 import PoseInFrame
from foxglove_schemas_protobuf.Quaternion_pb2 import Quaternion
from foxglove_schemas_protobuf.SceneEntity_pb2 import SceneEntity
from foxglove_schemas_protobuf.SceneEntityDeletion_pb2 import SceneEntityDeletion
from foxglove_schemas_protobuf.SceneUpdate_pb2 import SceneUpdate
from foxglove_schemas_protobuf.SpherePrimitive_pb2 import SpherePrimitive
from foxglove_schemas_protobuf.Vector2_pb2 import Vector2
from foxglove_schemas_protobuf.Vector3_pb2 import Vector3
from google.protobuf.duration_pb2 import Duration
from google.protobuf.timestamp_pb2 import Timestamp
from mcap_protobuf.schema import build_file_descriptor_set

from logpipe.mcap_merge import NewChannel
from logpipe.types import OBJECT_TYPES, NDArrayBool, NDArrayByte, NDArrayFloat, NDArrayInt, SceneSample

SCHEMA_ENCODING = "protobuf"
MESSAGE_ENCODING = "protobuf"
MESSAGE_CLASSES: dict[str, Any] = {
    str(c.DESCRIPTOR.full_name): c for c in (SceneUpdate, FrameTransform, PoseInFrame, CompressedImage, Grid)
}
"""The Protobuf class of every Foxglove schema logpipe writes, by schema name (``foxglove.SceneUpdate``...)."""

AGENT_SHAPES: dict[str, tuple[float, float, float]] = {
    "vehicle": (4.5, 1.9, 1.6),
    "bus_truck": (10.0, 2.6, 3.2),
    "pedestrian": (0.6, 0.6, 1.75),
    "cyclist": (1.8, 0.6, 1.7),
    "motorcyclist": (2.1, 0.8, 1.6),
    "unknown": (1.0, 1.0, 1.0),
}
"""Box of each object type: length (along the heading), width, height; metres (typical sizes: the logs
carry positions only)."""
TYPE_COLOURS: dict[str, tuple[float, float, float]] = {
    "vehicle": (0.12, 0.47, 0.71),
    "bus_truck": (0.58, 0.40, 0.74),
    "pedestrian": (1.0, 0.50, 0.05),
    "cyclist": (0.17, 0.63, 0.17),
    "motorcyclist": (0.84, 0.15, 0.16),
    "unknown": (0.55, 0.55, 0.55),
}
"""RGB 0..1 per object type (the same for a type in every file, so a type reads the same everywhere)."""
MIN_HEADING_SPEED = 0.5
"""m/s: slower motion between two steps gives no heading (position noise would turn parked cars)."""
POSITION_QUANTUM = 2.0**-10
"""m: drawn positions (boxes, the ego, line points) are snapped to this (~1 mm, far below what a viewer shows):
float64 noise in the low mantissa bytes is incompressible, zeroed bytes are not (ingest's scene compresses ~45%
smaller, forecasts ~3x). Exact values stay in ``logpipe.AgentStates``/``logpipe.Predictions`` and Parquet."""
ROTATION_QUANTUM = 2.0**-12
"""Quaternion components are snapped to this (an angle error below 0.03 degrees), for the same reason."""

HISTORY_RGBA = (0.6, 0.6, 0.6, 0.9)
"""Colour of a forecast target's observed history (RGBA 0..1)."""
TRUTH_RGBA = (0.1, 0.85, 0.25, 1.0)
"""Colour of its true future."""
MODE_RGB = (0.2, 0.45, 1.0)
"""Colour of its modes; opacity 0.25..1 by score relative to its best mode."""
_LINE_Z = 0.05  # metres above the ground, so lines are not hidden in a raster drawn at z = 0
_RASTER_Z = -0.05  # the raster lies just under the ground plane the boxes stand on


# ---------------------------------------------------------------------------------------------------------
# Schemas.


@cache
def schema_data(message_class: Any) -> bytes:
    """The ``FileDescriptorSet`` of a Protobuf class and its imports (an MCAP ``protobuf`` schema)."""
    return bytes(build_file_descriptor_set(message_class).SerializeToString())


def schema_name(message_class: Any) -> str:
    """``foxglove.SceneUpdate`` etc.: the full Protobuf name, the schema name Foxglove recognises."""
    return str(message_class.DESCRIPTOR.full_name)


def new_channel(topic: str, name: str, frame_id: str) -> NewChannel:
    """A channel of Foxglove schema ``name`` (a ``MESSAGE_CLASSES`` key) to append to a copied log; its
    metadata names the frame its messages use."""
    message_class = MESSAGE_CLASSES[name]
    return NewChannel(topic, name, SCHEMA_ENCODING, schema_data(message_class), MESSAGE_ENCODING,
                      metadata={"frame_id": frame_id})


# ---------------------------------------------------------------------------------------------------------
# Wire-format parts.


def _varint(value: int) -> bytes:
    """Protobuf base-128 varint of a non-negative int."""
    out = bytearray()
    while value > 0x7F:
        out.append((value & 0x7F) | 0x80)
        value >>= 7
    out.append(value)
    return bytes(out)


def _key(field_number: int) -> bytes:
    """Key of a length-delimited field (wire type 2)."""
    return _varint(field_number << 3 | 2)


def _serialize(message: Any) -> bytes:
    return bytes(message.SerializeToString())


def _sentinels(count: int, base: int) -> list[float]:
    # Subnormal doubles: exact, nonzero (so the field is written) and never a real size, colour or position.
    return [struct.unpack("<d", struct.pack("<Q", 0x000A_5E47_0000_0000 + base + i))[0] for i in range(count)]


class _Template:
    """The serialization of a message whose varying doubles hold sentinels, and where each sits.

    ``fill`` writes columns of values over the sentinels of one copy per row (doubles are fixed-size, little
    endian), so rows differing only in those doubles are built by numpy instead of one object each.
    """

    def __init__(self, build: Callable[[Sequence[float]], Any], count: int) -> None:
        self.data, self.offsets = self._locate(build, count, 0)
        self.size = len(self.data)
        # Built again with other sentinels: the same places must change and nothing else, so no byte run
        # that merely looks like a sentinel is taken for one.
        again, offsets = self._locate(build, count, 1 << 20)
        plain, other = bytearray(self.data), bytearray(again)
        for found in offsets:
            for at in found:
                plain[at : at + 8] = other[at : at + 8] = bytes(8)
        if offsets != self.offsets or plain != other:
            raise RuntimeError("template doubles are not where its sentinels are")

    @staticmethod
    def _locate(build: Callable[[Sequence[float]], Any], count: int, base: int) -> tuple[bytes, list[list[int]]]:
        marks = _sentinels(count, base)
        data = _serialize(build(marks))
        offsets = []
        for mark in marks:
            pattern = struct.pack("<d", mark)
            found, at = [], data.find(pattern)
            while at >= 0:
                found.append(at)
                at = data.find(pattern, at + 1)
            if not found:
                raise RuntimeError("template lost a sentinel (a field set to a default is not serialized)")
            offsets.append(found)
        return data, offsets

    def fill(self, columns: Sequence[NDArrayFloat]) -> NDArrayByte:
        """(n, size) uint8: row i is the template with column j's value i in place of sentinel j."""
        n = len(columns[0]) if columns else 0
        out = np.tile(np.frombuffer(self.data, np.uint8), (n, 1))
        for values, offsets in zip(columns, self.offsets, strict=True):
            raw = np.ascontiguousarray(values, dtype="<f8").view(np.uint8).reshape(n, 8)
            for at in offsets:
                out[:, at : at + 8] = raw
        return out

    def rows(self, columns: Sequence[NDArrayFloat]) -> list[bytes]:
        """``fill`` as one bytes object per row."""
        filled, size = self.fill(columns), self.size
        if len(filled) and (filled[:, -1] != 0).all():
            # numpy's fixed-width bytes make the objects in C; they drop trailing NUL bytes, hence the check.
            rows: list[bytes] = filled.view(f"S{size}").ravel().tolist()
            return rows
        blob = filled.tobytes()
        return [blob[i : i + size] for i in range(0, len(blob), size)]


def timestamp(ns: int) -> Timestamp:
    """A ``google.protobuf.Timestamp`` of ns since the epoch (the log's clock)."""
    return Timestamp(seconds=ns // 1_000_000_000, nanos=ns % 1_000_000_000)


def _half_angles(yaw: NDArrayFloat) -> tuple[NDArrayFloat, NDArrayFloat]:
    """(z, w) of the rotations by ``yaw`` about +z, snapped to ``ROTATION_QUANTUM``."""
    half = np.asarray(yaw, np.float64) / 2.0
    return snap(np.sin(half), ROTATION_QUANTUM), snap(np.cos(half), ROTATION_QUANTUM)


def snap(values: NDArrayFloat, quantum: float) -> NDArrayFloat:
    """``values`` rounded to multiples of ``quantum`` (a power of two, so exactly)."""
    snapped: NDArrayFloat = np.round(np.asarray(values, np.float64) / quantum) * quantum
    return snapped


def _rgba(rgb: Sequence[float], alpha: float) -> Color:
    return Color(r=rgb[0], g=rgb[1], b=rgb[2], a=alpha)


# ---------------------------------------------------------------------------------------------------------
# Agents of a log (ingest).


def display_headings(track: NDArrayInt, ts: NDArrayInt, x: NDArrayFloat, y: NDArrayFloat,
                     heading: NDArrayFloat) -> tuple[NDArrayFloat, NDArrayBool]:
    """The heading to draw for each row (rad, CCW from world +x) and whether there is one.

    The log's heading where it has one; else the direction of the track's motion to its next row (the last
    row: from its previous one) when faster than ``MIN_HEADING_SPEED``; else the track's nearest earlier such
    heading, then its nearest later one (a car waiting at a light keeps pointing where it went). A track that
    never moves and has no heading has none (its box is drawn axis-aligned, without an arrow).

    Args:
        track: (n,) track code of each row; ts: (n,) ns; x, y: (n,) metres; heading: (n,) rad, NaN where the
            log has none.
    """
    n = len(track)
    if n == 0:
        return np.zeros(0), np.zeros(0, bool)
    order = np.lexsort((ts, track))
    t_s, x_s, y_s, ts_s = track[order], x[order], y[order], ts[order].astype(np.float64)
    same = t_s[1:] == t_s[:-1]
    dx, dy, dt = np.diff(x_s), np.diff(y_s), np.diff(ts_s) / 1e9
    with np.errstate(divide="ignore", invalid="ignore"):
        fast = same & (np.hypot(dx, dy) > MIN_HEADING_SPEED * dt)
    step_yaw = np.arctan2(dy, dx)
    yaw = np.full(n, np.nan)
    has_next = np.concatenate([same, [False]])
    yaw[:-1][has_next[:-1] & fast] = step_yaw[has_next[:-1] & fast]
    last = ~has_next & np.concatenate([[False], same])  # last rows of tracks that have a previous row
    prev_fast = np.concatenate([[False], fast])
    take = last & prev_fast
    yaw[take] = step_yaw[np.flatnonzero(take) - 1]
    given = heading[order]
    yaw = np.where(np.isfinite(given), given, yaw)
    # Fill gaps within each track: forward from the last known row, then backward from the next one.
    ok = np.isfinite(yaw)
    index = np.arange(n)
    for direction in (1, -1):
        idx = np.where(ok, index, -1 if direction == 1 else n)[::direction]
        nearest = (np.maximum.accumulate(idx) if direction == 1 else np.minimum.accumulate(idx))[::direction]
        usable = ~ok & (nearest >= 0) & (nearest < n)
        src = nearest[usable]
        usable_rows = np.flatnonzero(usable)
        same_track = t_s[src] == t_s[usable_rows]
        yaw[usable_rows[same_track]] = yaw[src[same_track]]
        ok = np.isfinite(yaw)
    out_yaw, out_ok = np.empty(n), np.empty(n, bool)
    out_yaw[order], out_ok[order] = np.where(ok, yaw, 0.0), ok
    return out_yaw, out_ok


@dataclass
class LogAgents:
    """One log's rows for drawing, sorted by time (rows of a step together).

    Attributes:
        steps: (n,) step number of each row, non-decreasing.
        ts: (n,) row timestamps, ns (a step's message takes its first row's).
        x, y: (n,) metres in the log's world frame.
        yaw: (n,) heading to draw, rad (``display_headings``); has_heading: (n,) whether there is one.
        track: (n,) codes into ``track_names``; kind: (n,) codes into ``kinds``, a (object type, role) pair
            per code (type one of ``OBJECT_TYPES``, unknown names drawn as ``unknown``).
    """

    steps: NDArrayInt
    ts: NDArrayInt
    x: NDArrayFloat
    y: NDArrayFloat
    yaw: NDArrayFloat
    has_heading: NDArrayBool
    track: NDArrayInt
    track_names: list[str]
    kind: NDArrayInt
    kinds: list[tuple[str, str]]


def _agent_geometry(object_type: str, arrow: bool) -> Callable[[Sequence[float]], SceneEntity]:
    length, width, height = AGENT_SHAPES.get(object_type, AGENT_SHAPES["unknown"])
    rgb = TYPE_COLOURS.get(object_type, TYPE_COLOURS["unknown"])

    def build(v: Sequence[float]) -> SceneEntity:
        # Without a heading the box is axis-aligned: identity rotation, nothing to fill.
        x, y = v[0], v[1]
        turn = Quaternion(z=v[2], w=v[3]) if arrow else Quaternion(w=1.0)
        cube = CubePrimitive(pose=Pose(position=Vector3(x=x, y=y, z=height / 2.0), orientation=turn),
                             size=Vector3(x=length, y=width, z=height), color=_rgba(rgb, 0.85))
        arrows = []
        if arrow:  # from the box's top centre forwards, past its front
            arrows.append(ArrowPrimitive(
                pose=Pose(position=Vector3(x=x, y=y, z=height + 0.05), orientation=turn),
                shaft_length=max(0.55 * length, 0.4), shaft_diameter=max(0.12 * width, 0.06),
                head_length=max(0.3 * length, 0.25), head_diameter=max(0.35 * width, 0.18), color=_rgba(rgb, 1.0)))
        return SceneEntity(arrows=arrows, cubes=[cube])

    return build


@cache
def _agent_template(object_type: str, arrow: bool) -> _Template:
    return _Template(_agent_geometry(object_type, arrow), 4 if arrow else 2)


def agent_scene_updates(agents: LogAgents, frame: str) -> list[bytes]:
    """One serialized ``foxglove.SceneUpdate`` per step of ``agents`` (in time order): an entity per agent
    in ``frame`` (id = track id; a cube, an arrow when it has a heading; metadata ``track_id``,
    ``object_type``, ``role``), and deletions of the agents the previous step had and this one lacks.

    A message is its deletions, then per row the entity's key and length, the step's timestamp and frame, the
    track's id and metadata and the row's geometry. Each distinct part is serialized once; numpy orders
    references to them (an object array) and one ``bytes.join`` copies them, so no Python runs per row
    beyond cutting the geometry rows out of numpy's buffer.
    """
    n = len(agents.ts)
    if n == 0:
        return []
    changes = np.diff(agents.steps) != 0
    starts = np.concatenate([[0], np.flatnonzero(changes) + 1])
    step = np.concatenate([[0], np.cumsum(changes)]).astype(np.int64)  # index of the row's message
    step_ts = agents.ts[starts].tolist()
    pool = _Pool()
    frame_part, stamp_key = _serialize(SceneEntity(frame_id=frame)), _key(SceneEntity.TIMESTAMP_FIELD_NUMBER)
    stamps = [_serialize(timestamp(t)) for t in step_ts]
    step_id = pool.add([stamp_key + _varint(len(t)) + t + frame_part for t in stamps])
    del_step, deletions = _departures(agents.track, step, step_ts, agents.track_names)
    del_id = pool.add(deletions)

    # One part per distinct (track, kind): its id and metadata.
    per_track = max(len(agents.kinds), 1)
    combos, combo = np.unique(agents.track * per_track + agents.kind, return_inverse=True)
    track_parts = []
    for key in combos.tolist():
        name = agents.track_names[key // per_track]
        object_type, role = agents.kinds[key % per_track]
        track_parts.append(_serialize(SceneEntity(id=name, metadata=[
            KeyValuePair(key="track_id", value=name), KeyValuePair(key="object_type", value=object_type),
            KeyValuePair(key="role", value=role)])))
    track_id = pool.add(track_parts)

    # Geometry rows: one template per (object type, arrow or not), filled by numpy.
    qz, qw = _half_angles(np.where(agents.has_heading, agents.yaw, 0.0))
    geo_id = np.zeros(n, np.int64)
    type_code = [OBJECT_TYPES.index(t if t in AGENT_SHAPES else "unknown") for t, _ in agents.kinds]
    variant = np.asarray(type_code, np.int64)[agents.kind] * 2 + agents.has_heading.astype(np.int64)
    for v in np.unique(variant).tolist():
        rows = np.flatnonzero(variant == v)
        arrow = bool(v % 2)
        x, y = snap(agents.x[rows], POSITION_QUANTUM), snap(agents.y[rows], POSITION_QUANTUM)
        columns = [x, y, qz[rows], qw[rows]] if arrow else [x, y]
        geo_id[rows] = pool.add(_agent_template(OBJECT_TYPES[v // 2], arrow).rows(columns))

    lengths = pool.lengths()
    body = lengths[step_id[step]] + lengths[track_id[combo]] + lengths[geo_id]
    key = _key(SceneUpdate.ENTITIES_FIELD_NUMBER)
    unique_body, body_code = np.unique(body, return_inverse=True)
    head_id = pool.add([key + _varint(m) for m in unique_body.tolist()])[body_code]

    # Pieces in message order: per step its deletions, then per row its four parts.
    dels = np.bincount(del_step, minlength=len(starts))
    block = np.cumsum(dels + 4 * np.diff(np.append(starts, n)))
    block_start = np.concatenate([[0], block[:-1]])
    order = np.empty(int(block[-1]), np.int64)
    rank = np.arange(len(del_step)) - (np.cumsum(dels) - dels)[del_step]  # del_step is sorted
    order[block_start[del_step] + rank] = del_id
    at_row = block_start[step] + dels[step] + 4 * (np.arange(n) - starts[step])
    order[at_row], order[at_row + 1], order[at_row + 2], order[at_row + 3] = (
        head_id, step_id[step], track_id[combo], geo_id)
    blob = b"".join(pool.objects()[order].tolist())
    sizes = pool.lengths()[order]
    bounds = [*(np.cumsum(sizes) - sizes)[block_start].tolist(), len(blob)]
    return [blob[a:b] for a, b in itertools.pairwise(bounds)]


class _Pool:
    """Distinct byte strings, numbered in the order added."""

    def __init__(self) -> None:
        self._items: list[bytes] = []

    def add(self, items: list[bytes]) -> NDArrayInt:
        """Append ``items``; their numbers."""
        first = len(self._items)
        self._items.extend(items)
        return np.arange(first, len(self._items), dtype=np.int64)

    def lengths(self) -> NDArrayInt:
        return np.fromiter(map(len, self._items), np.int64, len(self._items))

    def objects(self) -> Any:
        """The items as a numpy object array (fancy indexing copies references, not bytes)."""
        out = np.empty(len(self._items), object)
        out[:] = self._items
        return out


def _departures(track: NDArrayInt, step: NDArrayInt, step_ts: list[int],
                names: list[str]) -> tuple[NDArrayInt, list[bytes]]:
    """The serialized ``deletions`` records of agents seen at a step and absent at the next one, and the
    (sorted) index of the step whose message carries each."""
    order = np.lexsort((step, track))
    t_s, s_s = track[order], step[order]
    continues = (t_s[1:] == t_s[:-1]) & (s_s[1:] == s_s[:-1] + 1)
    leaving = np.flatnonzero(~np.concatenate([continues, [False]]) & (s_s + 1 < len(step_ts)))
    at = s_s[leaving] + 1
    by_step = np.argsort(at, kind="stable")
    leaving, at = leaving[by_step], at[by_step]
    records = [_serialize(SceneUpdate(deletions=[SceneEntityDeletion(
        timestamp=timestamp(step_ts[a]), type=SceneEntityDeletion.MATCHING_ID, id=names[t])]))
        for a, t in zip(at.tolist(), t_s[leaving].tolist(), strict=True)]
    return at.astype(np.int64), records


@cache
def _pose_template(frame: str, turned: bool) -> _Template:
    def build(v: Sequence[float]) -> PoseInFrame:
        turn = Quaternion(z=v[2], w=v[3]) if turned else Quaternion(w=1.0)
        return PoseInFrame(frame_id=frame, pose=Pose(position=Vector3(x=v[0], y=v[1]), orientation=turn))

    return _Template(build, 4 if turned else 2)


@cache
def _transform_template(parent: str, child: str, turned: bool) -> _Template:
    def build(v: Sequence[float]) -> FrameTransform:
        turn = Quaternion(z=v[2], w=v[3]) if turned else Quaternion(w=1.0)
        return FrameTransform(parent_frame_id=parent, child_frame_id=child, translation=Vector3(x=v[0], y=v[1]),
                              rotation=turn)

    return _Template(build, 4 if turned else 2)


def _posed_rows(template: Callable[[bool], _Template], message_class: Any, ts: NDArrayInt, x: NDArrayFloat,
                y: NDArrayFloat, yaw: NDArrayFloat) -> list[bytes]:
    """Messages of ``message_class`` with a timestamp, then a template's fields: position (x, y), rotation
    by ``yaw`` about z (identity where NaN)."""
    turned = np.isfinite(yaw)
    qz, qw = _half_angles(np.where(turned, yaw, 0.0))
    bodies: list[bytes] = [b""] * len(ts)
    for flag in (True, False):
        rows = np.flatnonzero(turned == flag)
        px, py = snap(x[rows], POSITION_QUANTUM), snap(y[rows], POSITION_QUANTUM)
        columns = [px, py, qz[rows], qw[rows]] if flag else [px, py]
        for i, body in zip(rows.tolist(), template(flag).rows(columns) if len(rows) else [], strict=True):
            bodies[i] = body
    return [_serialize(message_class(timestamp=timestamp(t))) + b for t, b in zip(ts.tolist(), bodies, strict=True)]


def poses_in_frame(frame: str, ts: NDArrayInt, x: NDArrayFloat, y: NDArrayFloat,
                   yaw: NDArrayFloat) -> list[bytes]:
    """A serialized ``foxglove.PoseInFrame`` per row (time ``ts`` ns): position (x, y, 0) m in ``frame``,
    heading ``yaw`` rad (identity orientation where NaN)."""
    return _posed_rows(lambda turned: _pose_template(frame, turned), PoseInFrame, ts, x, y, yaw)


def frame_transforms(parent: str, child: str, ts: NDArrayInt, x: NDArrayFloat, y: NDArrayFloat,
                     yaw: NDArrayFloat) -> list[bytes]:
    """A serialized ``foxglove.FrameTransform`` per row (time ``ts`` ns): ``child``'s origin at (x, y, 0) m in
    ``parent``, turned by ``yaw`` rad about z (not turned where NaN)."""
    return _posed_rows(lambda turned: _transform_template(parent, child, turned), FrameTransform, ts, x, y, yaw)


def frame_transform(parent: str, child: str, t_ns: int, translation: Sequence[float],
                    rotation: Quaternion | None = None) -> bytes:
    """One serialized ``foxglove.FrameTransform``: ``child``'s origin at ``translation`` (x, y, z) m in
    ``parent``, its axes turned by ``rotation`` (identity when None)."""
    tx, ty, tz = (float(v) for v in translation)
    return _serialize(FrameTransform(timestamp=timestamp(t_ns), parent_frame_id=parent, child_frame_id=child,
                                     translation=Vector3(x=tx, y=ty, z=tz),
                                     rotation=rotation if rotation is not None else Quaternion(w=1.0)))


def log_centre(x: NDArrayFloat, y: NDArrayFloat) -> tuple[float, float]:
    """Centre of the box around a log's finite positions (metres, world frame); (0, 0) when there are none."""
    ok = np.isfinite(x) & np.isfinite(y)
    if not ok.any():
        return 0.0, 0.0
    return (float(x[ok].min() + x[ok].max()) / 2.0, float(y[ok].min() + y[ok].max()) / 2.0)


# ---------------------------------------------------------------------------------------------------------
# Forecasts of a sample (predict).


@cache
def _point_template() -> _Template:
    # A line's point record (z = 0 is not written); the line's pose lifts the whole line.
    return _Template(lambda v: LinePrimitive(points=[Point3(x=v[0], y=v[1])]), 2)


@cache
def _line_head(thickness: float) -> bytes:
    return _serialize(LinePrimitive(type=LinePrimitive.LINE_STRIP, thickness=thickness,
                                    pose=Pose(position=Vector3(z=_LINE_Z), orientation=Quaternion(w=1.0))))


@cache
def _line_colour(rgba: tuple[float, float, float, float]) -> bytes:
    return _serialize(LinePrimitive(color=Color(r=rgba[0], g=rgba[1], b=rgba[2], a=rgba[3])))


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
    key_lines, key_entities = _key(SceneEntity.LINES_FIELD_NUMBER), _key(SceneUpdate.ENTITIES_FIELD_NUMBER)
    life = Duration(seconds=max(lifetime_ns, 0) // 1_000_000_000, nanos=max(lifetime_ns, 0) % 1_000_000_000)
    stamp = timestamp(now_ns)
    entities = []
    at, line = 0, 0
    for j, row in enumerate(targets.tolist()):
        object_type = OBJECT_TYPES[int(sample.object_types[row])]
        name = sample.track_ids[row]
        cx, cy = (float(v) for v in snap(current[j], POSITION_QUANTUM))
        diameter = max(0.6 * AGENT_SHAPES.get(object_type, AGENT_SHAPES["unknown"])[1], 0.5)
        parts = [_serialize(SceneEntity(
            timestamp=stamp, frame_id=frame, id=name, lifetime=life,
            metadata=[KeyValuePair(key="sample_id", value=sample.sample_id), KeyValuePair(key="track_id", value=name),
                      KeyValuePair(key="object_type", value=object_type)],
            spheres=[SpherePrimitive(pose=Pose(position=Vector3(x=cx, y=cy, z=_LINE_Z), orientation=Quaternion(w=1)),
                                     size=Vector3(x=diameter, y=diameter, z=diameter),
                                     color=_rgba(TYPE_COLOURS.get(object_type, TYPE_COLOURS["unknown"]), 1.0))]))]
        for _ in range(per_target[j]):
            count, head, colour = lines[line]
            body = head + blob[at * size : (at + count) * size] + colour
            parts += (key_lines, _varint(len(body)), body)
            at += count
            line += 1
        entity = b"".join(parts)
        entities.append(key_entities + _varint(len(entity)) + entity)
    return b"".join(entities)


# ---------------------------------------------------------------------------------------------------------
# Rasters (predict).


def raster_rgb(raster: NDArrayByte, channels: Sequence[str]) -> NDArrayByte:
    """(C, H, W) uint8 map layers -> (H, W, 3) uint8 for viewing: red drivable area, green lanes, blue lane
    boundaries and crossings (the first three channels when the names are not these)."""
    names = list(channels)

    def layer(pick: Callable[[str], bool]) -> NDArrayByte:
        idx = [i for i, n in enumerate(names) if pick(n)]
        return raster[idx].max(axis=0) if idx else np.zeros(raster.shape[1:], np.uint8)

    if any(n in ("drivable_area", "lane_boundary") or n.startswith("lane_") for n in names):
        rgb = [layer(lambda n: n == "drivable_area"),
               layer(lambda n: n.startswith("lane_") and n != "lane_boundary"),
               layer(lambda n: n in ("lane_boundary", "crossing"))]
    else:
        rgb = [raster[i] if i < len(raster) else np.zeros(raster.shape[1:], np.uint8) for i in range(3)]
    return np.ascontiguousarray(np.stack(rgb, axis=-1).astype(np.uint8))


def raster_resolution(world_to_raster: NDArrayFloat) -> float:
    """Metres per pixel of a raster's (2, 3) world → pixel affine (a similarity: one scale for both axes)."""
    return 1.0 / math.sqrt(abs(float(np.linalg.det(np.asarray(world_to_raster, np.float64)[:, :2]))))


def raster_transform(parent: str, child: str, now_ns: int, world_to_raster: NDArrayFloat) -> bytes:
    """The serialized ``foxglove.FrameTransform`` placing raster frame ``child`` (module docstring) in ``parent``,
    the frame the affine's world coordinates are in; the raster lies ``_RASTER_Z`` m under the ground.

    The affine maps world (x, y) to pixel (u, v) with pixel centres at integers: a similarity whose image
    rows grow downwards (``logpipe.raster``), i.e. a reflection of world x/y, which with z into the ground is
    the rotation by pi about an axis in the ground plane.

    Raises:
        ValueError: the affine keeps orientation (rows growing upwards), which no logpipe raster does.
    """
    a = np.asarray(world_to_raster, np.float64)
    res = raster_resolution(a)
    m = a[:, :2] * res  # world → raster-frame axes, orthonormal
    if np.linalg.det(m) > 0:
        raise ValueError("raster affine keeps orientation: image rows must grow downwards (logpipe.raster)")
    origin = np.linalg.solve(a[:, :2], np.array([-0.5, -0.5]) - a[:, 2])  # the image's top-left corner
    # m = [[cos f, sin f], [sin f, -cos f]] mirrors about the line at f / 2: the raster's axes are world's turned
    # by pi about that line.
    half = math.atan2(m[1, 0], m[0, 0]) / 2.0
    rotation = Quaternion(x=math.cos(half), y=math.sin(half), z=0.0, w=0.0)
    return frame_transform(parent, child, now_ns, (origin[0], origin[1], _RASTER_Z), rotation)


def compressed_raster(frame: str, now_ns: int, rgb: NDArrayByte) -> bytes:
    """A serialized ``foxglove.CompressedImage``: ``rgb`` (H, W, 3) as PNG in ``frame``."""
    import cv2  # here: ingest, which writes no image, does not pay for loading OpenCV

    ok, png = cv2.imencode(".png", np.ascontiguousarray(rgb[..., ::-1]))  # OpenCV writes BGR
    if not ok:
        raise ValueError("PNG encoding of the raster failed")
    return _serialize(CompressedImage(timestamp=timestamp(now_ns), frame_id=frame, data=png.tobytes(), format="png"))


_GRID_FIELDS = [PackedElementField(name=name, offset=i, type=PackedElementField.UINT8)
                for i, name in enumerate(("red", "green", "blue", "alpha"))]


def raster_grid(frame: str, now_ns: int, rgb: NDArrayByte, resolution_m: float) -> bytes:
    """A serialized ``foxglove.Grid`` of ``rgb`` (H, W, 3) in raster frame ``frame``, cells ``resolution_m``
    wide, facing up: empty cells dim (alpha 64), drawn ones opaque.

    The raster frame's z points into the ground and the 3D panel draws a grid on its +z side, so the grid is
    turned by pi about x (its y runs up the image from the bottom row) and its rows are stored bottom first.
    """
    h, w, _ = rgb.shape
    rgba = np.empty((h, w, 4), np.uint8)
    rgba[..., :3] = rgb
    rgba[..., 3] = np.where(rgb.any(axis=-1), 255, 64)
    return _serialize(Grid(
        timestamp=timestamp(now_ns), frame_id=frame,
        pose=Pose(position=Vector3(y=h * resolution_m), orientation=Quaternion(x=1.0)),
        column_count=w, cell_size=Vector2(x=resolution_m, y=resolution_m), row_stride=w * 4, cell_stride=4,
        fields=_GRID_FIELDS, data=np.ascontiguousarray(rgba[::-1]).tobytes()))
