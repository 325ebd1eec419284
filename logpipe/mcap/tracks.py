"""MCAP output: each ingested log as a file a log viewer opens (Foxglove; ``logpipe.mcap.foxglove`` says what it
draws and why the frames are what they are).

Channels:
* ``/logpipe/agents`` (``logpipe.AgentStates``, JSON): every agent at each step, column-wise — one JSON
  message per step instead of one per agent keeps files small and writing fast.
* ``/logpipe/scene`` (``foxglove.SceneUpdate``, Protobuf): per step a box (and heading arrow) per agent,
  entity id = track id, in frame ``world``.
* ``/logpipe/tf`` (``foxglove.FrameTransform``, Protobuf): ``log_centre`` → ``world`` once (``world``'s
  origin at minus the centre of the log's positions, so the 3D panel opens on the log), and ``world`` →
  ``ego`` at each ego row.
* ``/logpipe/ego_pose`` (``foxglove.PoseInFrame``, Protobuf): the ego in ``world``.
* ``/logpipe/map`` (``foxglove.SceneUpdate``, Protobuf), for logs whose input carries its map (CommonRoad): the
  lanes once, under the agents (``logpipe.mcap.map_scene``).
Message log times are the true timestamps of the steps; the ``logpipe`` metadata record names the frames
and the centre.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from functools import cache
from pathlib import Path
from typing import Any

import numpy as np
import orjson
import pyarrow as pa
import pyarrow.compute as pc
from foxglove_schemas_protobuf.FrameTransform_pb2 import FrameTransform
from foxglove_schemas_protobuf.PoseInFrame_pb2 import PoseInFrame
from foxglove_schemas_protobuf.SceneUpdate_pb2 import SceneUpdate

from logpipe.contracts import json_schema
from logpipe.dataset.shards import log_runs
from logpipe.maps import MapStore
from logpipe.mcap import foxglove as fx
from logpipe.mcap.map_scene import MAP_TOPIC, map_scene_update
from logpipe.mcap.native import NativeMcap
from logpipe.storage.io import as_numpy
from logpipe.types import LogMeta, Role

AGENTS_TOPIC = "/logpipe/agents"
SCENE_TOPIC = "/logpipe/scene"
TF_TOPIC = "/logpipe/tf"
EGO_TOPIC = "/logpipe/ego_pose"
WORLD_FRAME = "world"
"""The frame of the tracks' x/y (and of every agent entity)."""
LOG_FRAME = "log_centre"
"""Root of an ingest MCAP's transform tree, at the centre of the log's positions."""
EGO_FRAME = "ego"


@cache
def json_schema_bytes(schema_name: str) -> bytes:
    """The JSON Schema of a ``jsonschema`` MCAP channel (``schemas/``), as stored in the MCAP's schema record."""
    return json.dumps(json_schema(schema_name), sort_keys=True).encode()


def _register(writer: NativeMcap, topic: str, schema_name: str) -> Any:
    return writer.channel(topic, "json", (schema_name, "jsonschema", json_schema_bytes(schema_name)))


def _register_protobuf(writer: NativeMcap, topic: str, message_class: Any) -> Any:
    return writer.channel(topic, fx.MESSAGE_ENCODING,
                          (fx.schema_name(message_class), fx.SCHEMA_ENCODING, fx.schema_data(message_class)))


def _codes(column: pa.ChunkedArray) -> tuple[np.ndarray, list[str]]:
    """Integer codes of a string (or dictionary) column and the names they index."""
    encoded = pc.dictionary_encode(column).combine_chunks()
    return as_numpy(encoded.indices).astype(np.int64), [str(v) for v in encoded.dictionary.to_pylist()]


def _python_list(column: pa.ChunkedArray) -> list[Any]:
    """A column as Python values (None for nulls). Through numpy when there are no nulls: ``to_pylist``
    builds an Arrow scalar per value, ~10x slower, and it was most of the cost of writing an MCAP."""
    values: list[Any] = column.to_pylist() if column.null_count else as_numpy(column).tolist()
    return values


def _json_texts(values: list[Any]) -> list[str]:
    """JSON text of each value, each distinct value encoded once (ids and labels repeat every step)."""
    encoded = {v: json.dumps(v) for v in set(values)}
    return [encoded[v] for v in values]


def _json_floats(values: np.ndarray) -> list[str]:
    """JSON text of each float, as ``json.dumps`` writes it (``float.__repr__`` for finite values).

    orjson formats the array ~6x faster than one ``repr`` per value and writes the same shortest
    round-trip digits; the two differ only in where they switch to exponent notation, so values in that
    range (0 < |v| < 1e-4, |v| >= 1e16) are written by ``repr`` itself.
    """
    values = np.ascontiguousarray(values, dtype=np.float64)
    if not bool(np.isfinite(values).all()):
        return [json.dumps(v) for v in values.tolist()]
    texts = orjson.dumps(values, option=orjson.OPT_SERIALIZE_NUMPY)[1:-1].decode().split(",") if len(values) else []
    magnitude = np.abs(values)
    for i in np.flatnonzero(((magnitude < 1e-4) & (magnitude > 0)) | (magnitude >= 1e16)).tolist():
        texts[i] = repr(float(values[i]))
    return texts


