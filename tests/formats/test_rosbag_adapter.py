"""RosbagAdapter on real bags: what ingests (tracks, spans, path lengths against the data's SOURCE.md) and how
every odd or broken bag fails (a SourceError naming file, topic and reason; kept as failures with keep_going)."""

from __future__ import annotations

import shutil
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from logpipe.errors import SourceError
from logpipe.formats.ros.mapping import load_mapping
from logpipe.formats.rosbag import RosbagAdapter
from logpipe.types import SourceFile

LOCAL = Path(__file__).resolve().parents[1] / "data" / "rosbags"
SHARED = Path(__file__).resolve().parents[2].parent / "shared" / "data"
BAGS = SHARED / "rosbags"
_absent = pytest.mark.skipif(not BAGS.is_dir(), reason="needs ../shared/data/rosbags")


def needs_shared(test: Callable[..., None]) -> Callable[..., None]:
    """Marks a test as needing ../shared/data (marker ``shared``) and skips it when the folder is absent."""
    return pytest.mark.shared(_absent(test))


def src(path: Path, root: Path | None = None) -> SourceFile:
    rel = str(path.relative_to(root)) if root else path.name
    return SourceFile(str(path), rel, "0" * 64, 0)


def ingest(path: Path, adapter: RosbagAdapter | None = None) -> tuple[pd.DataFrame, dict[str, object]]:
    parsed = (adapter or RosbagAdapter()).read([src(path, path.parent)], keep_going=False)
    assert not parsed.failures
    assert len(parsed.logs) == 1
    return parsed.tracks.to_pandas(), parsed.logs[0].attributes


def path_length(df: pd.DataFrame, track: str) -> float:
    g = df[df.track_id == track].sort_values("timestamp_ns")
    return float(np.linalg.norm(np.diff(g[["x", "y"]].to_numpy(), axis=0), axis=1).sum())


def error_of(path: Path, adapter: RosbagAdapter | None = None) -> SourceError:
    with pytest.raises(SourceError) as info:
        (adapter or RosbagAdapter()).read([src(path, BAGS)], keep_going=False)
    err = info.value
    assert err.file == str(path.relative_to(BAGS))
    return err


# --- real bags that ingest ---------------------------------------------------------------------------------


def test_datmo_intersection_local_copy() -> None:
    """The copy in tests/data: ego + red car detected without a mapping, 10 Hz, in frame map."""
    df, attrs = ingest(LOCAL / "datmo" / "intersection.bag")
    assert set(df.track_id) == {"ego", "red"}
    assert dict(df.groupby("track_id").role.first()) == {"ego": "ego", "red": "other"}
    # 6.5 s of 120 Hz poses: every 100 ms step inside [13:30:57.98, 13:31:04.48] (header stamps)
    for _tid, g in df.groupby("track_id"):
        t = g.timestamp_ns.sort_values().to_numpy()
        assert np.all(np.diff(t) == 100_000_000)
        assert t[0] == 1575811858000000000 and t[-1] == 1575811864400000000
    # SOURCE.md: ego path 3.5 m, red path 7.7 m
    assert path_length(df, "ego") == pytest.approx(3.5, abs=0.1)
    assert path_length(df, "red") == pytest.approx(7.7, abs=0.1)
    assert df.heading.notna().all() and df.vx.isna().all()  # PoseStamped has no velocity
    assert attrs["world_frame"] == "map"
    assert attrs["topics_used"] == {
        "/ego_pose": "geometry_msgs/msg/PoseStamped",
        "/red_pose": "geometry_msgs/msg/PoseStamped",
    }
    assert attrs["message_counts"]["/ego_pose"] == 781  # type: ignore[index]
    assert attrs["frame_ids"] == ["map"]


def test_hz_and_raw_timestamps() -> None:
    """hz changes the grid; hz=None keeps every source stamp (the original timestamps)."""
    bag = LOCAL / "datmo" / "intersection.bag"
    df5, _ = ingest(bag, RosbagAdapter(hz=5.0))
    assert np.all(np.diff(df5[df5.track_id == "ego"].timestamp_ns.sort_values().to_numpy()) == 200_000_000)
    raw, attrs = ingest(bag, RosbagAdapter(hz=None))
    assert (raw.track_id == "ego").sum() == 781 and (raw.track_id == "red").sum() == 780
    assert attrs["resampled_hz"] is None


