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
and the centre. What each channel is for and costs, and why both the JSON and the scene stay: ``docs/formats.md``
(MCAP outputs).

Speed: the logs of an ingest batch are built a group at a time (``GROUP_ROWS``; ``_BatchMessages``: one pass of
numpy over the group's rows for the scenes, the JSON, the ego's poses and transforms; tracks coded apart per log),
each message left as pieces (``bulk.Pieces``: a scene row is one piece, cut out of a numpy block) that are joined
only into its log's chunk, and each file is laid out whole by ``logpipe.mcap.bulk``, compressed and written on a
thread while the next group is built (``bulk.BackgroundWrites``); ``make bench``'s ``mcap_channels`` measures each
channel's share.
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
from logpipe.mcap.bulk import BackgroundWrites, BulkMcap, Pieces
from logpipe.mcap.map_scene import MAP_TOPIC, map_scene_update
from logpipe.storage.io import as_numpy
from logpipe.storage.write_journal import record_written_files
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


def _register(writer: BulkMcap, topic: str, schema_name: str) -> int:
    return writer.channel(topic, "json", (schema_name, "jsonschema", json_schema_bytes(schema_name)))


def _register_protobuf(writer: BulkMcap, topic: str, message_class: Any) -> int:
    return writer.channel(topic, fx.MESSAGE_ENCODING,
                          (fx.schema_name(message_class), fx.SCHEMA_ENCODING, fx.schema_data(message_class)))


def _codes(column: pa.ChunkedArray) -> tuple[np.ndarray, list[Any]]:
    """Integer codes of a column and the (Python) values they index."""
    encoded = pc.dictionary_encode(column).combine_chunks()
    return as_numpy(encoded.indices).astype(np.int64), encoded.dictionary.to_pylist()


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


@dataclass(frozen=True)
class JsonColumn:
    """A column's values as JSON texts, all rows in one comma-separated byte string: rows ``lo:hi`` are
    ``text[offsets[lo]:offsets[hi] - 1]``, so a step's array is one slice, not a join of a text per row."""

    text: bytes
    offsets: np.ndarray

    @classmethod
    def of_texts(cls, texts: list[str]) -> JsonColumn:
        """The column of these per-row texts."""
        lengths = np.fromiter(map(len, texts), np.int64, len(texts)) + 1
        return cls((",".join(texts) + ",").encode(), np.concatenate([[0], np.cumsum(lengths)]))

    @classmethod
    def of_floats(cls, values: np.ndarray) -> JsonColumn:
        """The column of these floats (``_json_floats``): orjson's array text itself where it equals
        ``json.dumps``'s, cut at its commas (no string per row)."""
        values = np.ascontiguousarray(values, dtype=np.float64)
        magnitude = np.abs(values)
        if not len(values) or not bool(np.isfinite(values).all()) or bool(
                (((magnitude < 1e-4) & (magnitude > 0)) | (magnitude >= 1e16)).any()):
            return cls.of_texts(_json_floats(values))
        text = orjson.dumps(values, option=orjson.OPT_SERIALIZE_NUMPY)[1:-1] + b","
        commas = np.flatnonzero(np.frombuffer(text, np.uint8) == ord(","))
        return cls(text, np.concatenate([[0], commas + 1]))

    @classmethod
    def of_codes(cls, codes: np.ndarray, values: list[Any]) -> JsonColumn:
        """The column of rows holding ``values[codes]``, each distinct value encoded once."""
        texts = [json.dumps(v).encode() + b"," for v in values]
        table = np.empty(len(texts), object)
        table[:] = texts
        lengths = np.fromiter(map(len, texts), np.int64, len(texts))[codes]
        return cls(b"".join(table[codes].tolist()), np.concatenate([[0], np.cumsum(lengths)]))


