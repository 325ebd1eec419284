"""Object-array topics → tracks, on bags written here with the rosbags writer (ROS1, ROS2 sqlite3, ROS2 MCAP).

No real bag carries object arrays, so each test writes one with known ground truth: an ego driving and
turning (nav_msgs/Odometry in ``map`` at 50 Hz) and two agents moving at constant velocity, published at 20 Hz
as MarkerArray / derived_object_msgs ObjectArray / Autoware TrackedObjects / vision_msgs Detection3DArray,
either in the world frame or in the ego's ``base_link`` frame (which the adapter must undo with the ego pose).
The non-default types are registered from the .msg files in ``tests/data/rosbags/msg``.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from rosbags.interfaces import Nodetype
from rosbags.rosbag1 import Writer as Writer1
from rosbags.rosbag2 import StoragePlugin
from rosbags.rosbag2 import Writer as Writer2
from rosbags.typesys import Stores, get_types_from_msg, get_typestore
from rosbags.typesys.store import Typestore

from logpipe.formats.mcapfile import McapAdapter
from logpipe.formats.ros.mapping import Mapping, load_mapping
from logpipe.formats.rosbag import RosbagAdapter
from logpipe.types import SourceFile

MSG_DIR = Path(__file__).resolve().parents[1] / "data" / "rosbags" / "msg"
T0 = 1_700_000_000_000_000_000  # ns, on the 10 Hz grid
DURATION_S = 3.0


def typestore_for(store: Stores) -> Typestore:
    """A default typestore plus every .msg file under MSG_DIR."""
    ts = get_typestore(store)
    types: dict[str, Any] = {}
    for path in sorted(MSG_DIR.rglob("*.msg")):
        name = f"{path.parts[-3]}/msg/{path.stem}"
        types.update(get_types_from_msg(path.read_text(), name))
    ts.register(types)
    return ts


_NUMPY = {
    name: getattr(np, name)
    for name in ("float32", "float64", "uint8", "int8", "int16", "uint16", "int32", "uint32", "int64", "uint64")
}


def _default(ts: Typestore, desc: tuple[Any, Any]) -> Any:
    node, spec = desc
    if node == Nodetype.BASE:
        typ = spec[0]
        return "" if typ == "string" else False if typ == "bool" else 0
    if node == Nodetype.NAME:
        return build(ts, spec)
    sub, length = spec
    if sub[0] == Nodetype.BASE and sub[1][0] in _NUMPY:
        return np.zeros(length if node == Nodetype.ARRAY else 0, dtype=_NUMPY[sub[1][0]])
    return [_default(ts, sub) for _ in range(length)] if node == Nodetype.ARRAY else []


def build(ts: Typestore, typename: str, **values: Any) -> Any:
    """A message of ``typename`` with every field defaulted, then ``values`` set."""
    _consts, fields = ts.fielddefs[typename]
    kwargs = {name: _default(ts, desc) for name, desc in fields}
    kwargs.update(values)
    return ts.types[typename](**kwargs)


def quat_z(yaw: float) -> tuple[float, float, float, float]:
    return (0.0, 0.0, math.sin(yaw / 2), math.cos(yaw / 2))


def ego_state(t: float) -> tuple[float, float, float]:
    """Ground-truth ego (x, y, yaw) in map at t seconds: drives +x at 2 m/s while turning at 0.2 rad/s."""
    return 1.0 + 2.0 * t, -2.0 + 0.3 * t, 0.2 * t


AGENTS: dict[str, dict[str, Any]] = {
    # key: (x0, y0, vx, vy), heading, class label per kind, size
    "a": {"p": (10.0, 5.0, 1.0, 0.0), "yaw": 0.0, "size": (4.5, 1.9), "type": "vehicle"},
    "b": {"p": (-3.0, 2.0, 0.0, 0.5), "yaw": math.pi / 2, "size": (0.6, 0.6), "type": "pedestrian"},
}


def agent_state(key: str, t: float) -> tuple[float, float, float]:
    x0, y0, vx, vy = AGENTS[key]["p"]
    return x0 + vx * t, y0 + vy * t, AGENTS[key]["yaw"]


def to_ego(x: float, y: float, yaw: float, t: float) -> tuple[float, float, float]:
    """World pose → pose in the ego's base_link at t."""
    ex, ey, eyaw = ego_state(t)
    dx, dy = x - ex, y - ey
    c, s = math.cos(-eyaw), math.sin(-eyaw)
    return c * dx - s * dy, s * dx + c * dy, yaw - eyaw