@needs_shared
@pytest.mark.parametrize(
    ("name", "ego_len", "red_len"),
    [("overtakes", 24.9, 20.0), ("parallel", 15.7, 10.7), ("overtake_ego", 7.3, 5.7), ("overtake_red", 5.4, 7.3)],
)
def test_datmo_bags(name: str, ego_len: float, red_len: float) -> None:
    df, _ = ingest(BAGS / "datmo" / f"{name}.bag")
    assert set(df.track_id) == {"ego", "red"}
    assert path_length(df, "ego") == pytest.approx(ego_len, abs=0.15)
    assert path_length(df, "red") == pytest.approx(red_len, abs=0.15)


@needs_shared
def test_two_robots_needs_a_mapping() -> None:
    """Three PoseStamped topics and none named ego: ambiguous without a mapping, three tracks with one."""
    bag = BAGS / "datmo" / "two_robots.bag"
    err = error_of(bag)
    assert "/mocap_pose" in err.reason and "mapping" in err.reason
    mapping = load_mapping(None, ["ego=/mocap_pose", "agent=/robot_1::vehicle", "agent=/robot_2::vehicle"])
    df, attrs = ingest(bag, RosbagAdapter(mapping=mapping))
    assert set(df.track_id) == {"ego", "robot_1", "robot_2"}
    assert set(df[df.role == "other"].object_type) == {"vehicle"}
    for track in ("ego", "robot_1", "robot_2"):  # SOURCE.md: paths 21-26 m over 32 s
        assert 21.0 <= path_length(df, track) <= 26.0
    assert attrs["frame_ids"] == [""]  # every pose has an empty frame_id: one unnamed world frame
    assert attrs["world_frame"] == ""


@needs_shared
def test_evo_ros_example_with_toml_mapping(tmp_path: Path) -> None:
    """Topic names without a leading slash; the mapping comes from a TOML file."""
    bag = BAGS / "evo" / "ROS_example.bag"
    assert "groundtruth" in error_of(bag).reason
    toml = tmp_path / "m.toml"
    toml.write_text('map = "evo"\n[ego]\ntopic = "groundtruth"\n')
    df, attrs = ingest(bag, RosbagAdapter(mapping=load_mapping(toml)))
    assert set(df.track_id) == {"ego"}
    assert path_length(df, "ego") == pytest.approx(140, rel=0.03)  # SOURCE.md: ~140 m path
    assert attrs["world_frame"] == "groundtruth"


@needs_shared
def test_tf_only_ego_ros1_and_ros2_agree() -> None:
    """evo tf_example: the ego is the only moving tf edge odom->base_footprint; lz4 ROS1 and sqlite3 ROS2 agree."""
    df1, attrs = ingest(BAGS / "evo" / "tf_example.bag")
    df2, _ = ingest(BAGS / "evo" / "tf_example")
    assert attrs["mapping"]["ego"]["tf"] == ["odom", "base_footprint"]  # type: ignore[index]
    assert attrs["world_frame"] == "odom"
    assert len(df1) == len(df2) == 516  # 51.7 s at 10 Hz
    assert np.allclose(df1.sort_values("timestamp_ns").x, df2.sort_values("timestamp_ns").x)


@needs_shared
def test_robot_localization_odometry() -> None:
    """bz2 bags, nav_msgs/Odometry ego with velocities; test2 has sim-time stamps near 0."""
    df, attrs = ingest(BAGS / "robot_localization" / "test1.bag")
    assert attrs["topics_used"] == {"/husky_velocity_controller/odom": "nav_msgs/msg/Odometry"}
    assert path_length(df, "ego") == pytest.approx(359, rel=0.02)  # SOURCE.md: 359 m path
    assert df.vx.notna().all()
    df2, _ = ingest(BAGS / "robot_localization" / "test2.bag")
    assert 47.5e9 <= df2.timestamp_ns.min() <= 47.7e9 and df2.timestamp_ns.max() <= 109e9


