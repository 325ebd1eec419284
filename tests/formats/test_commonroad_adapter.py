"""CommonRoadAdapter on the bundled real scenarios (one 2018b, one 2020a) and on damaged variants of them.

Expected values are read from the same files with the standard library's ElementTree, independently of the
adapter's lxml/XPath reading.
"""

from __future__ import annotations

import math
import re
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pytest

from logpipe.errors import SourceError
from logpipe.formats import detect
from logpipe.formats.commonroad import CommonRoadAdapter
from logpipe.types import PROTOCOLS, SourceFile

DATA = Path(__file__).resolve().parents[1] / "data" / "commonroad"
V2018 = DATA / "USA_Peach-3_1_T-1.xml"
V2020 = DATA / "USA_Peach-4_8_T-1.xml"


def src(path: Path) -> SourceFile:
    return SourceFile(str(path), path.name, "", path.stat().st_size)


def obstacles(path: Path) -> list[ET.Element]:
    root = ET.parse(path).getroot()
    return [*root.iter("dynamicObstacle"), *(o for o in root.iter("obstacle") if o.findtext("role") == "dynamic")]


@pytest.mark.parametrize("path", [V2018, V2020], ids=["2018b", "2020a"])
def test_every_state_of_every_dynamic_obstacle_becomes_a_row(path: Path) -> None:
    parsed = CommonRoadAdapter().read([src(path)], keep_going=False)
    rows = parsed.tracks.to_pandas()
    expected = obstacles(path)
    assert sorted(rows.track_id.unique()) == sorted(o.get("id") for o in expected)
    for obstacle in expected:
        states = [obstacle.find("initialState"), *obstacle.iter("state")]
        mine = rows[rows.track_id == obstacle.get("id")].sort_values("timestamp_ns")
        assert len(mine) == len(states)
        for (_, row), state in zip(mine.iterrows(), states, strict=True):
            step = int(state.findtext("time/exact"))
            assert row.timestamp_ns == step * 100_000_000  # timeStepSize 0.1 s, exact in ns
            assert row.x == float(state.findtext("position/point/x"))
            assert row.y == float(state.findtext("position/point/y"))
            theta, speed = float(state.findtext("orientation/exact")), float(state.findtext("velocity/exact"))
            assert row.heading == theta
            assert math.isclose(row.vx, speed * math.cos(theta)) and math.isclose(row.vy, speed * math.sin(theta))
        assert set(mine.length) == {float(obstacle.findtext("shape/rectangle/length"))}
        assert set(mine.width) == {float(obstacle.findtext("shape/rectangle/width"))}
    assert set(rows.object_type) == {"vehicle"} and set(rows.source_type) == {"car"} and set(rows.role) == {"other"}


def test_log_metadata_names_the_location_and_keeps_the_scenario_map() -> None:
    parsed = CommonRoadAdapter().read([src(V2018), src(V2020)], keep_going=False)
    first, second = parsed.logs
    assert first.log_id == first.map_id == "USA_Peach-3_1_T-1" and second.log_id == "USA_Peach-4_8_T-1"
    assert first.memberships == ("location/USA_Peach",) and first.attributes["location"] == "USA_Peach"
    assert first.attributes["commonroad_version"] == "2018b" and second.attributes["commonroad_version"] == "2020a"
    assert first.attributes["time_step_s"] == 0.1 and first.frame_rate_hz == 10.0
    assert "intersection" in first.attributes["tags"] and "intersection" in second.attributes["tags"]
    assert set(parsed.maps) == {"USA_Peach-3_1_T-1", "USA_Peach-4_8_T-1"}
    lanelets = len(ET.parse(V2020).getroot().findall("lanelet"))
    assert parsed.maps["USA_Peach-4_8_T-1"].counts()["lane_centerline"] == lanelets
    assert CommonRoadAdapter.default_protocol == PROTOCOLS["commonroad"]