def make_pose(ts: Typestore, x: float, y: float, yaw: float) -> Any:
    qx, qy, qz, qw = quat_z(yaw)
    return build(
        ts, "geometry_msgs/msg/Pose",
        position=build(ts, "geometry_msgs/msg/Point", x=x, y=y, z=0.0),
        orientation=build(ts, "geometry_msgs/msg/Quaternion", x=qx, y=qy, z=qz, w=qw),
    )  # fmt: skip


def header(ts: Typestore, t_ns: int, frame: str) -> Any:
    stamp = build(ts, "builtin_interfaces/msg/Time", sec=t_ns // 10**9, nanosec=t_ns % 10**9)
    return build(ts, "std_msgs/msg/Header", stamp=stamp, frame_id=frame)


UUIDS = {"a": bytes(range(16)), "b": bytes(range(100, 116))}
TRACK_IDS = {
    "markers": {"a": "car/1", "b": "pedestrian/2"},
    "derived_objects": {"a": "1", "b": "2"},
    "autoware": {"a": UUIDS["a"].hex(), "b": UUIDS["b"].hex()},
    "detection3d": {"a": "7", "b": "8"},
}
MSGTYPES = {
    "markers": "visualization_msgs/msg/MarkerArray",
    "derived_objects": "derived_object_msgs/msg/ObjectArray",
    "autoware": "autoware_perception_msgs/msg/TrackedObjects",
    "detection3d": "vision_msgs/msg/Detection3DArray",
}


def object_message(ts: Typestore, kind: str, t_ns: int, frame: str) -> Any:
    """One object-array message with both agents at t, in ``frame`` (``map`` or ``base_link``)."""
    t = (t_ns - T0) / 1e9
    poses = {}
    for key in AGENTS:
        x, y, yaw = agent_state(key, t)
        if frame == "base_link":
            x, y, yaw = to_ego(x, y, yaw, t)
        poses[key] = make_pose(ts, x, y, yaw)
    h = header(ts, t_ns, frame)
    vec = "geometry_msgs/msg/Vector3"
    if kind == "markers":
        markers = [
            build(ts, "visualization_msgs/msg/Marker", header=h, ns=TRACK_IDS[kind][k].split("/")[0],
                  id=int(TRACK_IDS[kind][k].split("/")[1]), pose=poses[k],
                  scale=build(ts, vec, x=AGENTS[k]["size"][0], y=AGENTS[k]["size"][1], z=1.0))
            for k in AGENTS
        ]  # fmt: skip
        return build(ts, MSGTYPES[kind], markers=markers)
    if kind == "derived_objects":
        classes = {"a": 6, "b": 4}
        objects = [
            build(ts, "derived_object_msgs/msg/Object", header=h, id=int(TRACK_IDS[kind][k]), pose=poses[k],
                  classification=classes[k],
                  shape=build(ts, "shape_msgs/msg/SolidPrimitive", type=1,
                              dimensions=np.array([*AGENTS[k]["size"], 1.5], dtype=np.float64)))
            for k in AGENTS
        ]  # fmt: skip
        return build(ts, MSGTYPES[kind], header=h, objects=objects)
    if kind == "autoware":
        labels = {"a": 1, "b": 7}
        objects = [
            build(
                ts, "autoware_perception_msgs/msg/TrackedObject",
                object_id=build(ts, "unique_identifier_msgs/msg/UUID", uuid=np.frombuffer(UUIDS[k], dtype=np.uint8)),
                existence_probability=1.0,
                classification=[
                    build(ts, "autoware_perception_msgs/msg/ObjectClassification", label=labels[k], probability=0.9),
                    build(ts, "autoware_perception_msgs/msg/ObjectClassification", label=0, probability=0.1),
                ],
                kinematics=build(ts, "autoware_perception_msgs/msg/TrackedObjectKinematics",
                                 pose_with_covariance=build(ts, "geometry_msgs/msg/PoseWithCovariance", pose=poses[k])),
                shape=build(ts, "autoware_perception_msgs/msg/Shape",
                            dimensions=build(ts, vec, x=AGENTS[k]["size"][0], y=AGENTS[k]["size"][1], z=1.5)),
            )
            for k in AGENTS
        ]  # fmt: skip
        return build(ts, MSGTYPES[kind], header=h, objects=objects)
    labels = {"a": "car", "b": "person"}
    detections = [
        build(
            ts, "vision_msgs/msg/Detection3D", header=h, id=TRACK_IDS[kind][k],
            results=[build(ts, "vision_msgs/msg/ObjectHypothesisWithPose",
                           hypothesis=build(ts, "vision_msgs/msg/ObjectHypothesis", class_id=labels[k], score=0.9))],
            bbox=build(ts, "vision_msgs/msg/BoundingBox3D", center=poses[k],
                       size=build(ts, vec, x=AGENTS[k]["size"][0], y=AGENTS[k]["size"][1], z=1.5)),
        )
        for k in AGENTS
    ]  # fmt: skip
    return build(ts, MSGTYPES[kind], header=h, detections=detections)


def odometry(ts: Typestore, t_ns: int) -> Any:
    t = (t_ns - T0) / 1e9
    x, y, yaw = ego_state(t)
    twist = build(ts, "geometry_msgs/msg/Twist", linear=build(ts, "geometry_msgs/msg/Vector3", x=2.0, y=0.0, z=0.0))
    return build(
        ts, "nav_msgs/msg/Odometry", header=header(ts, t_ns, "map"), child_frame_id="base_link",
        pose=build(ts, "geometry_msgs/msg/PoseWithCovariance", pose=make_pose(ts, x, y, yaw)),
        twist=build(ts, "geometry_msgs/msg/TwistWithCovariance", twist=twist),
    )  # fmt: skip


def messages(ts: Typestore, kind: str, frame: str) -> list[tuple[str, str, int, Any]]:
    """(topic, type, log time, message) of the whole recording, in time order."""
    out = []
    for i in range(int(DURATION_S * 50) + 1):
        t_ns = T0 + i * 20_000_000
        out.append(("/odom", "nav_msgs/msg/Odometry", t_ns, odometry(ts, t_ns)))
        if i % 5 == 0 or i % 5 == 2:  # 20 Hz-ish, irregular: 0 and 40 ms into each 100 ms
            out.append(("/objects", MSGTYPES[kind], t_ns + 1_000_000, object_message(ts, kind, t_ns, frame)))
    return out


def write_bag(path: Path, storage: str, kind: str, frame: str, odom_from_s: float = 0.0) -> Path:
    """Write the recording as a ROS1 bag (``ros1``) or a ROS2 bag folder (``sqlite3`` / ``mcap``); the ego's
    odometry starts ``odom_from_s`` seconds in."""
    if storage == "ros1":
        ts = typestore_for(Stores.ROS1_NOETIC)
        bag = path / f"{kind}_{frame}.bag"
        with Writer1(bag) as w1:
            conns: dict[str, Any] = {}
            for topic, typ, t_ns, msg in messages(ts, kind, frame):
                if topic == "/odom" and t_ns < T0 + odom_from_s * 1e9:
                    continue
                if topic not in conns:
                    conns[topic] = w1.add_connection(topic, typ, typestore=ts)
                w1.write(conns[topic], t_ns, ts.serialize_ros1(msg, typ))
        return bag
    ts = typestore_for(Stores.ROS2_HUMBLE)
    bag = path / f"{kind}_{frame}_{storage}"
    plugin = StoragePlugin.SQLITE3 if storage == "sqlite3" else StoragePlugin.MCAP
    with Writer2(bag, version=9, storage_plugin=plugin) as w2:
        conns = {}
        for topic, typ, t_ns, msg in messages(ts, kind, frame):
            if topic not in conns:
                conns[topic] = w2.add_connection(topic, typ, typestore=ts)
            w2.write(conns[topic], t_ns, ts.serialize_cdr(msg, typ))
    return bag


def source(path: Path) -> SourceFile:
    return SourceFile(str(path), path.name, "0" * 64, 0)


def check_tracks(table: Any, kind: str, *, with_ego: bool = True) -> None:
    """The ingested agents match the ground truth at every 10 Hz step (positions to 1 mm, headings to 1 mrad)."""
    df = table.to_pandas()
    ids = TRACK_IDS[kind]
    assert set(df.track_id) == set(ids.values()) | ({"ego"} if with_ego else set())
    for key, tid in ids.items():
        rows = df[df.track_id == tid].sort_values("timestamp_ns")
        t = (rows.timestamp_ns.to_numpy() - T0) / 1e9
        # every 10 Hz step from the first header stamp (0 s) to the last (3 s): header time, not log time
        assert np.allclose(np.diff(rows.timestamp_ns.to_numpy()), 100_000_000)
        assert t[0] == pytest.approx(0.0) and t[-1] == pytest.approx(DURATION_S)
        gt = np.array([agent_state(key, ti) for ti in t])
        assert np.abs(rows.x.to_numpy() - gt[:, 0]).max() < 2e-3
        assert np.abs(rows.y.to_numpy() - gt[:, 1]).max() < 2e-3
        dh = np.angle(np.exp(1j * (rows.heading.to_numpy() - gt[:, 2])))
        assert np.abs(dh).max() < 2e-3
        assert set(rows.object_type) == {AGENTS[key]["type"]}
        assert set(rows.role) == {"other"}
        assert rows.length.to_numpy() == pytest.approx(AGENTS[key]["size"][0])
    if with_ego:
        ego = df[df.track_id == "ego"].sort_values("timestamp_ns")
        t = (ego.timestamp_ns.to_numpy() - T0) / 1e9
        gt = np.array([ego_state(ti) for ti in t])
        assert set(ego.role) == {"ego"}
        assert np.abs(ego.x.to_numpy() - gt[:, 0]).max() < 1e-6
        # Odometry twist is in base_link: rotated into map it points along the ego heading
        assert np.allclose(ego.vx.to_numpy(), 2.0 * np.cos(gt[:, 2]), atol=1e-6)
        assert np.allclose(ego.vy.to_numpy(), 2.0 * np.sin(gt[:, 2]), atol=1e-6)


@pytest.mark.parametrize("storage", ["ros1", "sqlite3", "mcap"])
@pytest.mark.parametrize("kind", list(MSGTYPES))
def test_object_arrays_in_vehicle_frame(tmp_path: Path, storage: str, kind: str) -> None:
    """Objects given in base_link come out in map, detected without a mapping, for every storage."""
    bag = write_bag(tmp_path, storage, kind, "base_link")
    parsed = RosbagAdapter().read([source(bag)], keep_going=False)
    assert not parsed.failures
    check_tracks(parsed.tracks, kind)
    meta = parsed.logs[0]
    assert meta.attributes["world_frame"] == "map"
    assert meta.attributes["mapping"]["ego"]["topic"] == "/odom"
    assert meta.attributes["topics_used"]["/objects"] == MSGTYPES[kind]


@pytest.mark.parametrize("kind", list(MSGTYPES))
def test_object_arrays_in_world_frame_with_mapping(tmp_path: Path, kind: str) -> None:
    """With a mapping and objects already in map; the map id comes from the mapping."""
    bag = write_bag(tmp_path, "sqlite3", kind, "map")
    mapping = load_mapping(None, ["ego=/odom", "agent=/objects", "map=testtrack"])
    assert isinstance(mapping, Mapping)
    parsed = RosbagAdapter(mapping=mapping).read([source(bag)], keep_going=False)
    check_tracks(parsed.tracks, kind)
    assert parsed.logs[0].map_id == "testtrack"
    assert parsed.logs[0].frame_rate_hz == 10.0


def test_ros2_mcap_bag_read_as_plain_mcap(tmp_path: Path) -> None:
    """The storage file of a ROS2 MCAP bag is a plain MCAP: the mcap adapter gives the same tracks."""
    bag = write_bag(tmp_path, "mcap", "autoware", "base_link")
    (mcap_file,) = sorted(bag.glob("*.mcap"))
    by_mcap = McapAdapter().read([source(mcap_file)], keep_going=False).tracks
    by_rosbags = RosbagAdapter().read([source(bag)], keep_going=False).tracks
    check_tracks(by_mcap, "autoware")
    key = ["track_id", "timestamp_ns"]
    a = by_mcap.to_pandas().sort_values(key).reset_index(drop=True)
    b = by_rosbags.to_pandas().sort_values(key).reset_index(drop=True)
    assert np.allclose(a.x, b.x) and np.allclose(a.y, b.y) and list(a.track_id) == list(b.track_id)


def test_objects_only_without_ego_need_no_tf(tmp_path: Path) -> None:
    """Agents alone (no ego topic) in the world frame: no ego row, no tf needed."""
    bag = write_bag(tmp_path, "ros1", "markers", "map")
    mapping = load_mapping(None, ["agent=/objects"])
    parsed = RosbagAdapter(mapping=mapping).read([source(bag)], keep_going=False)
    check_tracks(parsed.tracks, "markers", with_ego=False)


def test_vehicle_frame_objects_without_ego_fail_clearly(tmp_path: Path) -> None:
    """Objects in base_link with no ego and no tf cannot be placed: a SourceError naming the topic."""
    from logpipe.errors import SourceError

    bag = write_bag(tmp_path, "ros1", "detection3d", "base_link")
    mapping = load_mapping(None, ["agent=/objects", "world_frame=map"])
    with pytest.raises(SourceError) as info:
        RosbagAdapter(mapping=mapping).read([source(bag)], keep_going=False)
    assert info.value.field == "/objects"
    assert "base_link" in info.value.reason


Builder = Callable[[Typestore, str], Any]


def test_split_sqlite3_parts_without_metadata(tmp_path: Path) -> None:
    """Two .db3 parts of one recording in a folder without metadata.yaml: one log, as if unsplit."""
    ts = typestore_for(Stores.ROS2_HUMBLE)
    msgs = messages(ts, "derived_objects", "base_link")
    half = len(msgs) // 2
    folder = tmp_path / "rec"
    folder.mkdir()
    for part, chunk in enumerate((msgs[:half], msgs[half:])):
        bag = tmp_path / f"part{part}"
        with Writer2(bag, version=9, storage_plugin=StoragePlugin.SQLITE3) as w2:
            conns: dict[str, Any] = {}
            for topic, typ, t_ns, msg in chunk:
                if topic not in conns:
                    conns[topic] = w2.add_connection(topic, typ, typestore=ts)
                w2.write(conns[topic], t_ns, ts.serialize_cdr(msg, typ))
        (bag / f"part{part}.db3").rename(folder / f"rec_{part}.db3")
        (bag / "metadata.yaml").unlink()
        bag.rmdir()
    adapter = RosbagAdapter()
    assert adapter.discover(tmp_path) == [folder]
    parsed = adapter.read([source(folder)], keep_going=False)
    check_tracks(parsed.tracks, "derived_objects")
    assert parsed.logs[0].log_id == "rec" and parsed.logs[0].attributes["files"] == ["rec_0.db3", "rec_1.db3"]


def test_rosbag_adapter_reads_a_bare_mcap_storage_file(tmp_path: Path) -> None:
    """A ROS2 .mcap without its metadata.yaml opens with rosbags too."""
    bag = write_bag(tmp_path, "mcap", "markers", "base_link")
    (storage,) = bag.glob("*.mcap")
    (bag / "metadata.yaml").unlink()
    parsed = RosbagAdapter().read([source(storage)], keep_going=False)
    check_tracks(parsed.tracks, "markers")
    assert parsed.logs[0].attributes["storage"] == "rosbag2"


def test_objects_before_the_first_ego_pose_are_counted_not_invented(tmp_path: Path) -> None:
    """Vehicle-frame objects seen before the ego's odometry starts cannot be placed: left out and counted."""
    bag = write_bag(tmp_path, "ros1", "derived_objects", "base_link", odom_from_s=1.0)
    parsed = RosbagAdapter().read([source(bag)], keep_going=False)
    df = parsed.tracks.to_pandas()
    first = (df.groupby("track_id").timestamp_ns.min() - T0) / 1e9
    assert first["ego"] == pytest.approx(1.0) and first["1"] >= 0.8  # the tf holds 200 ms before its first stamp
    dropped = parsed.logs[0].attributes["rows_without_transform"]
    assert dropped["/objects"] == 2 * 16  # both objects in the 16 messages before 0.8 s
