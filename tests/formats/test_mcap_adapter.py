"""McapAdapter: the real nav2 recording, the odd/broken real MCAPs, and MCAPs written here in each encoding
(ros2msg/CDR, ros1msg, JSON) to check decoding and that a damaged or cut file fails clearly."""

from __future__ import annotations

import json
import math
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from mcap.writer import Writer
from rosbags.typesys import Stores, get_typestore

from logpipe.errors import SourceError
from logpipe.formats.mcapfile import McapAdapter
from logpipe.formats.ros.mapping import load_mapping
from logpipe.types import SourceFile

SHARED = Path(__file__).resolve().parents[2].parent / "shared" / "data"
MCAPS = SHARED / "mcap"
_absent = pytest.mark.skipif(not MCAPS.is_dir(), reason="needs ../shared/data/mcap")


def needs_shared(test: Callable[..., None]) -> Callable[..., None]:
    """Marks a test as needing ../shared/data (marker ``shared``) and skips it when the folder is absent."""
    return pytest.mark.shared(_absent(test))


T0 = 1_600_000_000_000_000_000


def src(path: Path) -> SourceFile:
    rel = str(path.relative_to(MCAPS)) if path.is_relative_to(MCAPS) else path.name
    return SourceFile(str(path), rel, "0" * 64, 0)


def pose_fields(i: int) -> tuple[float, float, float]:
    """Ground truth of the written recordings: x = 0.5 t, y = 2, yaw = 0.1 t, at 20 Hz."""
    t = i * 0.05
    return 0.5 * t, 2.0, 0.1 * t


SRV_EVENT = b"""service_msgs/ServiceEventInfo info
AddTwoInts_Request[<=1] request
AddTwoInts_Response[<=1] response
================================================================================
MSG: example_interfaces/AddTwoInts_Request
int64 a
int64 b
---
int64 sum
"""