def test_format_is_detected_from_the_xml_root(tmp_path: Path) -> None:
    assert detect(DATA) == "commonroad" and detect(V2020) == "commonroad"
    other = tmp_path / "other.xml"
    other.write_text('<?xml version="1.0"?><osm version="0.6"></osm>')
    assert not CommonRoadAdapter().sniff(other)
    assert CommonRoadAdapter().discover(DATA) == [V2018, V2020]


@pytest.mark.parametrize("step", ["0.2", "0.04"])
def test_other_step_sizes_are_resampled_to_10_hz_without_bridging(tmp_path: Path, step: str) -> None:
    text = V2018.read_text().replace('timeStepSize="0.1"', f'timeStepSize="{step}"')
    path = tmp_path / "scenario.xml"
    path.write_text(text)
    parsed = CommonRoadAdapter().read([src(path)], keep_going=False)
    rows = parsed.tracks.to_pandas()
    assert parsed.logs[0].attributes["resampled_from_hz"] == round(1 / float(step), 6)
    original = CommonRoadAdapter().read([src(V2018)], keep_going=False).tracks.to_pandas()
    for track_id, mine in rows.groupby("track_id"):
        t = np.sort(mine.timestamp_ns.to_numpy())
        assert (np.diff(t) == 100_000_000).all()  # on the 10 Hz grid
        source = original[original.track_id == track_id].sort_values("timestamp_ns")
        span_ns = (len(source) - 1) * round(float(step) * 1e9)
        assert t[0] == 0 and t[-1] == span_ns // 100_000_000 * 100_000_000  # inside the track's span only
        # a grid time falls between source states k and k+1: linear interpolation of their positions
        k = (t * 1e-9 / float(step)).astype(int).clip(max=len(source) - 2)
        w = t * 1e-9 / float(step) - k
        xs = source.x.to_numpy()
        np.testing.assert_allclose(mine.sort_values("timestamp_ns").x.to_numpy(), xs[k] * (1 - w) + xs[k + 1] * w,
                                   atol=1e-9)


def _damaged(tmp_path: Path, old: str, new: str, *, base: Path = V2018) -> Path:
    """``base`` with the first ``old`` replaced by ``new`` (and, for a renamed element, its closing tag too)."""
    text = base.read_text()
    assert old in text, old
    text = text.replace(old, new, 1)
    opened, renamed = re.fullmatch(r"<(\w+)>", old), re.fullmatch(r"<(\w+)>", new)
    if opened and renamed:
        text = text.replace(f"</{opened.group(1)}>", f"</{renamed.group(1)}>", 1)
    path = tmp_path / "damaged.xml"
    path.write_text(text)
    return path


_FIRST_STATE_TIME = "<time>\n               <exact>1</exact>\n            </time>"
CASES: list[tuple[str, str, str, str, str | None]] = [
    # (id, old text, new text, expected field, expected words)
    ("unknown type", "<type>car</type>", "<type>spaceship</type>", "type", "obstacle 405: unknown obstacle type"),
    ("missing time", _FIRST_STATE_TIME, "", "time", "obstacle 405, trajectory state 1: <time> is missing"),
    ("gap", _FIRST_STATE_TIME, _FIRST_STATE_TIME.replace(">1<", ">2<"), "time", "obstacle 405: time skips"),
    ("backwards", _FIRST_STATE_TIME, _FIRST_STATE_TIME.replace(">1<", ">0<"), "time", "obstacle 405: time repeats"),
    ("nan x", "<x>-14.1891</x>", "<x>nan</x>", "x", "obstacle 405, trajectory state 1"),
    ("inf y", "<y>10.7437</y>", "<y>-inf</y>", "y", "not finite"),
    ("huge x", "<x>-14.1891</x>", "<x>1e400</x>", "x", "not finite"),
    ("text x", "<x>-14.1891</x>", "<x>west</x>", "x", "not a number"),
    ("nan heading", "<exact>-1.5783</exact>", "<exact>NaN</exact>", "orientation", "obstacle 405, initialState"),
    ("interval", "<orientation>\n               <exact>-1.5783</exact>\n            </orientation>",
     "<orientation><intervalStart>-1.6</intervalStart><intervalEnd>-1.5</intervalEnd></orientation>",
     "orientation", "interval"),
    ("no position point", "<position>\n               <point>\n                  <x>-14.1891</x>\n"
     "                  <y>10.7437</y>\n               </point>", "<position><circle><radius>1</radius></circle>",
     "position", "uncertain position"),
    ("no shape", "<shape>", "<notshape>", "shape", "<shape> is missing"),
    ("negative length", "<length>4.7244</length>", "<length>-4.7</length>", "length", "not positive"),
    ("duplicate id", '<obstacle id="405">', '<obstacle id="407">', "id", "obstacle 407: the id is used twice"),
    ("bad step", 'timeStepSize="0.1"', 'timeStepSize="-1"', "timeStepSize", "not a step"),
    ("unsafe id", 'benchmarkID="USA_Peach-3_1_T-1"', 'benchmarkID="../../escape"', "benchmarkID", "file name"),
    ("bad lanelet point", "<x>-15.1963</x>", "<x>inf</x>", "x", "lanelet 43163 leftBound"),
    ("lanelet without bound", "<rightBound>", "<notBound>", "rightBound", "lanelet 43163 rightBound is missing"),
]


