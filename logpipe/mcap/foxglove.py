"""Foxglove messages for logpipe's MCAPs, Protobuf-encoded with Foxglove's own classes
(``foxglove-schemas-protobuf``), so Foxglove and other viewers (Rerun reads Foxglove schemas as Protobuf only)
can open them.

What the files show (``logpipe.mcap.tracks`` writes ingest's MCAP, ``logpipe.stages.predict`` adds predictions):

* agents: one ``foxglove.SceneUpdate`` per step, one entity per agent (id = track id, so an agent keeps its
  entity from step to step), a cube sized and coloured by object type (``AGENT_SHAPES``, ``TYPE_COLOURS``) and
  an arrow along the heading where the log gives one or the agent's motion shows one; an agent that leaves is
  deleted in the next step's message. Metadata: track id, object type, role.
* forecasts (``logpipe.mcap.forecast_scene``): one ``SceneUpdate`` per prediction sample, per target its
  observed history (grey), the true future where the log has it (orange), a sphere at its current position
  (its type's colour) and the K modes (blue, more opaque the higher their score), living for the horizon; and a
  ``legend`` entity of texts naming each colour (its own channel, once per log).
* rasters: the sample's map raster as a ``foxglove.CompressedImage`` (PNG) and, because the 3D panel draws
  an image only through a camera calibration (its image layer projects through a pinhole camera model;
  without one an image shows only in the Image panel), also as a ``foxglove.Grid`` with ``red``/``green``/
  ``blue``/``alpha`` fields, which the 3D panel draws as a coloured layer under the scene. Both are in the
  raster frame (``logpipe.mcap.raster_image``).

Frames (``foxglove.FrameTransform``; a transform's translation/rotation is the child frame's origin/axes in
its parent). The 3D panel shows the scene in its display frame, which by default is the ``followTf`` of a
saved layout, else the first of ``base_link``, ``odom``, ``map``, ``earth`` (REP-105 names) that exists, else
the root of the transform tree with the most frames (``defaultFrameId`` of open-source Foxglove Studio's 3D
renderer); the camera starts at that frame's origin. Ingest's tree is therefore ``log_centre`` (root, no
REP-105 name) → ``world`` (the tracks' frame, translated by minus the centre of the log's positions) →
``ego`` (the ego's pose at each step, where the log has an ego): the panel opens on the middle of the log, not
at a world origin kilometres away (Argoverse cities), and "follow ego" is one click. ROS logs keep their own
tree (``map``/``odom`` win the default), and logpipe's frames hang off their world frame.

Speed: ingest writes a message per step for every log and predict one per sample with thousands of line
points, so messages are spliced from pre-serialized parts (``logpipe.mcap.protobuf_splice``): the bytes equal the
classes' own serialization except that a double that is exactly 0 is written rather than left out.

Size: drawn positions and rotations are snapped to ``POSITION_QUANTUM`` / ``ROTATION_QUANTUM`` (about a
millimetre and a hundredth of a degree) so that zstd can compress their doubles; the exact numbers are in the
JSON channels and the Parquet tables.
"""

from __future__ import annotations

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
from foxglove_schemas_protobuf.Pose_pb2 import Pose
from foxglove_schemas_protobuf.PoseInFrame_pb2 import PoseInFrame
from foxglove_schemas_protobuf.Quaternion_pb2 import Quaternion
from foxglove_schemas_protobuf.SceneEntity_pb2 import SceneEntity
from foxglove_schemas_protobuf.SceneEntityDeletion_pb2 import SceneEntityDeletion
from foxglove_schemas_protobuf.SceneUpdate_pb2 import SceneUpdate
from foxglove_schemas_protobuf.Vector3_pb2 import Vector3
from google.protobuf.timestamp_pb2 import Timestamp
from mcap_protobuf.schema import build_file_descriptor_set

