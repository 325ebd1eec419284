"""inspect: topics, types, counts, span and frequency, decodability and the mapping logpipe would use."""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path

import pytest
from rich.console import Console

from logpipe.inspect import inspect_paths, render

LOCAL = Path(__file__).resolve().parents[1] / "data" / "rosbags"
SHARED = Path(__file__).resolve().parents[2].parent / "shared" / "data"
_absent = pytest.mark.skipif(not SHARED.is_dir(), reason="needs ../shared/data")


def needs_shared(test: Callable[..., None]) -> Callable[..., None]:
    """Marks a test as needing ../shared/data (marker ``shared``) and skips it when the folder is absent."""
    return pytest.mark.shared(_absent(test))


def by_topic(report: dict[str, object]) -> dict[str, dict[str, object]]:
    return {r["topic"]: r for r in report["topics"]}  # type: ignore[attr-defined,index]


def test_local_bag_report_and_render() -> None:
    (rep,) = inspect_paths([LOCAL / "datmo" / "intersection.bag"])
    assert rep["ok"] and rep["format"] == "rosbag1"
    assert rep["message_count"] == 4338 and rep["duration_s"] == pytest.approx(6.502, abs=0.01)
    topics = by_topic(rep)
    assert topics["/ego_pose"]["count"] == 781 and topics["/ego_pose"]["role"] == "ego"
    assert topics["/red_pose"]["role"] == "agent" and topics["/scan"]["role"] is None
    assert topics["/ego_pose"]["frequency_hz"] == pytest.approx(120, rel=0.01)
    assert all(t["decodes"] for t in topics.values())
    assert rep["mapping"]["ego"]["topic"] == "/ego_pose"  # type: ignore[index]
    json.dumps(rep)  # the --json output
    console = Console(record=True, width=160)
    render([rep], console)
    text = console.export_text()
    assert "/red_pose" in text and "agent" in text and "120.0" in text


@needs_shared
def test_reports_over_the_shared_folders() -> None:
    """Every real file gets a report; broken ones say why instead of raising."""
    reps = {
        Path(r["path"]).relative_to(SHARED).as_posix(): r for r in inspect_paths([SHARED / "rosbags", SHARED / "mcap"])
    }
    assert len(reps) == 32 + 10
    bad = {k: r["error"] for k, r in reps.items() if not r["ok"]}
    assert set(bad) == {
        "rosbags/webviz/bag-with-empty-message-definition.bag",
        "rosbags/rosbag2/rosbag2_tests/resources/mcap/wrong_rmw_test",
        "rosbags/rosbag2/rosbag2_tests/resources/sqlite3/wrong_rmw_test",
        "rosbags/rosbag2/ros2bag/test/resources/empty_bag",
        "rosbags/rosbag2/rosbag2_py/test/resources/mcap/talker",
        "rosbags/rosbag2/rosbag2_py/test/resources/sqlite3/talker",
        "mcap/keelson/2024-05-15.mcap",
    }
    assert "invalid magic" in bad["mcap/keelson/2024-05-15.mcap"]
    talker = by_topic(reps["rosbags/rosbag2/rosbag2_py/test/resources/sqlite3/talker"])
    assert "none can be read" in talker["/topic"]["note"]  # type: ignore[operator]
    # service events: listed, with the decoding failure
    svc = by_topic(reps["mcap/rosbag2/rosbag2_cpp/test/rosbag2_cpp/bags/topics_and_services.mcap"])
    assert svc["/add_two_ints/_service_event"]["decodes"] is False and svc["/parameter_events"]["decodes"] is True
    fallback = reps["rosbags/rosbag2/rosbag2_tests/resources/mcap/bag_with_topics_and_service_events"]
    assert fallback["format"] == "rosbag2 (mcap reader)" and ".srv" in fallback["rosbags_refused"]
    assert by_topic(fallback)["/test_topic1"]["decodes"] is True
    seek = by_topic(reps["rosbags/rosbag2/rosbag2_transport/test/resources/sqlite3/test_bag_for_seek"])
    assert seek["topic1"]["decodes"] is False
    assert len(reps["mcap/keelson/test.mcap"]["topics"]) == 649
    # mappings: detected where unambiguous, explained where not
    assert reps["mcap/evo/nav2_turtlebot.mcap"]["mapping"]["ego"]["topic"] == "/odom"
    assert reps["rosbags/evo/tf_example.bag"]["mapping"]["ego"]["tf"] == ["odom", "base_footprint"]
    assert "give a mapping" in reps["rosbags/datmo/two_robots.bag"]["mapping_error"]
    nav2 = by_topic(reps["mcap/evo/nav2_turtlebot.mcap"])
    assert nav2["/odom"]["count"] == 2639 and nav2["/odom"]["message_encoding"] == "cdr"
    json.dumps(list(reps.values()))


@needs_shared
def test_av2_report() -> None:
    (rep,) = inspect_paths([SHARED / "av2" / "scenario_0a1e6f0a-1817-4a98-b02e-db8c9327d151.parquet"])
    assert rep["ok"] and rep["focal"] == ["138951"] and rep["ego"] == ["AV"] and rep["map_id"] == "austin"
    assert rep["timestamps"] == 110 and rep["duration_s"] == pytest.approx(10.9)