@dataclass
class LogRows:
    """A track table's columns as the texts and arrays the MCAP writer needs, converted once per batch of
    logs (per log, seven column conversions cost more than the log's messages) and sliced per log.

    Attributes:
        steps, ts, x, y: (rows,) step, timestamp (ns) and position (m, world frame) of each row.
        heading: (rows,) heading in radians or None per row; None when the column is all null.
        roles: (rows,) role of each row.
        track_ids, object_types, role_texts, xs, ys: JSON texts of each row's values.
        heading_values: (rows,) heading in radians, NaN where null.
        track_codes, kind_codes: (rows,) codes into ``track_names`` and ``kinds`` ((object type, role) pairs).
    """

    steps: np.ndarray
    ts: np.ndarray
    x: np.ndarray
    y: np.ndarray
    heading: list[Any] | None
    roles: list[str]
    track_ids: list[str]
    object_types: list[str]
    role_texts: list[str]
    xs: list[str]
    ys: list[str]
    heading_values: np.ndarray
    track_codes: np.ndarray
    track_names: list[str]
    kind_codes: np.ndarray
    kinds: list[tuple[str, str]]

    @classmethod
    def of(cls, tracks: pa.Table) -> LogRows:
        """The rows of ``tracks`` (canonical track-table columns)."""
        heading_col = tracks.column("heading")
        roles = _python_list(tracks.column("role"))
        x, y = as_numpy(tracks.column("x")), as_numpy(tracks.column("y"))
        track_codes, track_names = _codes(tracks.column("track_id"))
        type_codes, type_names = _codes(tracks.column("object_type"))
        role_codes, role_names = _codes(tracks.column("role"))
        kind_codes = type_codes * max(len(role_names), 1) + role_codes
        kinds = [(t, r) for t in type_names for r in role_names]
        return cls(
            steps=as_numpy(tracks.column("step")), ts=as_numpy(tracks.column("timestamp_ns")), x=x, y=y,
            heading=_python_list(heading_col) if heading_col.null_count < len(heading_col) else None,
            roles=roles, track_ids=_json_texts(_python_list(tracks.column("track_id"))),
            object_types=_json_texts(_python_list(tracks.column("object_type"))), role_texts=_json_texts(roles),
            xs=_json_floats(x), ys=_json_floats(y),
            heading_values=as_numpy(pc.fill_null(heading_col.cast(pa.float64()), math.nan)).astype(np.float64),
            track_codes=track_codes, track_names=track_names, kind_codes=kind_codes, kinds=kinds,
        )

    def slice(self, lo: int, hi: int) -> LogRows:
        """Rows ``lo:hi`` (views of the arrays, copies of the lists; names shared)."""
        heading = None if self.heading is None else self.heading[lo:hi]
        return LogRows(self.steps[lo:hi], self.ts[lo:hi], self.x[lo:hi], self.y[lo:hi], heading, self.roles[lo:hi],
                       self.track_ids[lo:hi], self.object_types[lo:hi], self.role_texts[lo:hi], self.xs[lo:hi],
                       self.ys[lo:hi], self.heading_values[lo:hi], self.track_codes[lo:hi], self.track_names,
                       self.kind_codes[lo:hi], self.kinds)

    def __len__(self) -> int:
        return len(self.steps)