def write_mcap(path: Path, encoding: str, n: int = 60, chunk_size: int = 1024, *, service: bool = False) -> Path:
    """A PoseStamped stream on /ego_pose in one of the encodings (``cdr``, ``ros1``, ``json``)."""
    store = Stores.ROS1_NOETIC if encoding == "ros1" else Stores.ROS2_HUMBLE
    ts = get_typestore(store)
    typ = "geometry_msgs/msg/PoseStamped"
    with path.open("wb") as f:
        w = Writer(f, chunk_size=chunk_size)
        w.start(profile="ros2" if encoding == "cdr" else "", library="logpipe-tests")
        if encoding == "json":
            sid = w.register_schema(typ, "jsonschema", b"{}")
        elif encoding == "ros1":
            sid = w.register_schema("geometry_msgs/PoseStamped", "ros1msg", ts.generate_msgdef(typ)[0].encode())
        else:
            sid = w.register_schema(typ, "ros2msg", ts.generate_msgdef(typ, ros_version=2)[0].encode())
        cid = w.register_channel("/ego_pose", encoding, sid)
        if service:  # a rosbag2 service-event channel: its .srv-style schema does not parse as a message
            srv = w.register_schema("example_interfaces/srv/AddTwoInts_Event", "ros2msg", SRV_EVENT)
            srv_channel = w.register_channel("/add_two_ints/_service_event", "cdr", srv)
            w.add_message(srv_channel, log_time=T0, data=b"\x00\x01\x00\x00", publish_time=T0)
        for i in range(n):
            x, y, yaw = pose_fields(i)
            t_ns = T0 + i * 50_000_000
            stamp = {"sec": t_ns // 10**9, "nanosec": t_ns % 10**9}
            pose = {"position": {"x": x, "y": y, "z": 0.0},
                    "orientation": {"x": 0.0, "y": 0.0, "z": math.sin(yaw / 2), "w": math.cos(yaw / 2)}}  # fmt: skip
            if encoding == "json":
                data = json.dumps({"header": {"stamp": stamp, "frame_id": "odom"}, "pose": pose}).encode()
            else:
                T = ts.types  # noqa: N806
                hdr = {"stamp": T["builtin_interfaces/msg/Time"](**stamp), "frame_id": "odom"}
                if encoding == "ros1":
                    hdr["seq"] = i
                msg = T[typ](
                    header=T["std_msgs/msg/Header"](**hdr),
                    pose=T["geometry_msgs/msg/Pose"](
                        position=T["geometry_msgs/msg/Point"](**pose["position"]),
                        orientation=T["geometry_msgs/msg/Quaternion"](**pose["orientation"]),
                    ),
                )
                data = bytes(ts.serialize_ros1(msg, typ) if encoding == "ros1" else ts.serialize_cdr(msg, typ))
            w.add_message(cid, log_time=t_ns + 1000, data=data, publish_time=t_ns)
        w.finish()
    return path


@pytest.mark.parametrize("encoding", ["cdr", "ros1", "json"])
def test_encodings_decode_to_the_same_track(tmp_path: Path, encoding: str) -> None:
    path = write_mcap(tmp_path / f"pose_{encoding}.mcap", encoding)
    parsed = McapAdapter().read([src(path)], keep_going=False)
    df = parsed.tracks.to_pandas().sort_values("timestamp_ns")
    assert set(df.track_id) == {"ego"} and set(df.role) == {"ego"}
    t = (df.timestamp_ns.to_numpy() - T0) / 1e9
    assert np.allclose(np.diff(t), 0.1) and t[0] == 0 and t[-1] == pytest.approx(2.9)  # header stamps, 10 Hz
    assert np.allclose(df.x, 0.5 * t) and np.allclose(df.y, 2.0) and np.allclose(df.heading, 0.1 * t)
    meta = parsed.logs[0]
    assert meta.log_id == f"pose_{encoding}" and meta.attributes["world_frame"] == "odom"


def test_cut_mcap_keeps_what_precedes_the_cut(tmp_path: Path) -> None:
    """A file cut in the middle: an error by default; with keep_going the complete chunks are used."""
    full = write_mcap(tmp_path / "full.mcap", "cdr", n=200)
    data = full.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: len(data) // 2])
    with pytest.raises(SourceError) as info:
        McapAdapter().read([src(cut)], keep_going=False)
    assert info.value.file == "cut.mcap" and "cut short" in info.value.reason
    parsed = McapAdapter().read([src(cut)], keep_going=True)
    assert len(parsed.failures) == 1 and "cut short" in parsed.failures[0].reason
    df = parsed.tracks.to_pandas()
    assert 20 < len(df) < 100  # about half of the 10 s, and nothing invented past the cut
    assert parsed.logs[0].attributes["indexed"] is False


def test_undecodable_schema_names_the_topic(tmp_path: Path) -> None:
    """A pose channel whose ros2msg schema cannot be parsed: SourceError on that topic, message 1."""
    path = tmp_path / "bad_schema.mcap"
    with path.open("wb") as f:
        w = Writer(f)
        w.start(profile="ros2", library="logpipe-tests")
        sid = w.register_schema("geometry_msgs/msg/PoseStamped", "ros2msg", b"this is not ---- a msg definition")
        cid = w.register_channel("/ego_pose", "cdr", sid)
        w.add_message(cid, log_time=T0, data=b"\x00\x01\x00\x00", publish_time=T0)
        w.finish()
    with pytest.raises(SourceError) as info:
        McapAdapter().read([src(path)], keep_going=False)
    assert info.value.field == "/ego_pose" and info.value.line == 1
    assert "cannot be parsed" in info.value.reason


def test_not_an_mcap(tmp_path: Path) -> None:
    path = tmp_path / "x.mcap"
    path.write_bytes(b"hello world, not an mcap at all")
    with pytest.raises(SourceError) as info:
        McapAdapter().read([src(path)], keep_going=False)
    assert "not a readable MCAP file" in info.value.reason


@needs_shared
def test_nav2_turtlebot_odometry() -> None:
    """The real ROS2 recording: /odom is the ego (the only Odometry; AMCL is the same robot and ignored)."""
    parsed = McapAdapter().read([src(MCAPS / "evo" / "nav2_turtlebot.mcap")], keep_going=False)
    df = parsed.tracks.to_pandas().sort_values("timestamp_ns")
    attrs = parsed.logs[0].attributes
    assert set(df.track_id) == {"ego"}
    assert attrs["topics_used"] == {"/odom": "nav_msgs/msg/Odometry"}
    assert attrs["profile"] == "ros2" and attrs["world_frame"] == "odom"
    assert attrs["message_counts"]["/odom"] == 2639
    # header stamps are simulation time (~929-1025 s) although log times are 2026 wall-clock: ~97 s either way
    span = (df.timestamp_ns.max() - df.timestamp_ns.min()) / 1e9
    assert span == pytest.approx(96.6, abs=0.5) and len(df) == 950
    assert df.vx.notna().all()
    xy = df[["x", "y"]].to_numpy()
    assert np.linalg.norm(np.diff(xy, axis=0), axis=1).sum() == pytest.approx(34.3, abs=0.5)


@needs_shared
def test_nav2_amcl_and_tf_mappings_agree_with_odom() -> None:
    """The same robot via AMCL (map frame) or via tf odom->base_footprint: consistent with /odom."""
    path = MCAPS / "evo" / "nav2_turtlebot.mcap"
    odom = McapAdapter().read([src(path)], keep_going=False).tracks.to_pandas().set_index("timestamp_ns")
    via_tf = McapAdapter(mapping=load_mapping(None, ["ego.tf=odom:base_footprint"])).read([src(path)], keep_going=False)
    tf_df = via_tf.tracks.to_pandas().set_index("timestamp_ns")
    common = odom.index.intersection(tf_df.index)
    assert len(common) > 800
    assert np.abs(odom.loc[common, "x"] - tf_df.loc[common, "x"]).max() < 0.05
    amcl = McapAdapter(
        mapping=load_mapping(
            None,
            ["ego=/amcl_pose"],
        )
    ).read([src(path)], keep_going=False)
    assert amcl.logs[0].attributes["world_frame"] == "map" and amcl.tracks.num_rows > 0


@needs_shared
@pytest.mark.parametrize(
    ("rel", "field", "words"),
    [
        ("keelson/2024-05-15.mcap", None, "invalid magic"),
        ("keelson/test.mcap", None, "keelson.primitives.TimestampedBytes"),
        ("coscene/example.mcap", "/log", "foxglove.Log"),
        ("rosbag2/rosbag2_cpp/test/rosbag2_cpp/bags/only_services.mcap", "/add_two_ints/_service_event",
         "service-event type"),
        ("rosbag2/rosbag2_cpp/test/rosbag2_cpp/bags/topics_and_services.mcap", "/add_two_ints/_service_event",
         "service-event type"),
        ("rosbag2/rosbag2_cpp/test/rosbag2_cpp/bags/only_topics.mcap", None, "rcl_interfaces/msg/ParameterEvent"),
        ("rosbag2/rosbag2_py/test/resources/mcap/reindex_test_bags/multiple_files/multiple_files_0.mcap", "/chatter",
         "std_msgs/msg/String"),
    ],
)  # fmt: skip
def test_real_mcaps_without_tracks_fail_clearly(rel: str, field: str | None, words: str) -> None:
    with pytest.raises(SourceError) as info:
        McapAdapter().read([src(MCAPS / rel)], keep_going=False)
    assert info.value.file == rel and info.value.field == field
    assert words in info.value.reason


@needs_shared
def test_keep_going_over_the_folder() -> None:
    adapter = McapAdapter()
    paths = adapter.discover(MCAPS)
    assert len(paths) == 10
    parsed = adapter.read([src(p) for p in paths], keep_going=True)
    assert [log.log_id for log in parsed.logs] == ["nav2_turtlebot"]
    assert len(parsed.failures) == 9


def test_service_channel_beside_a_pose_topic(tmp_path: Path) -> None:
    """rosbags refuses a whole ROS2 MCAP for one .srv schema; both adapters still read the pose topic."""
    from logpipe.formats.rosbag import RosbagAdapter

    path = write_mcap(tmp_path / "with_service.mcap", "cdr", service=True)
    by_mcap = McapAdapter().read([src(path)], keep_going=False)
    by_rosbag = RosbagAdapter().read([src(path)], keep_going=False)
    assert by_mcap.tracks.num_rows == by_rosbag.tracks.num_rows == 30
    attrs = by_rosbag.logs[0].attributes
    assert "mcap reader" in attrs["storage"] and ".srv schema" in attrs["rosbags_refused"]
    # asked for explicitly, the service channel fails on its own topic and the rest is kept
    mapping = load_mapping(None, ["ego=/ego_pose", "agent=/add_two_ints/_service_event"])
    kept = McapAdapter(mapping=mapping).read([src(path)], keep_going=True)
    assert kept.tracks.num_rows == 30 and [f.field for f in kept.failures] == ["/add_two_ints/_service_event"]
    assert "service-event type" in kept.failures[0].reason


def test_foxglove_json_pose_and_transforms(tmp_path: Path) -> None:
    """A non-ROS MCAP with Foxglove JSON schemas: PoseInFrame agent in 'base', placed by FrameTransform map->base."""
    path = tmp_path / "foxglove.mcap"
    with path.open("wb") as f:
        w = Writer(f)
        w.start(profile="", library="logpipe-tests")
        pose_schema = w.register_schema("foxglove.PoseInFrame", "jsonschema", b"{}")
        tf_schema = w.register_schema("foxglove.FrameTransform", "jsonschema", b"{}")
        pose_ch = w.register_channel("/buoy", "json", pose_schema)
        tf_ch = w.register_channel("/tf", "json", tf_schema)
        for i in range(21):
            t_ns = T0 + i * 100_000_000
            stamp = {"sec": t_ns // 10**9, "nsec": t_ns % 10**9}
            tf = {"timestamp": stamp, "parent_frame_id": "map", "child_frame_id": "base",
                  "translation": {"x": 10.0 + i, "y": 0.0, "z": 0.0},
                  "rotation": {"x": 0.0, "y": 0.0, "z": math.sin(math.pi / 4), "w": math.cos(math.pi / 4)}}  # fmt: skip
            pose = {"timestamp": stamp, "frame_id": "base",
                    "pose": {"position": {"x": 1.0, "y": 0.0, "z": 0.0},
                             "orientation": {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0}}}  # fmt: skip
            w.add_message(tf_ch, log_time=t_ns, data=json.dumps(tf).encode(), publish_time=t_ns)
            w.add_message(pose_ch, log_time=t_ns, data=json.dumps(pose).encode(), publish_time=t_ns)
        w.finish()
    mapping = load_mapping(None, ["agent=/buoy:buoy", "world_frame=map"])
    parsed = McapAdapter(mapping=mapping).read([src(path)], keep_going=False)
    df = parsed.tracks.to_pandas().sort_values("timestamp_ns")
    i = (df.timestamp_ns.to_numpy() - T0) // 100_000_000
    # base is rotated +90 deg at (10 + i, 0): 1 m ahead of it is (10 + i, 1) in map, facing +y
    assert len(df) == 21 and set(df.track_id) == {"buoy"}
    assert np.allclose(df.x, 10.0 + i) and np.allclose(df.y, 1.0) and np.allclose(df.heading, math.pi / 2)
