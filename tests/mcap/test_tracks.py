"""Ingest's per-log MCAP: the agents' JSON is exactly ``json.dumps`` of the documented message; the ego's pose
and frame are Foxglove Protobuf messages (tests/mcap/test_foxglove.py checks every channel on real logs)."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pyarrow as pa
import pytest
from mcap.reader import make_reader

from logpipe.contracts import conform, tracks_schema
from logpipe.mcap import foxglove as fx
from logpipe.mcap.tracks import AGENTS_TOPIC, EGO_TOPIC, LOG_FRAME, SCENE_TOPIC, TF_TOPIC, WORLD_FRAME, write_log_mcap

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
        # Per step agents + scene, the root transform, per ego row its pose + transform.
        assert write_log_mcap("L", _log(encoded), target, "MIA") == 2 * 2 + 1 + 2 * 2
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
        poses = [fx.MESSAGE_CLASSES["foxglove.PoseInFrame"].FromString(d) for d in got[EGO_TOPIC]]
        assert [(p.timestamp.seconds, p.timestamp.nanos) for p in poses] == [(0, 10), (0, 20)]
        # Drawn positions and rotations are snapped (foxglove.POSITION_QUANTUM: 0.1 m is drawn at 102/1024 m).
        assert [(p.frame_id, p.pose.position.x, p.pose.position.y) for p in poses] == [
            (WORLD_FRAME, 102 / 1024, 0.0), (WORLD_FRAME, 2.5, 0.5)]
        assert abs(poses[0].pose.orientation.z - math.sin(0.25)) <= fx.ROTATION_QUANTUM / 2  # the heading, halved
        transforms = [fx.MESSAGE_CLASSES["foxglove.FrameTransform"].FromString(d) for d in got[TF_TOPIC]]
        assert [(t.parent_frame_id, t.child_frame_id) for t in transforms] == [
            (LOG_FRAME, WORLD_FRAME), (WORLD_FRAME, "ego"), (WORLD_FRAME, "ego")]
        # The root sits at the centre of the positions' box: x in [-3, 123456.789], y in [0, 7.25].
        assert (transforms[0].translation.x, transforms[0].translation.y) == (-(123456.789 - 3.0) / 2, -3.625)
        scenes = [fx.MESSAGE_CLASSES["foxglove.SceneUpdate"].FromString(d) for d in got[SCENE_TOPIC]]
        assert [[e.id for e in s.entities] for s in scenes] == [["ego", "a"], ["ego", "a", "b"]]


def test_float_texts_equal_json_dumps_across_exponent_ranges() -> None:
    import numpy as np

    from logpipe.mcap.tracks import _json_floats

    rng = np.random.default_rng(0)
    tricky = [0.0, -0.0, 1.0, -2.5, 1e-4, 9.999e-5, 1e-5, -3.7e-7, 5e-324, 0.1, 1 / 3, 123456.789, 2.0**53,
              9.999999e15, 1e16, -1.5e16, 1e300, 1.7976931348623157e308]
    values = np.concatenate([np.array(tricky), rng.uniform(-5000, 5000, 2000), rng.normal(0, 1e-4, 2000),
                             10.0 ** rng.uniform(-12, 20, 2000)])
    assert _json_floats(values) == [json.dumps(v) for v in values.tolist()]
    assert _json_floats(np.array([1.0, float("nan"), float("inf")])) == ["1.0", "NaN", "Infinity"]
    assert _json_floats(np.array([], dtype=np.float64)) == []


def test_a_batch_of_logs_writes_one_file_per_log_as_each_log_alone(tmp_path: Path) -> None:
    from logpipe.mcap.tracks import write_log_mcaps
    from logpipe.types import LogMeta

    second = _log(False).set_column(0, _log(False).schema.field("log_id"), pa.array(["M"] * 5))
    batch = pa.concat_tables([_log(False), second])
    metas = [LogMeta("L", "argoverse1", "L.csv", "0" * 64, "MIA", 10.0),
             LogMeta("M", "argoverse1", "M.csv", "1" * 64, None, 10.0)]
    messages = write_log_mcaps(batch, metas, tmp_path / "batch")
    assert sorted(p.name for p in (tmp_path / "batch").iterdir()) == ["L.mcap", "M.mcap"]
    alone = write_log_mcap("L", _log(False), tmp_path / "L.mcap", "MIA")
    alone += write_log_mcap("M", second, tmp_path / "M.mcap", None)
    assert messages == alone
    for name in ("L.mcap", "M.mcap"):
        assert (tmp_path / "batch" / name).read_bytes() == (tmp_path / name).read_bytes()


def test_json_columns_cut_to_each_rows_json_dumps() -> None:
    import numpy as np

    from logpipe.mcap.tracks import JsonColumn

    rng = np.random.default_rng(1)
    plain = rng.uniform(-5000, 5000, 500)  # orjson's own text, cut at its commas
    tricky = np.concatenate([plain, [1e-5, 0.0, -0.0, 2.0**60]])  # repr fix-ups: the per-row path
    for values in (plain, tricky):
        column = JsonColumn.of_floats(values)
        for lo, hi in ((0, len(values)), (3, 17), (len(values) - 1, len(values))):
            text = column.text[column.offsets[lo] : column.offsets[hi] - 1].decode()
            assert text == ",".join(json.dumps(v) for v in values[lo:hi].tolist())
    names = JsonColumn.of_codes(np.array([2, 0, 2, 1]), ["a", 'q"uote', "é"])
    assert names.text[: names.offsets[4] - 1].decode() == ",".join(json.dumps(v) for v in ["é", "a", "é", 'q"uote'])


def test_a_logs_file_does_not_depend_on_the_logs_built_with_it(tmp_path: Path,
                                                              monkeypatch: pytest.MonkeyPatch) -> None:
    # Two agents leave log L at the same step, so its scene there deletes both: the deletions follow the order the
    # agents first appear in L, whatever log K (built with it, the same track ids in another order) holds.
    import logpipe.mcap.tracks as tracks_module
    from logpipe.types import LogMeta

    def log(log_id: str, steps: list[list[str]]) -> pa.Table:
        rows = [(s, t) for s, names in enumerate(steps) for t in names]
        return conform(pa.table({
            "log_id": [log_id] * len(rows), "timestamp_ns": pa.array([100 * s for s, _ in rows], pa.int64()),
            "step": pa.array([s for s, _ in rows], pa.int32()), "track_id": [t for _, t in rows],
            "object_type": ["pedestrian"] * len(rows), "role": ["other"] * len(rows),
            "x": [float(i) for i in range(len(rows))], "y": [0.5] * len(rows),
            "heading": pa.array([None] * len(rows), pa.float64()), "source_type": ["X"] * len(rows)}), tracks_schema())

    k, lone = log("K", [["b", "a"], ["c"], ["c"]]), log("L", [["a", "b", "c"], ["c"], ["c"]])
    metas = [LogMeta(i, "ethucy", f"{i}.txt", str(n) * 64, None, 10.0) for n, i in enumerate("KL")]
    write_log_mcap("L", lone, tmp_path / "L.mcap", None)
    for group_rows in (1, 1 << 20):  # each log a group of its own, and both logs in one group
        monkeypatch.setattr(tracks_module, "GROUP_ROWS", group_rows)
        folder = tmp_path / f"batch-{group_rows}"
        tracks_module.write_log_mcaps(pa.concat_tables([k, lone]), metas, folder)
        assert (folder / "L.mcap").read_bytes() == (tmp_path / "L.mcap").read_bytes()
    with (tmp_path / "L.mcap").open("rb") as fh:
        scenes = [m.data for _, c, m in make_reader(fh).iter_messages() if c.topic == SCENE_TOPIC]
    update = fx.MESSAGE_CLASSES["foxglove.SceneUpdate"].FromString(scenes[1])
    assert [d.id for d in update.deletions] == ["a", "b"]