def write_log_mcap(log_id: str, tracks: pa.Table | LogRows, target: Path, map_id: str | None,
                   lanes: MapStore | None = None) -> int:
    """Write one log's rows (sorted by step) to ``target``, with ``lanes`` drawn under them when given; returns
    the number of messages.

    ``target`` must be in a folder nobody reads yet (ingest's staging folder, renamed into place whole):
    per-file temp-and-rename would cost more than the MCAP itself at millions of small logs.
    """
    rows = tracks if isinstance(tracks, LogRows) else LogRows.of(tracks)
    steps, ts, headings = rows.steps, rows.ts, None
    if rows.heading is not None:
        headings = [json.dumps(v) for v in rows.heading]
    # Each row's values as JSON text once, joined per step: the same bytes as json.dumps of the message
    # dict (key order kept), at a fraction of the cost (JSON encoding was the largest part of ingest's MCAP).
    bounds = np.flatnonzero(np.diff(steps)) + 1
    starts = np.concatenate([[0], bounds]).tolist()
    ends = np.concatenate([bounds, [len(steps)]]).tolist()
    ego_role = Role.EGO.value
    ego_rows = [i for i, r in enumerate(rows.roles) if r == ego_role]
    log_text, frame_text = json.dumps(log_id), json.dumps(WORLD_FRAME)
    track_ids, object_types, role_texts, xs, ys = rows.track_ids, rows.object_types, rows.role_texts, rows.xs, rows.ys
    tracks_local, track_index = np.unique(rows.track_codes, return_inverse=True)
    yaw, has_heading = fx.display_headings(track_index, ts, rows.x, rows.y, rows.heading_values)
    agents = fx.LogAgents(steps=steps, ts=ts, x=rows.x, y=rows.y, yaw=yaw, has_heading=has_heading,
                          track=track_index, track_names=[rows.track_names[c] for c in tracks_local.tolist()],
                          kind=rows.kind_codes, kinds=rows.kinds)
    scenes = fx.agent_scene_updates(agents, WORLD_FRAME)
    cx, cy = fx.log_centre(rows.x, rows.y)
    count = 0
    target.parent.mkdir(parents=True, exist_ok=True)
    # Sequences 1, 2, ... per channel (the SDK numbers them) and publish time = log time (ours was the same).
    with NativeMcap(target) as writer:
        writer.metadata("logpipe", {"log_id": log_id, "map_id": map_id or "", "frame_id": WORLD_FRAME,
                                    "root_frame_id": LOG_FRAME, "centre_x": repr(cx), "centre_y": repr(cy)})
        agents_channel = _register(writer, AGENTS_TOPIC, "logpipe.AgentStates")
        scene_channel = _register_protobuf(writer, SCENE_TOPIC, SceneUpdate)
        tf_channel = _register_protobuf(writer, TF_TOPIC, FrameTransform)
        ego = _register_protobuf(writer, EGO_TOPIC, PoseInFrame) if ego_rows else None
        map_channel = _register_protobuf(writer, MAP_TOPIC, SceneUpdate) if lanes is not None else None
        if len(ts):
            t0 = int(ts[0])
            tf_channel.log(fx.frame_transform(LOG_FRAME, WORLD_FRAME, t0, (-cx, -cy, 0.0)), t0, None)
            count += 1
            if map_channel is not None and lanes is not None:
                map_channel.log(map_scene_update(lanes, WORLD_FRAME, t0), t0, None)
                count += 1
        agents_log, scene_log = agents_channel.log, scene_channel.log
        for i, (lo, hi) in enumerate(zip(starts, ends, strict=True)):
            t = int(ts[lo])
            parts = [
                f'{{"log_id":{log_text},"timestamp_ns":{t},"step":{int(steps[lo])},"frame_id":{frame_text}',
                ',"track_id":[', ",".join(track_ids[lo:hi]), '],"object_type":[', ",".join(object_types[lo:hi]),
                '],"role":[', ",".join(role_texts[lo:hi]), '],"x":[', ",".join(xs[lo:hi]),
                '],"y":[', ",".join(ys[lo:hi]), "]",
            ]
            if headings is not None:
                parts += [',"heading":[', ",".join(headings[lo:hi]), "]"]
            parts.append("}")
            agents_log("".join(parts).encode(), t, None)
            scene_log(scenes[i], t, None)
            count += 2
        if ego is not None:
            count += _write_ego(ego, tf_channel, np.asarray(ego_rows), ts, rows.x, rows.y, yaw, has_heading)
    return count


def write_log_mcaps(tracks: pa.Table, metas: list[LogMeta], folder: Path,
                    lanes: dict[str, MapStore] | None = None) -> int:
    """Write ``folder/<log_id>.mcap`` for every log of ``tracks`` (an ingest batch in canonical order, logs
    contiguous), each with its map id from ``metas`` and its ``lanes`` (by log id) where given; returns the number
    of messages written."""
    # Log boundaries from the log codes (no string per row), every column converted once for the batch.
    logs = pc.dictionary_encode(tracks.column("log_id")).combine_chunks()
    codes, names = as_numpy(logs.indices), logs.dictionary.to_pylist()
    maps = {m.log_id: m.map_id for m in metas}
    rows = LogRows.of(tracks)
    messages = 0
    starts, ends = log_runs(codes)
    for lo, hi in zip(starts.tolist(), ends.tolist(), strict=True):
        log_id = names[codes[lo]]
        messages += write_log_mcap(log_id, rows.slice(lo, hi), folder / f"{log_id}.mcap", maps.get(log_id),
                                   (lanes or {}).get(log_id))
    return messages


def _write_ego(
    pose_channel: Any, tf_channel: Any, rows: np.ndarray, ts: np.ndarray, x: np.ndarray,
    y: np.ndarray, yaw: np.ndarray, has_heading: np.ndarray,
) -> int:
    """The ego's pose and ``world`` → ``ego`` transform at each ego row (not turned where it has no heading)."""
    times, ex, ey = ts[rows], x[rows], y[rows]
    heading = np.where(has_heading[rows], yaw[rows], np.nan)
    poses = fx.poses_in_frame(WORLD_FRAME, times, ex, ey, heading)
    transforms = fx.frame_transforms(WORLD_FRAME, EGO_FRAME, times, ex, ey, heading)
    for t, pose, tf in zip(times.tolist(), poses, transforms, strict=True):
        pose_channel.log(pose, t, None)
        tf_channel.log(tf, t, None)
    return 2 * len(poses)