@dataclass
class LogRows:
    """A track table's columns as the texts and arrays the MCAP writer needs, converted once per batch of
    logs (per log, seven column conversions cost more than the log's messages).

    Attributes:
        steps, ts, x, y: (rows,) step, timestamp (ns) and position (m, world frame) of each row.
        heading_values: (rows,) heading in radians, NaN where null.
        json: the JSON texts of ``track_id``, ``object_type``, ``role``, ``x``, ``y`` and, unless the column is
            all null, ``heading`` (null where null), in that order (the ``logpipe.AgentStates`` arrays).
        ego: (rows,) whether the row's role is the ego.
        track_codes, kind_codes: (rows,) codes into ``track_names`` and ``kinds`` ((object type, role) pairs).
    """

    steps: np.ndarray
    ts: np.ndarray
    x: np.ndarray
    y: np.ndarray
    heading_values: np.ndarray
    json: dict[str, JsonColumn]
    ego: np.ndarray
    track_codes: np.ndarray
    track_names: list[str]
    kind_codes: np.ndarray
    kinds: list[tuple[str, str]]

    @classmethod
    def of(cls, tracks: pa.Table, json_heading: bool | None = None) -> LogRows:
        """The rows of ``tracks`` (canonical track-table columns); ``json_heading``: whether the JSON carries
        ``heading`` (None: unless the column is all null in ``tracks``)."""
        heading_col = tracks.column("heading")
        x, y = as_numpy(tracks.column("x")), as_numpy(tracks.column("y"))
        track_codes, track_names = _codes(tracks.column("track_id"))
        type_codes, type_names = _codes(tracks.column("object_type"))
        role_codes, role_names = _codes(tracks.column("role"))
        kind_codes = type_codes * max(len(role_names), 1) + role_codes
        kinds = [(str(t), str(r)) for t in type_names for r in role_names]
        heading = as_numpy(pc.fill_null(heading_col.cast(pa.float64()), math.nan)).astype(np.float64)
        columns = {"track_id": JsonColumn.of_codes(track_codes, track_names),
                   "object_type": JsonColumn.of_codes(type_codes, type_names),
                   "role": JsonColumn.of_codes(role_codes, role_names),
                   "x": JsonColumn.of_floats(x), "y": JsonColumn.of_floats(y)}
        if heading_col.null_count < len(heading_col) if json_heading is None else json_heading:
            null = np.isnan(heading)
            texts = _json_floats(np.where(null, 0.0, heading))
            for i in np.flatnonzero(null).tolist():
                texts[i] = "null"
            columns["heading"] = JsonColumn.of_texts(texts)
        ego_code = role_names.index(Role.EGO.value) if Role.EGO.value in role_names else -1
        return cls(steps=as_numpy(tracks.column("step")), ts=as_numpy(tracks.column("timestamp_ns")), x=x, y=y,
                   heading_values=heading, json=columns, ego=role_codes == ego_code, track_codes=track_codes,
                   track_names=[str(t) for t in track_names], kind_codes=kind_codes, kinds=kinds)

    def __len__(self) -> int:
        return len(self.steps)


def write_log_mcap(log_id: str, tracks: pa.Table | LogRows, target: Path, map_id: str | None,
                   lanes: MapStore | None = None) -> int:
    """Write one log's rows (sorted by step) to ``target``, with ``lanes`` drawn under them when given; returns
    the number of messages (``write_log_mcaps`` for one log).

    ``target`` must be in a folder nobody reads yet (ingest's staging folder, renamed into place whole):
    per-file temp-and-rename would cost more than the MCAP itself at millions of small logs.
    """
    rows = tracks if isinstance(tracks, LogRows) else LogRows.of(tracks)
    with BackgroundWrites() as files:
        counts = _write_logs(rows, [(log_id, 0, len(rows))], {log_id: target}, {log_id: map_id},
                             {log_id: lanes} if lanes is not None else {}, files)
        record_written_files(files.finish())  # written in place (in staging): the proof a later cleanup needs
    return counts[target]


def write_log_mcaps(tracks: pa.Table, metas: list[LogMeta], folder: Path,
                    lanes: dict[str, MapStore] | None = None) -> int:
    """Write ``folder/<log_id>.mcap`` for every log of ``tracks`` (an ingest batch in canonical order, logs
    contiguous), each with its map id from ``metas`` and its ``lanes`` (by log id) where given; returns the number
    of messages written."""
    return sum(n for n, _, _ in write_log_mcap_files(tracks, metas, folder, lanes).values())


GROUP_ROWS = 32_768
"""Rows of the logs built at once. A batch's logs are built a group at a time (still one numpy pass per group, not
per log) so that the files of one group are compressed and written on the writing thread while the next group is
built, instead of all the writing waiting for all the building."""