from logpipe.mcap.bulk import Pieces
from logpipe.mcap.merge import NewChannel
from logpipe.mcap.protobuf_splice import (
    ByteTable,
    Template,
    concatenated,
    field_key,
    length_delimited_rows,
    serialize,
    timestamps,
    varint,
)
from logpipe.types import OBJECT_TYPES, NDArrayBool, NDArrayFloat, NDArrayInt

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
# Message parts.


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


def rgba(rgb: Sequence[float], alpha: float) -> Color:
    """A Foxglove colour of RGB 0..1 and an opacity."""
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
                             size=Vector3(x=length, y=width, z=height), color=rgba(rgb, 0.85))
        arrows = []
        if arrow:  # from the box's top centre forwards, past its front
            arrows.append(ArrowPrimitive(
                pose=Pose(position=Vector3(x=x, y=y, z=height + 0.05), orientation=turn),
                shaft_length=max(0.55 * length, 0.4), shaft_diameter=max(0.12 * width, 0.06),
                head_length=max(0.3 * length, 0.25), head_diameter=max(0.35 * width, 0.18), color=rgba(rgb, 1.0)))
        return SceneEntity(arrows=arrows, cubes=[cube])

    return build


@cache
def _agent_template(object_type: str, arrow: bool) -> Template:
    return Template(_agent_geometry(object_type, arrow), 4 if arrow else 2)


def agent_scene_updates(agents: LogAgents, frame: str, log_starts: NDArrayInt | None = None) -> list[bytes]:
    """``agent_scene_pieces`` as one bytes object per message."""
    return agent_scene_pieces(agents, frame, log_starts).messages()


