"""A CommonRoad scenario's lanelet network as a map store, checked against the file read with ElementTree."""

from __future__ import annotations

import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pytest

from logpipe.errors import SourceError
from logpipe.maps import FeatureKind, MapSource, load_map

DATA = Path(__file__).resolve().parents[1] / "data" / "commonroad"
V2018 = DATA / "USA_Peach-3_1_T-1.xml"
V2020 = DATA / "USA_Peach-4_8_T-1.xml"


def bound(lanelet: ET.Element, side: str) -> np.ndarray:
    return np.array([(float(p.findtext("x")), float(p.findtext("y"))) for p in lanelet.find(side).findall("point")])


@pytest.mark.parametrize("path", [V2018, V2020], ids=["2018b", "2020a"])
def test_each_lanelet_gives_its_outline_and_centerline(path: Path) -> None:
    store = load_map(path)
    root = ET.parse(path).getroot()
    lanelets = root.findall("lanelet")
    assert store.map_id == root.get("benchmarkID")
    rows = {(r["kind"], r["feature_id"]): r for r in store.table.to_pylist()}
    for lanelet in lanelets:
        left, right = bound(lanelet, "leftBound"), bound(lanelet, "rightBound")
        centre = rows[(str(FeatureKind.LANE_CENTERLINE), lanelet.get("id"))]
        np.testing.assert_allclose(np.c_[centre["xs"], centre["ys"]], (left + right) / 2)
        assert centre["direction"] == "forward"
        assert centre["successors"] == [s.get("ref") for s in lanelet.findall("successor")]
        assert centre["predecessors"] == [s.get("ref") for s in lanelet.findall("predecessor")]
        area = rows[(str(FeatureKind.DRIVABLE_AREA), lanelet.get("id"))]
        np.testing.assert_allclose(np.c_[area["xs"], area["ys"]], np.vstack([left, right[::-1]]))
    # every bound once: shared ones (adjacent lanelets, opposite lanes) are one boundary
    keys = {min(tuple(map(tuple, np.round(b, 3))), tuple(map(tuple, np.round(b[::-1], 3))))
            for lanelet in lanelets for b in (bound(lanelet, "leftBound"), bound(lanelet, "rightBound"))}
    assert store.counts()["lane_boundary"] == len(keys)


def test_line_markings_neighbours_and_intersections_of_the_2020a_file() -> None:
    store = load_map(V2020)
    root = ET.parse(V2020).getroot()
    table = store.table.to_pylist()
    marks = {r["mark_type"] for r in table if r["kind"] == "lane_boundary"}
    assert {"dashed", "solid"} <= marks
    centre = {r["lane_id"]: r for r in table if r["kind"] == "lane_centerline"}
    for lanelet in root.findall("lanelet"):
        left = lanelet.find("adjacentLeft")
        same = left is not None and left.get("drivingDir") == "same"
        assert centre[lanelet.get("id")]["left_neighbor_id"] == (left.get("ref") if same else None)
        assert centre[lanelet.get("id")]["lane_type"] == "urban"
    turns = {}
    for incoming in root.iter("incoming"):
        for word, turn in (("Right", "RIGHT"), ("Left", "LEFT"), ("Straight", "NONE")):
            for ref in incoming.findall(f"successors{word}"):
                turns.setdefault(ref.get("ref"), turn)
    assert turns and {k: centre[k]["turn_direction"] for k in turns} == turns
    assert sum(bool(r["is_intersection"]) for r in centre.values()) == len(turns)
    lights = {lanelet.get("id") for lanelet in root.findall("lanelet") if lanelet.find("trafficLightRef") is not None}
    assert lights and all(centre[k]["has_traffic_control"] for k in lights)


def test_a_commonroad_file_is_a_map_for_map_source(tmp_path: Path) -> None:
    source = MapSource(files={"peach": V2020})
    assert source.get("peach").counts()["drivable_area"] == len(ET.parse(V2020).getroot().findall("lanelet"))
    own = MapSource(own={"USA_Peach-4_8_T-1": V2020}, files={"x": V2018})
    assert own.resolve("USA_Peach-4_8_T-1", "USA_Peach-4_8_T-1") == V2020  # the log's own map first
    assert own.resolve("x", "USA_Peach-4_8_T-1") == V2018  # an explicit --map still wins


def test_entity_declarations_in_a_map_file_are_refused(tmp_path: Path) -> None:
    bomb = tmp_path / "bomb.xml"
    bomb.write_text('<?xml version="1.0"?><!DOCTYPE c [<!ENTITY a "aaaaaaaaaa"><!ENTITY b "&a;&a;&a;&a;&a;">]>'
                    '<commonRoad benchmarkID="X_Y-1" timeStepSize="0.1"><lanelet id="&b;"/></commonRoad>')
    with pytest.raises(SourceError, match="DOCTYPE"):
        load_map(bomb)