@needs_shared
def test_webviz_turtles_are_agents_and_bz2_matches() -> None:
    df, attrs = ingest(BAGS / "webviz" / "example.bag")
    df_bz2, _ = ingest(BAGS / "webviz" / "example-bz2.bag")
    assert set(df.track_id) == {"turtle1", "turtle2"} and set(df.role) == {"other"}
    assert "ego" not in attrs["mapping"]  # type: ignore[operator]
    assert df.drop(columns="log_id").equals(df_bz2.drop(columns="log_id"))
    assert df.x.between(0, 11.1).all() and df.y.between(0, 11.1).all()  # turtlesim's 11 m square


# --- odd and broken bags -----------------------------------------------------------------------------------

R2 = "rosbag2"


@needs_shared
@pytest.mark.parametrize(
    ("rel", "field", "words"),
    [
        ("webviz/bag-with-empty-message-definition.bag", "/led_array_status", "EMPTY message definition"),
        (f"{R2}/rosbag2_py/test/resources/mcap/talker", "/rosout", "reads none from the storage"),
        (f"{R2}/rosbag2_py/test/resources/sqlite3/talker", "/rosout", "reads none from the storage"),
        (f"{R2}/rosbag2_tests/resources/mcap/wrong_rmw_test", "/array_topic", "'wrong_format'"),
        (f"{R2}/rosbag2_tests/resources/sqlite3/wrong_rmw_test", "/test_topic", "'wrong_format'"),
        (f"{R2}/rosbag2_tests/resources/mcap/bag_with_topics_and_service_events", "/test_service1/_service_event",
         "service-event type"),
        (f"{R2}/rosbag2_tests/resources/sqlite3/bag_with_topics_and_service_events", "/test_service1/_service_event",
         "service-event type"),
        (f"{R2}/rosbag2_cpp/test/rosbag2_cpp/bags/topics_and_services.db3", "/add_two_ints/_service_event",
         "service-event type"),
        (f"{R2}/rosbag2_transport/test/resources/mcap/test_bag_for_seek", "topic1", "has no '/msg/'"),
        (f"{R2}/rosbag2_transport/test/resources/sqlite3/test_bag_for_seek", "topic1", "has no '/msg/'"),
        (f"{R2}/ros2bag/test/resources/empty_bag", None, "holds no messages"),
        (f"{R2}/rosbag2_tests/resources/sqlite3/cdr_test", None, "no topic logpipe can turn into tracks"),
        (f"{R2}/rosbag2_py/test/resources/sqlite3/wbag", None, "no topic logpipe can turn into tracks"),
        (f"{R2}/rosbag2_py/test/resources/sqlite3/reindex_test_bags/multiple_files", "/chatter", "std_msgs/msg/String"),
        ("webviz/only-a-cube-no-tf-ros-melodic.bag", "/marker_in_parent_frame", "visualization_msgs/msg/Marker"),
        ("webviz/only-a-cube.bag", None, "no track rows"),
    ],
)  # fmt: skip
def test_bad_bags_fail_clearly(rel: str, field: str | None, words: str) -> None:
    err = error_of(BAGS / rel)
    assert err.field == field
    assert words in err.reason
    assert "Traceback" not in err.describe()


@needs_shared
def test_keep_going_reports_and_keeps_the_good_bags() -> None:
    good = BAGS / "datmo" / "intersection.bag"
    bad = [BAGS / "webviz" / "bag-with-empty-message-definition.bag", BAGS / R2 / "ros2bag/test/resources/empty_bag"]
    parsed = RosbagAdapter().read([src(p, BAGS) for p in [bad[0], good, bad[1]]], keep_going=True)
    assert [log.log_id for log in parsed.logs] == ["intersection"]
    assert set(parsed.tracks.column("track_id").to_pylist()) == {"ego", "red"}
    assert [f.file for f in parsed.failures] == [str(p.relative_to(BAGS)) for p in bad]