@pytest.mark.parametrize(("old", "new", "field", "words"), [c[1:] for c in CASES], ids=[c[0] for c in CASES])
def test_damaged_file_is_one_error_naming_file_obstacle_and_field(tmp_path: Path, old: str, new: str, field: str,
                                                                  words: str) -> None:
    path = _damaged(tmp_path, old, new)
    with pytest.raises(SourceError) as caught:
        CommonRoadAdapter().read([src(path)], keep_going=False)
    err = caught.value
    assert err.file == "damaged.xml" and err.field == field and words in err.reason, err.describe()
    assert "\n" not in err.describe()


def test_a_duplicate_id_needs_a_second_obstacle_with_it() -> None:
    # the "duplicate id" case above renames obstacle 405 to the id of another obstacle of the same file
    ids = [o.get("id") for o in obstacles(V2018)]
    assert "405" in ids and "407" in ids


@pytest.mark.parametrize("text", [
    '<?xml version="1.0"?><!DOCTYPE lolz [<!ENTITY lol "lol"><!ENTITY lol2 "&lol;&lol;&lol;&lol;&lol;&lol;">]>'
    '<commonRoad benchmarkID="A_B-1" timeStepSize="0.1">&lol2;</commonRoad>',
    '<?xml version="1.0"?><!DOCTYPE r [<!ENTITY xxe SYSTEM "file:///etc/passwd">]>'
    '<commonRoad benchmarkID="A_B-1" timeStepSize="0.1"><lanelet id="&xxe;"/></commonRoad>',
], ids=["entity expansion", "external entity"])
def test_entities_are_refused_not_expanded(tmp_path: Path, text: str) -> None:
    path = tmp_path / "bomb.xml"
    path.write_text(text)
    with pytest.raises(SourceError, match="DOCTYPE") as caught:
        CommonRoadAdapter().read([src(path)], keep_going=False)
    assert "root:" not in caught.value.describe()


