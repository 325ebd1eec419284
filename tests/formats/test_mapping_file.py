"""The mapping file (TOML or YAML) and CLI overrides."""

from __future__ import annotations

from pathlib import Path

import pytest

from logpipe.errors import SourceError
from logpipe.formats.ros.mapping import AgentSpec, EgoSpec, Mapping, load_mapping

TOML = """
map = "barc_lab"
world_frame = "map"

[ego]
topic = "/ego_pose"
object_type = "vehicle"

[[agents]]
topic = "/red_pose"
track_id = "red"
object_type = "vehicle"

[[agents]]
topic = "/objects"
"""

YAML = """
map: barc_lab
world_frame: map
ego: {topic: /ego_pose, object_type: vehicle}
agents:
  - {topic: /red_pose, track_id: red, object_type: vehicle}
  - /objects
"""


def test_toml_and_yaml_give_the_same_mapping(tmp_path: Path) -> None:
    (tmp_path / "m.toml").write_text(TOML)
    (tmp_path / "m.yaml").write_text(YAML)
    a = load_mapping(tmp_path / "m.toml")
    b = load_mapping(tmp_path / "m.yaml")
    assert (
        a
        == b
        == Mapping(
            ego=EgoSpec(topic="/ego_pose", object_type="vehicle"),
            agents=(AgentSpec("/red_pose", "red", "vehicle"), AgentSpec("/objects")),
            map_id="barc_lab",
            world_frame="map",
        )
    )
    assert a is not None and a.topics == ["/ego_pose", "/red_pose", "/objects"]


def test_cli_overrides_merge_over_the_file(tmp_path: Path) -> None:
    (tmp_path / "m.toml").write_text(TOML)
    m = load_mapping(
        tmp_path / "m.toml", ["map=other", "ego.tf=odom:base_link", "agent=/blue:blue:cyclist", "time=log"]
    )
    assert m is not None
    assert m.map_id == "other" and m.time == "log"
    assert m.ego == EgoSpec(topic=None, tf=("odom", "base_link"), object_type="vehicle")
    assert m.agents[-1] == AgentSpec("/blue", "blue", "cyclist")
    assert load_mapping(None, []) is None
    assert load_mapping(None, ["ego=/odom"]) == Mapping(ego=EgoSpec(topic="/odom"))


@pytest.mark.parametrize(
    ("overrides", "field"),
    [
        (["ego=/odom", "ego.object_type=spaceship"], "ego.object_type"),
        (["agent=/x::boat"], "agents[0].object_type"),
        (["colour=red"], "colour"),
        (["time=never"], "time"),
    ],
)
def test_bad_values_name_the_key(overrides: list[str], field: str) -> None:
    with pytest.raises(SourceError) as info:
        load_mapping(None, overrides)
    assert info.value.field == field


def test_bad_files(tmp_path: Path) -> None:
    (tmp_path / "bad.toml").write_text("map = [")
    with pytest.raises(SourceError, match="cannot read mapping"):
        load_mapping(tmp_path / "bad.toml")
    (tmp_path / "list.yaml").write_text("- a\n- b\n")
    with pytest.raises(SourceError, match="top level"):
        load_mapping(tmp_path / "list.yaml")
    (tmp_path / "both.yaml").write_text("ego: {topic: /a, tf: [odom, base]}\n")
    with pytest.raises(SourceError, match="exactly one"):
        load_mapping(tmp_path / "both.yaml")


def test_adapters_take_a_path_or_a_mapping_with_overrides(tmp_path: Path) -> None:
    from logpipe.formats.mcapfile import McapAdapter
    from logpipe.formats.rosbag import RosbagAdapter

    (tmp_path / "m.yaml").write_text(YAML)
    by_path = RosbagAdapter(mapping=str(tmp_path / "m.yaml"), mapping_overrides=["map=elsewhere"]).options.mapping
    assert by_path is not None and by_path.map_id == "elsewhere" and by_path.ego == EgoSpec(topic="/ego_pose")
    base = load_mapping(tmp_path / "m.yaml")
    merged = McapAdapter(mapping=base, mapping_overrides=["agent=/green"]).options.mapping
    assert merged is not None and [a.topic for a in merged.agents] == ["/red_pose", "/objects", "/green"]
    assert McapAdapter(mapping=base).options.mapping is base
    with pytest.raises(ValueError, match="unknown typestore"):
        RosbagAdapter(typestore="ros7")