def test_unknown_input(tmp_path: Path) -> None:
    (tmp_path / "notes.txt").write_text("hello")
    (rep,) = inspect_paths([tmp_path / "notes.txt"])
    assert not rep["ok"] and "is not a ROS bag" in rep["error"]
    (tmp_path / "empty").mkdir()
    (rep,) = inspect_paths([tmp_path / "empty"])
    assert not rep["ok"] and "holds no ROS bag" in rep["error"]


@needs_shared
def test_files_of_a_bag_folder_stand_for_the_folder() -> None:
    """Pointing at metadata.yaml or a storage file of a rosbag2 folder inspects the folder."""
    folder = SHARED / "rosbags" / "evo" / "tf_example"
    for path in (folder / "metadata.yaml", folder / "tf_example.db3", folder):
        (rep,) = inspect_paths([path])
        assert rep["path"] == str(folder) and rep["ok"]
    sensor = SHARED / "av2" / "sensor_logs" / "adcf7d18-0510-35b0-a2fa-b4cea13a6d76"
    (rep,) = inspect_paths([sensor / "city_SE3_egovehicle.feather"])
    assert rep["path"] == str(sensor) and rep["map_id"] == "PIT"


@needs_shared
def test_protobuf_channels_decode() -> None:
    """Protobuf channels decode from the FileDescriptorSets stored in the file (needs mcap-protobuf-support)."""
    pytest.importorskip("mcap_protobuf")
    keelson, coscene = inspect_paths([SHARED / "mcap" / "keelson" / "test.mcap", SHARED / "mcap" / "coscene"])
    assert len(keelson["topics"]) == 649 and all(t["decodes"] for t in keelson["topics"])
    assert {t["message_encoding"] for t in keelson["topics"]} == {"protobuf"}
    assert by_topic(coscene)["/log"]["decodes"] is True


def _mapping_round_trip(source: Path, tmp_path: Path) -> int:
    """``inspect --format toml`` → file → ``ingest --mapping FILE`` gives the tracks the detected mapping gives
    (track shards byte for byte); returns the number of track rows."""
    import tomllib

    from typer.testing import CliRunner

    from logpipe.cli import app
    from logpipe.dataset.reader import Dataset
    from logpipe.formats.ros.mapping import mapping_from_dict, read_mapping_document

    runner = CliRunner()
    shown = runner.invoke(app, ["inspect", str(source), "--format", "toml"])
    assert shown.exit_code == 0, shown.output
    mapping_file = tmp_path / "map.toml"
    mapping_file.write_text(shown.stdout)
    (report,) = inspect_paths([source])
    assert mapping_from_dict(read_mapping_document(mapping_file)) == mapping_from_dict(report["mapping"])
    assert tomllib.loads(shown.stdout) == report["mapping"]
    auto, mapped = tmp_path / "auto", tmp_path / "mapped"
    for out, extra in ((auto, []), (mapped, ["--mapping", str(mapping_file)])):
        done = runner.invoke(app, ["ingest", str(source), "--out", str(out), "--no-mcap", "--json", *extra])
        assert done.exit_code == 0, done.output
    a, m = Dataset.open(auto), Dataset.open(mapped)
    assert m.tracks().equals(a.tracks())
    assert [p.read_bytes() for p in m.shard_paths] == [p.read_bytes() for p in a.shard_paths]
    rows: int = a.tracks().num_rows
    return rows


def test_toml_mapping_round_trip_on_a_bag(tmp_path: Path) -> None:
    assert _mapping_round_trip(LOCAL / "datmo" / "intersection.bag", tmp_path) > 0


@needs_shared
def test_toml_mapping_round_trip_on_an_mcap(tmp_path: Path) -> None:
    """The one real MCAP with a detectable mapping (nav2 odometry: the ego only); GPL-3.0 test data of evo, so
    read from ../shared rather than copied into tests/data."""
    assert _mapping_round_trip(SHARED / "mcap" / "evo" / "nav2_turtlebot.mcap", tmp_path) > 0


def test_toml_refused_without_a_mapping(tmp_path: Path) -> None:
    from typer.testing import CliRunner

    from logpipe.cli import app

    (tmp_path / "notes.txt").write_text("hello")
    result = CliRunner().invoke(app, ["inspect", str(tmp_path / "notes.txt"), "--format", "toml"])
    assert result.exit_code == 2 and "no mapping detected" in result.output and result.stdout == ""


@needs_shared
def test_toml_refused_when_the_mapping_is_ambiguous() -> None:
    from logpipe.errors import LogpipeError
    from logpipe.inspect import mapping_toml

    with pytest.raises(LogpipeError, match="could be the ego"):
        mapping_toml(inspect_paths([SHARED / "rosbags" / "datmo" / "two_robots.bag"]))
    with pytest.raises(LogpipeError, match="detect different mappings"):
        mapping_toml(inspect_paths([LOCAL / "datmo" / "intersection.bag",
                                    SHARED / "rosbags" / "evo" / "tf_example.bag"]))