def agent_scene_pieces(agents: LogAgents, frame: str, log_starts: NDArrayInt | None = None) -> Pieces:
    """One serialized ``foxglove.SceneUpdate`` per step of ``agents`` (in time order): an entity per agent
    in ``frame`` (id = track id; a cube, an arrow when it has a heading; metadata ``track_id``,
    ``object_type``, ``role``), and deletions of the agents the previous step had and this one lacks.

    ``agents`` may hold several logs one after the other (steps numbered on across them, tracks coded apart):
    ``log_starts`` are the indexes of the steps that start a log (none: one log), and no log's message deletes
    an agent of the log before it. Built for a batch of logs at once, the numpy work is per batch, not per log.

    A message is its deletions, then per row the entity's key and length, the step's timestamp and frame, the
    track's id and metadata and the row's geometry. Each distinct part is serialized once; numpy copies them into
    blocks of rows whose parts have the same lengths (``protobuf_splice.length_delimited_rows``) and each row's
    entity is cut out of its block as one bytes object, so no Python runs per row or per part.
    """
    n = len(agents.ts)
    if n == 0:
        return Pieces.of_messages([])
    changes = np.diff(agents.steps) != 0
    starts = np.concatenate([[0], np.flatnonzero(changes) + 1])
    step = np.concatenate([[0], np.cumsum(changes)]).astype(np.int64)  # index of the row's message
    stamps = stamp_table(agents.ts[starts])
    steps = np.arange(len(starts))
    step_parts = concatenated([(concatenated([(stamps, steps)], field_key(SceneEntity.TIMESTAMP_FIELD_NUMBER)), steps),
                               (ByteTable.of_items([serialize(SceneEntity(frame_id=frame))]), np.zeros_like(steps))])
    last_steps = np.zeros(len(starts), bool)
    if log_starts is not None and len(log_starts):
        last_steps[np.asarray(log_starts, np.int64)[np.asarray(log_starts) > 0] - 1] = True
    del_step, deletions = _departures(agents.track, step, stamps, agents.track_names, last_steps)

    # One part per distinct (track, kind): its id and metadata.
    per_track = max(len(agents.kinds), 1)
    combos, combo = np.unique(agents.track * per_track + agents.kind, return_inverse=True)
    track_parts = []
    for key in combos.tolist():
        name = agents.track_names[key // per_track]
        object_type, role = agents.kinds[key % per_track]
        track_parts.append(serialize(SceneEntity(id=name, metadata=[
            KeyValuePair(key="track_id", value=name), KeyValuePair(key="object_type", value=object_type),
            KeyValuePair(key="role", value=role)])))

    # Geometry rows: one template per (object type, arrow or not), filled by numpy.
    qz, qw = _half_angles(np.where(agents.has_heading, agents.yaw, 0.0))
    type_code = [OBJECT_TYPES.index(t if t in AGENT_SHAPES else "unknown") for t, _ in agents.kinds]
    variant = np.asarray(type_code, np.int64)[agents.kind] * 2 + agents.has_heading.astype(np.int64)
    geometry = []
    for v in np.unique(variant).tolist():
        rows = np.flatnonzero(variant == v)
        arrow = bool(v % 2)
        x, y = snap(agents.x[rows], POSITION_QUANTUM), snap(agents.y[rows], POSITION_QUANTUM)
        geometry.append((rows, _agent_template(OBJECT_TYPES[v // 2], arrow).fill(
            [x, y, qz[rows], qw[rows]] if arrow else [x, y])))
    # Each row's entity (its key and length, the step's timestamp and frame, the track's part, its geometry) is
    # one bytes object, cut out of numpy blocks of the rows whose parts have the same lengths.
    entities, entity_lengths = length_delimited_rows(field_key(SceneUpdate.ENTITIES_FIELD_NUMBER), [
        (step_parts, step), (ByteTable.of_items(track_parts), combo.reshape(-1)),
        (ByteTable.of_rows(n, geometry), np.arange(n))])

    # Pieces in message order: per step its deletions, then its rows' entities.
    dels = np.bincount(del_step, minlength=len(starts))
    block = np.cumsum(dels + np.diff(np.append(starts, n)))
    block_start = np.concatenate([[0], block[:-1]])
    objects = np.empty(int(block[-1]), object)
    rank = np.arange(len(del_step)) - (np.cumsum(dels) - dels)[del_step]  # del_step is sorted
    at_deletion = block_start[del_step] + rank
    deletion_objects = np.empty(len(deletions), object)
    deletion_objects[:] = deletions  # bytes as they are (a list would become a fixed-width array first)
    objects[at_deletion] = deletion_objects
    at_row = block_start[step] + dels[step] + (np.arange(n) - starts[step])
    objects[at_row] = entities
    lengths = np.empty(len(objects), np.int64)
    lengths[at_deletion] = np.fromiter(map(len, deletions), np.int64, len(deletions))
    lengths[at_row] = entity_lengths
    return Pieces(objects, lengths, np.append(block_start, len(objects)))


def _departures(track: NDArrayInt, step: NDArrayInt, stamps: ByteTable, names: list[str],
                last_steps: NDArrayBool) -> tuple[NDArrayInt, list[bytes]]:
    """The serialized ``deletions`` records of agents seen at a step and absent at the next one (unless the step
    is its log's last, ``last_steps``), and the (sorted) index of the step whose message carries each; ``stamps``:
    each step's serialized timestamp."""
    order = np.lexsort((step, track))
    t_s, s_s = track[order], step[order]
    continues = (t_s[1:] == t_s[:-1]) & (s_s[1:] == s_s[:-1] + 1)
    steps = len(stamps.lengths)
    leaving = np.flatnonzero(~np.concatenate([continues, [False]]) & (s_s + 1 < steps) & ~last_steps[s_s])
    at = s_s[leaving] + 1
    by_step = np.argsort(at, kind="stable")
    leaving, at = leaving[by_step], at[by_step]
    # SceneUpdate.deletions = [{timestamp, type MATCHING_ID (0, so not written), id}], spliced per the wire format.
    ids = ByteTable.of_items([_ID_KEY + varint(len(b)) + b for b in (n.encode() for n in names)])
    stamped = concatenated([(stamps, np.arange(steps))], _STAMP_KEY)
    records, _ = concatenated([(stamped, at), (ids, t_s[leaving])], _DELETIONS_KEY).objects()
    return at.astype(np.int64), records.tolist()


def stamp_table(ns: NDArrayInt) -> ByteTable:
    """``timestamp_bytes`` of each of ``ns``, by numpy (before the epoch: by the ``Timestamp`` class)."""
    if len(ns) and int(np.min(ns)) < 0:
        return ByteTable.of_items([timestamp_bytes(t) for t in np.asarray(ns).tolist()])
    return timestamps(ns)


def timestamp_bytes(ns: int) -> bytes:
    """``serialize(timestamp(ns))`` without building the message (a few times faster; ingest makes one per step
    and per departing agent)."""
    if ns < 0:
        return serialize(timestamp(ns))
    seconds, nanos = divmod(ns, 1_000_000_000)
    return (b"\x08" + varint(seconds) if seconds else b"") + (b"\x10" + varint(nanos) if nanos else b"")


_ID_KEY = field_key(SceneEntityDeletion.ID_FIELD_NUMBER)
_STAMP_KEY = field_key(SceneEntityDeletion.TIMESTAMP_FIELD_NUMBER)
_DELETIONS_KEY = field_key(SceneUpdate.DELETIONS_FIELD_NUMBER)
if SceneEntityDeletion.MATCHING_ID != 0:  # the splice above leaves the type out, as proto3 does for 0
    raise RuntimeError("SceneEntityDeletion.MATCHING_ID is not the default")


@cache
def _pose_template(frame: str, turned: bool) -> Template:
    def build(v: Sequence[float]) -> PoseInFrame:
        turn = Quaternion(z=v[2], w=v[3]) if turned else Quaternion(w=1.0)
        return PoseInFrame(frame_id=frame, pose=Pose(position=Vector3(x=v[0], y=v[1]), orientation=turn))

    return Template(build, 4 if turned else 2)


@cache
def _transform_template(parent: str, child: str, turned: bool) -> Template:
    def build(v: Sequence[float]) -> FrameTransform:
        turn = Quaternion(z=v[2], w=v[3]) if turned else Quaternion(w=1.0)
        return FrameTransform(parent_frame_id=parent, child_frame_id=child, translation=Vector3(x=v[0], y=v[1]),
                              rotation=turn)

    return Template(build, 4 if turned else 2)


def _posed_rows(template: Callable[[bool], Template], message_class: Any, ts: NDArrayInt, x: NDArrayFloat,
                y: NDArrayFloat, yaw: NDArrayFloat) -> list[bytes]:
    """Messages of ``message_class`` with a timestamp, then a template's fields: position (x, y), rotation
    by ``yaw`` about z (identity where NaN)."""
    turned = np.isfinite(yaw)
    qz, qw = _half_angles(np.where(turned, yaw, 0.0))
    blocks = []
    for flag in (True, False):
        rows = np.flatnonzero(turned == flag)
        px, py = snap(x[rows], POSITION_QUANTUM), snap(y[rows], POSITION_QUANTUM)
        blocks.append((rows, template(flag).fill([px, py, qz[rows], qw[rows]] if flag else [px, py])))
    # Each message: its timestamp field (numpy-encoded), then its template row.
    rows = np.arange(len(ts))
    stamp = concatenated([(stamp_table(ts), rows)], field_key(message_class.TIMESTAMP_FIELD_NUMBER))
    messages, _ = concatenated([(stamp, rows), (ByteTable.of_rows(len(ts), blocks), rows)]).objects()
    out: list[bytes] = messages.tolist()
    return out


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
    return serialize(FrameTransform(timestamp=timestamp(t_ns), parent_frame_id=parent, child_frame_id=child,
                                     translation=Vector3(x=tx, y=ty, z=tz),
                                     rotation=rotation if rotation is not None else Quaternion(w=1.0)))


def log_centre(x: NDArrayFloat, y: NDArrayFloat) -> tuple[float, float]:
    """Centre of the box around a log's finite positions (metres, world frame); (0, 0) when there are none."""
    ok = np.isfinite(x) & np.isfinite(y)
    if not ok.any():
        return 0.0, 0.0
    return (float(x[ok].min() + x[ok].max()) / 2.0, float(y[ok].min() + y[ok].max()) / 2.0)