def test_malformed_xml_names_its_line(tmp_path: Path) -> None:
    text = V2020.read_text()
    path = tmp_path / "cut.xml"
    path.write_text(text[: len(text) // 2])
    with pytest.raises(SourceError, match="malformed XML") as caught:
        CommonRoadAdapter().read([src(path)], keep_going=False)
    assert caught.value.line is not None and caught.value.line > 100


def test_keep_going_quarantines_only_the_bad_file(tmp_path: Path) -> None:
    bad = _damaged(tmp_path, "<type>car</type>", "<type>spaceship</type>")
    parsed = CommonRoadAdapter().read([src(bad), src(V2020)], keep_going=True)
    assert [m.log_id for m in parsed.logs] == ["USA_Peach-4_8_T-1"] and set(parsed.maps) == {"USA_Peach-4_8_T-1"}
    assert len(parsed.failures) == 1 and parsed.failures[0].field == "type"


def test_every_commonroad_obstacle_type_maps_to_one_of_ours(tmp_path: Path) -> None:
    # the vocabulary of CommonRoad's ObstacleType (2018b-2020a XSD), each written into the 2020a sample
    from logpipe.formats.commonroad import OBSTACLE_TYPES

    words = ["car", "truck", "bus", "bicycle", "pedestrian", "priorityVehicle", "parkedVehicle", "constructionZone",
             "train", "roadBoundary", "motorcycle", "taxi", "building", "pillar", "median_strip", "unknown"]
    assert sorted(OBSTACLE_TYPES) == sorted(words)
    text = V2020.read_text()
    first = re.search(r"<dynamicObstacle id=\"(\d+)\">\s*<type>car</type>", text)
    assert first is not None
    for word in ("bus", "pedestrian", "bicycle", "motorcycle"):
        path = tmp_path / f"{word}.xml"
        path.write_text(text.replace(first.group(0), first.group(0).replace(">car<", f">{word}<")))
        rows = CommonRoadAdapter().read([src(path)], keep_going=False).tracks.to_pandas()
        mine = rows[rows.track_id == first.group(1)]
        assert set(mine.source_type) == {word}
        assert set(mine.object_type) == {OBSTACLE_TYPES[word].value}


def test_gzip_files_read_like_plain_ones_and_bombs_are_refused(tmp_path: Path) -> None:
    import gzip

    packed = tmp_path / "USA_Peach-4_8_T-1.xml.gz"
    packed.write_bytes(gzip.compress(V2020.read_bytes()))
    adapter = CommonRoadAdapter()
    assert adapter.discover(tmp_path) == [packed] and detect(packed) == "commonroad"
    plain = adapter.read([src(V2020)], keep_going=False)
    unpacked = adapter.read([src(packed)], keep_going=False)
    assert unpacked.tracks.equals(plain.tracks) and unpacked.maps["USA_Peach-4_8_T-1"].table.equals(
        plain.maps["USA_Peach-4_8_T-1"].table)
    assert unpacked.logs[0].source_sha256 != plain.logs[0].source_sha256  # the digest of the bytes on disk
    bomb = tmp_path / "bomb.xml.gz"
    head = b'<?xml version="1.0"?><commonRoad benchmarkID="A_B-1" timeStepSize="0.1">'
    bomb.write_bytes(gzip.compress(head + b" " * (300 << 20)))  # 300 MiB of blanks in ~300 KB
    with pytest.raises(SourceError, match="over 16 MiB"):
        adapter.read([src(bomb)], keep_going=False)
    cut = tmp_path / "cut.xml.gz"
    cut.write_bytes(packed.read_bytes()[:-40])
    with pytest.raises(SourceError, match="gzip"):
        adapter.read([src(cut)], keep_going=False)


def test_generated_scenarios_are_marked_synthetic(tmp_path: Path) -> None:
    text = V2020.read_text().replace('benchmarkID="USA_Peach-4_8_T-1"', 'benchmarkID="synthetic_USA_Peach-4_8_T-1_0"')
    text = re.sub(r'source="[^"]*"', 'source="SYNTHETIC traffic (logpipe)"', text, count=1)
    path = tmp_path / "synthetic_USA_Peach-4_8_T-1_0.xml"
    path.write_text(text)
    meta = CommonRoadAdapter().read([src(path)], keep_going=False).logs[0]
    assert meta.attributes["synthetic"] is True and meta.attributes["location"] == "USA_Peach"
    assert set(meta.memberships) == {"location/USA_Peach", "synthetic"}
    real = CommonRoadAdapter().read([src(V2020)], keep_going=False).logs[0]
    assert real.attributes["synthetic"] is False and "synthetic" not in real.memberships