@needs_shared
def test_allow_empty() -> None:
    """allow_empty turns 'no tracks' into an empty log, not a broken bag into one."""
    adapter = RosbagAdapter(allow_empty=True)
    parsed = adapter.read([src(BAGS / R2 / "ros2bag/test/resources/empty_bag", BAGS)], keep_going=False)
    assert parsed.tracks.num_rows == 0 and len(parsed.logs) == 1
    with pytest.raises(SourceError):
        adapter.read([src(BAGS / R2 / "rosbag2_tests/resources/sqlite3/wrong_rmw_test", BAGS)], keep_going=False)


def test_truncated_bag(tmp_path: Path) -> None:
    """A bag cut in half (no index at the end): a SourceError, not a traceback."""
    data = (LOCAL / "datmo" / "intersection.bag").read_bytes()
    cut = tmp_path / "cut.bag"
    cut.write_bytes(data[: len(data) // 2])
    with pytest.raises(SourceError) as info:
        RosbagAdapter().read([src(cut)], keep_going=False)
    assert info.value.file == "cut.bag"
    assert "index" in info.value.reason or "cannot open" in info.value.reason


def test_missing_and_unsupported_mapping_topics() -> None:
    """A mapping naming a missing topic or a non-pose topic fails on that topic; keep_going keeps the rest."""
    bag = LOCAL / "datmo" / "intersection.bag"
    mapping = load_mapping(None, ["ego=/ego_pose", "agent=/nope", "agent=/scan"])
    with pytest.raises(SourceError) as info:
        RosbagAdapter(mapping=mapping).read([src(bag)], keep_going=False)
    assert info.value.field == "/nope" and "not in the log" in info.value.reason
    parsed = RosbagAdapter(mapping=mapping).read([src(bag)], keep_going=True)
    assert [f.field for f in parsed.failures] == ["/nope", "/scan"]
    assert "sensor_msgs/msg/LaserScan" in parsed.failures[1].reason
    assert set(parsed.tracks.column("track_id").to_pylist()) == {"ego"}


def test_discover_and_sniff(tmp_path: Path) -> None:
    """Bags, rosbag2 folders and split folders are found; standalone .mcap files are left to the MCAP adapter."""
    shutil.copy(LOCAL / "datmo" / "intersection.bag", tmp_path / "a.bag")
    (tmp_path / "split").mkdir()
    for i in range(2):
        (tmp_path / "split" / f"rec_{i}.db3").write_bytes(b"SQLite format 3\x00")
    (tmp_path / "x.mcap").write_bytes(b"\x89MCAP0\r\n")
    (tmp_path / "notes.bag").write_text("not a bag")
    found = RosbagAdapter().discover(tmp_path)
    assert found == [tmp_path / "a.bag", tmp_path / "split"]


@needs_shared
def test_discover_shared_layout() -> None:
    found = {str(p.relative_to(BAGS)) for p in RosbagAdapter().discover(BAGS)}
    assert "evo/tf_example" in found and "evo/tf_example.bag" in found
    assert f"{R2}/rosbag2_py/test/resources/sqlite3/reindex_test_bags/multiple_files" in found
    assert f"{R2}/rosbag2_py/test/resources/mcap/wbag" in found
    assert not any(p.endswith(".mcap") for p in found)


@needs_shared
def test_sniffing_rosbag2_folder_files() -> None:
    """A rosbag2 folder's files belong to the rosbag adapter (the registry sniffs files), not to the MCAP one."""
    from logpipe.formats.mcapfile import McapAdapter

    folder = BAGS / R2 / "rosbag2_py/test/resources/mcap/wbag"
    assert RosbagAdapter().sniff(folder / "wbag_0.mcap") and not McapAdapter().sniff(folder / "wbag_0.mcap")
    assert RosbagAdapter().discover(folder / "metadata.yaml") == [folder]
    standalone = SHARED / "mcap" / "evo" / "nav2_turtlebot.mcap"
    assert McapAdapter().sniff(standalone) and not RosbagAdapter().sniff(standalone)
