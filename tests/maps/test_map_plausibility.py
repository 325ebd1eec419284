"""Issue 56 item 9, maps: non-finite and absurd vertices are one error naming the file in every map format (NaN,
Infinity and 1e400 were accepted, 1e300 an OverflowError traceback), and map names match exactly (``.``, ``a`` or
``lane`` picked the MIA map by substring)."""

from __future__ import annotations

import re
import shutil
from pathlib import Path

import numpy as np
import pytest

from logpipe.errors import SourceError
from logpipe.maps import MapSource, find_map_files, load_map, map_names

MAPS = Path(__file__).resolve().parents[2] / "tests" / "data" / "maps"
AV2_JSON = MAPS / "log_map_archive_0a1e6f0a-1817-4a98-b02e-db8c9327d151.json"
AV1_XML = MAPS / "pruned_argoverse_FIX_00000_vector_map.xml"
OSM = MAPS / "lanelet2_fixture.osm"
NPZ = MAPS / "MIA_lane_centerlines_crop_2645.npz"


def _replace_first(path: Path, target: Path, pattern: str, value: str) -> Path:
    text = path.read_text()
    edited, count = re.subn(pattern, lambda m: m.group(1) + value + m.group(2), text, count=1)
    assert count == 1
    target.write_text(edited)
    return target


@pytest.mark.parametrize("value", ["NaN", "Infinity", "-Infinity", "1e400", "1e300", "-4e12"])
def test_av2_json_vertices(tmp_path: Path, value: str) -> None:
    bad = _replace_first(AV2_JSON, tmp_path / AV2_JSON.name, r'("x": )-?[0-9.]+(,)', value)
    with pytest.raises(SourceError, match=f"{re.escape(str(bad))}: .*not finite or beyond"):
        load_map(bad)


@pytest.mark.parametrize("value", ["nan", "inf", "-inf", "1e300", "1e12"])
def test_av1_xml_vertices(tmp_path: Path, value: str) -> None:
    bad = _replace_first(AV1_XML, tmp_path / AV1_XML.name, r'(<node id="1" x=")[0-9.]+(")', value)
    with pytest.raises(SourceError, match="not finite or beyond"):
        load_map(bad)


@pytest.mark.parametrize("value", ["nan", "inf", "1e300"])
def test_lanelet2_osm_vertices(tmp_path: Path, value: str) -> None:
    bad = _replace_first(OSM, tmp_path / OSM.name, r'(<tag k="local_x" v=")10.0000(")', value)
    with pytest.raises(SourceError, match=re.escape(str(bad))):
        load_map(bad)


@pytest.mark.parametrize("value", [np.nan, np.inf, 1e300])
def test_av1_npz_vertices(tmp_path: Path, value: float) -> None:
    with np.load(NPZ, allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files}
    arrays["points"] = arrays["points"].astype(np.float64)
    arrays["points"][5, 0] = value
    bad = tmp_path / NPZ.name
    np.savez(bad, **arrays)
    with pytest.raises(SourceError, match="not finite or beyond"):
        load_map(bad)


def test_the_intact_maps_still_load() -> None:
    for path in (AV2_JSON, AV1_XML, OSM, NPZ):
        assert len(load_map(path).table) > 0


@pytest.mark.parametrize("name", [".", "a", "lane", "centerlines", "json", "_", "MI"])
def test_a_map_name_matches_exactly_not_by_substring(tmp_path: Path, name: str) -> None:
    shutil.copy(NPZ, tmp_path / "MIA_lane_centerlines.npz")
    assert find_map_files(name, [tmp_path]) == []
    assert MapSource(roots=(tmp_path,)).resolve(name) is None


def test_the_names_a_map_answers_to() -> None:
    assert find_map_files("MIA", [MAPS]) == [NPZ, MAPS / "log_map_archive_3b3570b4-7b0b-3268-a571-b0889dbf40b6____MIA_"
                                                   "city_47894.json"]
    assert map_names(AV1_XML) >= {"fix"}
    assert "pit_city_57819" in map_names(Path("log_map_archive_ab-12____PIT_city_57819.json"))
    assert MapSource(roots=(MAPS,)).resolve("mia") == NPZ
