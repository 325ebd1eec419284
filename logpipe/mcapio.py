"""MCAP output: each ingested log as a file a log viewer opens (Foxglove), with JSON-encoded channels.

Channels:
* ``/logpipe/agents`` (``logpipe.AgentStates``): every agent at each step, column-wise — one JSON message
  per step instead of one per agent keeps files small and writing fast.
* ``/logpipe/ego_pose`` (``foxglove.PoseInFrame``): the ego, so the 3D panel can follow it.
Message log times are the true timestamps of the steps.
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
from mcap.writer import CompressionType, Writer

from logpipe import __version__
from logpipe.contracts import json_schema
from logpipe.io import as_numpy
from logpipe.types import Role

AGENTS_TOPIC = "/logpipe/agents"
EGO_TOPIC = "/logpipe/ego_pose"
WORLD_FRAME = "world"


@cache
def _schema_bytes(schema_name: str) -> bytes:
    return json.dumps(json_schema(schema_name), sort_keys=True).encode()


def _register(writer: Writer, topic: str, schema_name: str) -> int:
    schema_id = writer.register_schema(name=schema_name, encoding="jsonschema", data=_schema_bytes(schema_name))
    return writer.register_channel(topic=topic, message_encoding="json", schema_id=schema_id)


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

    @classmethod
    def of(cls, tracks: pa.Table) -> LogRows:
        """The rows of ``tracks`` (canonical track-table columns)."""
        heading_col = tracks.column("heading")
        roles = _python_list(tracks.column("role"))
        x, y = as_numpy(tracks.column("x")), as_numpy(tracks.column("y"))
        return cls(
            steps=as_numpy(tracks.column("step")), ts=as_numpy(tracks.column("timestamp_ns")), x=x, y=y,
            heading=_python_list(heading_col) if heading_col.null_count < len(heading_col) else None,
            roles=roles, track_ids=_json_texts(_python_list(tracks.column("track_id"))),
            object_types=_json_texts(_python_list(tracks.column("object_type"))), role_texts=_json_texts(roles),
            xs=_json_floats(x), ys=_json_floats(y),
        )

    def slice(self, lo: int, hi: int) -> LogRows:
        """Rows ``lo:hi`` (views of the arrays, copies of the lists)."""
        heading = None if self.heading is None else self.heading[lo:hi]
        return LogRows(self.steps[lo:hi], self.ts[lo:hi], self.x[lo:hi], self.y[lo:hi], heading, self.roles[lo:hi],
                       self.track_ids[lo:hi], self.object_types[lo:hi], self.role_texts[lo:hi], self.xs[lo:hi],
                       self.ys[lo:hi])

    def __len__(self) -> int:
        return len(self.steps)


def write_log_mcap(log_id: str, tracks: pa.Table | LogRows, target: Path, map_id: str | None) -> int:
    """Write one log's rows (sorted by step) to ``target``; returns the number of messages.

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
    count = 0
    target.parent.mkdir(parents=True, exist_ok=True)
    with target.open("wb") as fh:
        writer = Writer(fh, compression=CompressionType.ZSTD)
        writer.start(profile="", library=f"logpipe {__version__}")
        writer.add_metadata("logpipe", {"log_id": log_id, "map_id": map_id or "", "frame_id": WORLD_FRAME})
        agents = _register(writer, AGENTS_TOPIC, "logpipe.AgentStates")
        ego = _register(writer, EGO_TOPIC, "foxglove.PoseInFrame") if ego_rows else None
        for lo, hi in zip(starts, ends, strict=True):
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
            writer.add_message(agents, log_time=t, publish_time=t, data="".join(parts).encode(), sequence=count)
            count += 1
        if ego is not None:
            count += _write_ego(writer, ego, ego_rows, ts, rows.x, rows.y, rows.heading)
        writer.finish()  # type: ignore[no-untyped-call]
    return count


def _write_ego(
    writer: Writer, channel: int, rows: list[int], ts: np.ndarray, x: np.ndarray, y: np.ndarray,
    heading: list[Any] | None,
) -> int:
    ex, ey = x[rows], y[rows]
    # Heading from the source when given, else from motion (forward difference, last one repeated).
    if heading is not None and all(heading[r] is not None for r in rows):
        yaw = np.array([heading[r] for r in rows], dtype=np.float64)
    else:
        dx = np.diff(ex, append=ex[-1:]) if len(rows) > 1 else np.zeros(1)
        dy = np.diff(ey, append=ey[-1:]) if len(rows) > 1 else np.zeros(1)
        if len(rows) > 1:
            dx[-1], dy[-1] = dx[-2], dy[-2]
        yaw = np.arctan2(dy, dx)
    # json.dumps of {"timestamp", "frame_id", "pose": {"position", "orientation"}} written as a template.
    px, py = _json_floats(ex), _json_floats(ey)
    halves = [a / 2.0 for a in yaw.tolist()]  # a rotation about z: (0, 0, sin(yaw/2), cos(yaw/2))
    qz = _json_floats(np.array([math.sin(a) for a in halves], dtype=np.float64))
    qw = _json_floats(np.array([math.cos(a) for a in halves], dtype=np.float64))
    frame = json.dumps(WORLD_FRAME)
    for i, row in enumerate(rows):
        t = int(ts[row])
        pose = (f'{{"timestamp":{{"sec":{t // 1_000_000_000},"nsec":{t % 1_000_000_000}}},"frame_id":{frame},'
                f'"pose":{{"position":{{"x":{px[i]},"y":{py[i]},"z":0.0}},'
                f'"orientation":{{"x":0.0,"y":0.0,"z":{qz[i]},"w":{qw[i]}}}}}}}')
        writer.add_message(channel, log_time=t, publish_time=t, data=pose.encode(), sequence=i)
    return len(rows)