def write_log_mcap_files(tracks: pa.Table, metas: list[LogMeta], folder: Path,
                         lanes: dict[str, MapStore] | None = None) -> dict[Path, tuple[int, int, str]]:
    """``write_log_mcaps``, returning (messages, bytes, sha256) per file written (what the manifest records, so
    nobody reads the files back to hash them)."""
    # Log boundaries from the log codes (no string per row), every column converted once per group of logs.
    logs = pc.dictionary_encode(tracks.column("log_id")).combine_chunks()
    codes, names = as_numpy(logs.indices), logs.dictionary.to_pylist()
    starts, ends = log_runs(codes)
    runs = [(str(names[codes[lo]]), lo, hi) for lo, hi in zip(starts.tolist(), ends.tolist(), strict=True)]
    maps = {m.log_id: m.map_id for m in metas}
    targets = {log_id: folder / f"{log_id}.mcap" for log_id, _, _ in runs}
    counts: dict[Path, int] = {}
    json_heading = tracks.column("heading").null_count < tracks.num_rows
    with BackgroundWrites() as files:
        group: list[tuple[str, int, int]] = []
        for k, run in enumerate(runs):
            group.append(run)
            if k + 1 < len(runs) and runs[k + 1][2] - group[0][1] <= GROUP_ROWS:
                continue
            lo, hi = group[0][1], group[-1][2]
            # Whether the JSON has ``heading`` stays the batch's choice, as when the batch was built at once.
            rows = LogRows.of(tracks.slice(lo, hi - lo), json_heading)
            counts |= _write_logs(rows, [(i, a - lo, b - lo) for i, a, b in group], targets, maps, lanes or {},
                                  files)
            group = []
        written = files.finish()
    record_written_files(written)  # written in place (in staging): the proof a later cleanup needs
    return {target: (counts[target], *written[target]) for target in counts}


def _write_logs(rows: LogRows, runs: list[tuple[str, int, int]], targets: dict[str, Path],
                maps: dict[str, str | None], lanes: dict[str, MapStore], files: BackgroundWrites) -> dict[Path, int]:
    """Every log's MCAP, its messages built for all the logs at once (``_BatchMessages``) and cut per log, handed
    to ``files`` to be finished and written; the number of messages per file."""
    batch = _BatchMessages.of(rows, runs)
    written: dict[Path, int] = {}
    for i, (log_id, lo, hi) in enumerate(runs):
        a, b = batch.log_steps[i], batch.log_steps[i + 1]
        e, f = batch.log_ego[i], batch.log_ego[i + 1]
        step_ts = batch.step_ts[a:b]
        cx, cy = fx.log_centre(rows.x[lo:hi], rows.y[lo:hi])
        writer = BulkMcap()
        writer.metadata("logpipe", {"log_id": log_id, "map_id": maps.get(log_id) or "", "frame_id": WORLD_FRAME,
                                    "root_frame_id": LOG_FRAME, "centre_x": repr(cx), "centre_y": repr(cy)})
        writer.log(_register(writer, AGENTS_TOPIC, "logpipe.AgentStates"), step_ts, batch.agents.part(a, b))
        writer.log(_register_protobuf(writer, SCENE_TOPIC, SceneUpdate), step_ts, batch.scenes.part(a, b))
        tf = _register_protobuf(writer, TF_TOPIC, FrameTransform)
        t0 = step_ts[:1].tolist()
        writer.log(tf, t0, [fx.frame_transform(LOG_FRAME, WORLD_FRAME, t, (-cx, -cy, 0.0)) for t in t0])
        count = 2 * (b - a) + len(t0) + 2 * (f - e)
        if f > e:
            ego_ts = batch.ego_ts[e:f]
            writer.log(_register_protobuf(writer, EGO_TOPIC, PoseInFrame), ego_ts, batch.ego_poses[e:f])
            writer.log(tf, ego_ts, batch.ego_transforms[e:f])
        store = lanes.get(log_id)
        if store is not None:
            map_channel = _register_protobuf(writer, MAP_TOPIC, SceneUpdate)
            writer.log(map_channel, t0, [map_scene_update(store, WORLD_FRAME, t) for t in t0])
            count += len(t0)
        files.submit(writer.prepare(), targets[log_id])
        written[targets[log_id]] = count
    return written


