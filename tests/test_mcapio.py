"""Ingest's per-log MCAP: the JSON it writes is exactly ``json.dumps`` of the documented message."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pyarrow as pa
from mcap.reader import make_reader

from logpipe.contracts import conform, tracks_schema
from logpipe.mcapio import AGENTS_TOPIC, EGO_TOPIC, WORLD_FRAME, write_log_mcap

COMPACT = (",", ":")


def _log(encoded: bool) -> pa.Table:
    tracks = ["ego", "a", "ego", "a", "b"]
    roles = ["ego", "other", "ego", "other", "focal"]
    table = pa.table({
        "log_id": ["L"] * 5, "timestamp_ns": pa.array([10, 10, 20, 20, 20], pa.int64()),
        "step": pa.array([0, 0, 1, 1, 1], pa.int32()),
        "track_id": pa.array(tracks).dictionary_encode() if encoded else tracks,
        "object_type": ["vehicle", "pedestrian", "vehicle", "pedestrian", "cyclist"],
        "role": pa.array(roles).dictionary_encode() if encoded else roles,
        "x": [0.1, 1e-7, 2.5, 123456.789, -3.0], "y": [0.0, 1.0 / 3.0, 0.5, 2.0, 7.25],
        "heading": pa.array([0.5, None, 0.75, 1.0, -2.0], pa.float64()),
        "source_type": ["AV"] * 5,
    })
    return conform(table, tracks_schema(), keep_dictionaries=encoded)


def _messages(path: Path) -> dict[str, list[bytes]]:
    out: dict[str, list[bytes]] = {}
    with path.open("rb") as fh:
        for _, channel, message in make_reader(fh).iter_messages():
            out.setdefault(channel.topic, []).append(message.data)
    return out


def test_messages_equal_json_dumps_of_the_documented_dicts(tmp_path: Path) -> None:
    for encoded in (False, True):
        target = tmp_path / f"{encoded}.mcap"
        assert write_log_mcap("L", _log(encoded), target, "MIA") == 4
        got = _messages(target)
        expected_agents = [
            {"log_id": "L", "timestamp_ns": 10, "step": 0, "frame_id": WORLD_FRAME, "track_id": ["ego", "a"],
             "object_type": ["vehicle", "pedestrian"], "role": ["ego", "other"], "x": [0.1, 1e-7],
             "y": [0.0, 1.0 / 3.0], "heading": [0.5, None]},
            {"log_id": "L", "timestamp_ns": 20, "step": 1, "frame_id": WORLD_FRAME, "track_id": ["ego", "a", "b"],
             "object_type": ["vehicle", "pedestrian", "cyclist"], "role": ["ego", "other", "focal"],
             "x": [2.5, 123456.789, -3.0], "y": [0.5, 2.0, 7.25], "heading": [0.75, 1.0, -2.0]},
        ]
        assert got[AGENTS_TOPIC] == [json.dumps(m, separators=COMPACT).encode() for m in expected_agents]
        poses = [json.loads(d) for d in got[EGO_TOPIC]]
        assert [p["timestamp"] for p in poses] == [{"sec": 0, "nsec": 10}, {"sec": 0, "nsec": 20}]
        assert [p["pose"]["position"] for p in poses] == [{"x": 0.1, "y": 0.0, "z": 0.0},
                                                          {"x": 2.5, "y": 0.5, "z": 0.0}]
        assert poses[0]["pose"]["orientation"]["z"] == math.sin(0.25)  # the source heading, halved
        assert got[EGO_TOPIC][0] == json.dumps(poses[0], separators=COMPACT).encode()


def test_float_texts_equal_json_dumps_across_exponent_ranges() -> None:
    import numpy as np

    from logpipe.mcapio import _json_floats

    rng = np.random.default_rng(0)
    tricky = [0.0, -0.0, 1.0, -2.5, 1e-4, 9.999e-5, 1e-5, -3.7e-7, 5e-324, 0.1, 1 / 3, 123456.789, 2.0**53,
              9.999999e15, 1e16, -1.5e16, 1e300, 1.7976931348623157e308]
    values = np.concatenate([np.array(tricky), rng.uniform(-5000, 5000, 2000), rng.normal(0, 1e-4, 2000),
                             10.0 ** rng.uniform(-12, 20, 2000)])
    assert _json_floats(values) == [json.dumps(v) for v in values.tolist()]
    assert _json_floats(np.array([1.0, float("nan"), float("inf")])) == ["1.0", "NaN", "Infinity"]
    assert _json_floats(np.array([], dtype=np.float64)) == []


def test_log_rows_slices_write_what_each_log_alone_writes(tmp_path: Path) -> None:
    from logpipe.mcapio import LogRows

    two = pa.concat_tables([_log(True), _log(True)])
    rows = LogRows.of(two)
    assert len(rows) == 10
    write_log_mcap("L", rows.slice(5, 10), tmp_path / "sliced.mcap", "MIA")
    write_log_mcap("L", _log(True), tmp_path / "alone.mcap", "MIA")
    assert _messages(tmp_path / "sliced.mcap") == _messages(tmp_path / "alone.mcap")