@dataclass
class _BatchMessages:
    """The messages of a batch of logs, built for all of them at once, in log order.

    Attributes:
        step_ts: (steps,) each step's time (ns); ``agents``, ``scenes``: its ``/logpipe/agents`` JSON and
            ``/logpipe/scene`` update; ``log_steps``: (logs + 1,) log i's steps are ``log_steps[i]:log_steps[i + 1]``.
        ego_ts, ego_poses, ego_transforms: each ego row's time, pose and ``world`` -> ``ego`` transform;
            ``log_ego``: (logs + 1,) bounds of each log's, like ``log_steps``.
    """

    step_ts: np.ndarray
    agents: Pieces
    scenes: Pieces
    log_steps: list[int]
    ego_ts: np.ndarray
    ego_poses: list[bytes]
    ego_transforms: list[bytes]
    log_ego: list[int]

    @classmethod
    def of(cls, rows: LogRows, runs: list[tuple[str, int, int]]) -> _BatchMessages:
        """The messages of ``runs`` (log id, first row, end row) of ``rows``."""
        n = len(rows)
        log_of_row = np.zeros(n, np.int64)
        for i, (_, lo, hi) in enumerate(runs):
            log_of_row[lo:hi] = i
        new_step = np.ones(n, bool)
        new_step[1:] = (np.diff(rows.steps) != 0) | (np.diff(log_of_row) != 0)
        starts = np.flatnonzero(new_step)
        step = np.cumsum(new_step) - 1
        log_steps = np.searchsorted(starts, [lo for _, lo, _ in runs] + [n]).tolist()
        # Tracks coded apart per log: a track id that recurs in another log of the batch is another agent.
        width = max(len(rows.track_names), 1)
        tracks_local, first_row, track_index = np.unique(log_of_row * width + rows.track_codes, return_index=True,
                                                         return_inverse=True)
        # Each log's tracks numbered in the order they first appear in it (what orders a step's deletions), so a
        # log's bytes do not depend on which other logs share its batch or group.
        by_first = np.argsort(first_row, kind="stable")
        rank = np.empty(len(by_first), np.int64)
        rank[by_first] = np.arange(len(by_first))
        tracks_local, track_index = tracks_local[by_first], rank[track_index.reshape(-1)]
        yaw, has_heading = fx.display_headings(track_index, rows.ts, rows.x, rows.y, rows.heading_values)
        names = [rows.track_names[c % width] for c in tracks_local.tolist()]
        agents = fx.LogAgents(steps=step, ts=rows.ts, x=rows.x, y=rows.y, yaw=yaw, has_heading=has_heading,
                              track=track_index, track_names=names, kind=rows.kind_codes, kinds=rows.kinds)
        scenes = fx.agent_scene_pieces(agents, WORLD_FRAME, np.asarray(log_steps[:-1], np.int64))
        ego = np.flatnonzero(rows.ego)
        heading = np.where(has_heading[ego], yaw[ego], np.nan)
        ego_ts, ex, ey = rows.ts[ego], rows.x[ego], rows.y[ego]
        return cls(
            step_ts=rows.ts[starts], agents=_agent_json(rows, starts, [r[0] for r in runs], log_of_row),
            scenes=scenes, log_steps=log_steps, ego_ts=ego_ts,
            ego_poses=fx.poses_in_frame(WORLD_FRAME, ego_ts, ex, ey, heading),
            ego_transforms=fx.frame_transforms(WORLD_FRAME, EGO_FRAME, ego_ts, ex, ey, heading),
            log_ego=np.searchsorted(ego, [lo for _, lo, _ in runs] + [n]).tolist())


def _agent_json(rows: LogRows, starts: np.ndarray, log_ids: list[str], log_of_row: np.ndarray) -> Pieces:
    """The ``/logpipe/agents`` message of each step (rows ``starts[i]:starts[i + 1]``): the same bytes as
    ``json.dumps`` of the documented dict (key order kept), as pieces: a head per step, then per array its key,
    a view of the step's rows in its ``JsonColumn`` (no copy until the chunk is joined) and its bracket."""
    frame_text = json.dumps(WORLD_FRAME)
    log_texts = [json.dumps(i) for i in log_ids]
    ends = np.append(starts[1:], len(rows))
    heads = [f'{{"log_id":{log_texts[log]},"timestamp_ns":{t},"step":{step},"frame_id":{frame_text}'.encode()
             for t, step, log in zip(rows.ts[starts].tolist(), rows.steps[starts].tolist(),
                                     log_of_row[starts].tolist(), strict=True)]
    width = 2 + 3 * len(rows.json)  # pieces per message
    objects = np.empty(len(starts) * width, object)
    lengths = np.empty(len(starts) * width, np.int64)
    objects[0::width], lengths[0::width] = heads, np.fromiter(map(len, heads), np.int64, len(heads))
    for j, (name, column) in enumerate(rows.json.items()):
        key, view = f',"{name}":['.encode(), memoryview(column.text)
        lo, hi = column.offsets[starts], column.offsets[ends] - 1
        objects[1 + 3 * j :: width], lengths[1 + 3 * j :: width] = key, len(key)
        objects[2 + 3 * j :: width] = [view[a:b] for a, b in zip(lo.tolist(), hi.tolist(), strict=True)]
        lengths[2 + 3 * j :: width] = hi - lo
        objects[3 + 3 * j :: width], lengths[3 + 3 * j :: width] = b"]", 1
    objects[width - 1 :: width], lengths[width - 1 :: width] = b"}", 1
    return Pieces(objects, lengths, np.arange(0, len(objects) + 1, width, dtype=np.int64))
