"""Map adapters: AV1 npz and vector-map XML, AV2 JSON, Lanelet2 OSM, the registry and MapSource."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest

from logpipe.errors import DatasetError, SourceError
from logpipe.maps import FeatureKind, MapSource, MapStore, load_map
from logpipe.maps import lanelet2 as l2

DATA = Path(__file__).parents[1] / "data" / "maps"
SHARED = (Path(__file__).parents[2] / ".." / "shared" / "data").resolve()
AV2_WITH_CL = DATA / "log_map_archive_0a1e6f0a-1817-4a98-b02e-db8c9327d151.json"
AV2_NO_CL = DATA / "log_map_archive_3b3570b4-7b0b-3268-a571-b0889dbf40b6____MIA_city_47894.json"


def _attrs(store: MapStore, feature_id: str) -> dict[str, object]:
    rows = store.table.to_pylist()
    return next(r for r in rows if r["feature_id"] == feature_id and r["kind"] == "lane_centerline")


def test_av1_npz_crop() -> None:
    store = load_map(DATA / "MIA_lane_centerlines_crop_2645.npz")
    assert store.map_id == "MIA"
    assert store.counts()["lane_centerline"] == 512
    with np.load(DATA / "MIA_lane_centerlines_crop_2645.npz", allow_pickle=False) as z:
        ids, off, pts = z["lane_ids"], z["offsets"], z["points"]
    row = int(np.flatnonzero(np.array(store.feature_ids(range(len(store)))) == str(ids[7]))[0])
    assert np.array_equal(store.geometry(row), pts[off[7] : off[8]])
    assert set(store.table.column("source").to_pylist()) == {"argoverse1_npz"}


def test_av1_npz_rejects_broken(tmp_path: Path) -> None:
    bad = tmp_path / "MIA_bad.npz"
    np.savez(bad, lane_ids=np.array([1, 2]), offsets=np.array([0, 2, 9]), points=np.zeros((4, 2)))
    with pytest.raises(SourceError, match="offsets"):
        load_map(bad)


def test_av1_pickles_are_never_opened(tmp_path: Path) -> None:
    # The original `*_array` files are pickles: no adapter claims them, so nothing unpickles them.
    fake = tmp_path / "MIA_array"
    fake.write_bytes(b"\x80\x04\x95not really a pickle")
    with pytest.raises(DatasetError, match=r"not a map format|no map named|expected one map"):
        load_map(fake)


def test_av1_vector_map_xml() -> None:
    store = load_map(DATA / "pruned_argoverse_FIX_00000_vector_map.xml")
    assert store.map_id == "FIX"
    assert store.counts()["lane_centerline"] == 4
    a1001 = _attrs(store, "1001")
    assert a1001["successors"] == ["1003", "1004"]
    assert a1001["is_intersection"] is False
    a1004 = _attrs(store, "1004")
    assert a1004["turn_direction"] == "LEFT"
    assert a1004["is_intersection"] is True and a1004["has_traffic_control"] is True
    assert a1004["right_neighbor_id"] == "1003" and a1004["left_neighbor_id"] is None
    assert a1004["predecessors"] == ["1001"]
    g = store.geometry(int(np.flatnonzero(np.array(store.feature_ids(range(4))) == "1004")[0]))
    # Quarter circle of radius 15 about (1045, 2015): every vertex 15 m from the centre.
    assert np.allclose(np.hypot(g[:, 0] - 1045, g[:, 1] - 2015), 15.0, atol=1e-3)
    assert np.allclose(g[0], [1045, 2000]) and np.allclose(g[-1], [1060, 2015])


def test_av1_xml_errors_name_the_lane(tmp_path: Path) -> None:
    text = (DATA / "pruned_argoverse_FIX_00000_vector_map.xml").read_text()
    broken = tmp_path / "pruned_argoverse_FIX_1_vector_map.xml"
    broken.write_text(text.replace('<nd ref="35" />', '<nd ref="999999" />'))
    with pytest.raises(SourceError, match=r"lane 1004 refers to unknown node"):
        load_map(broken)
    bad_bool = tmp_path / "pruned_argoverse_FIX_2_vector_map.xml"
    bad_bool.write_text(text.replace('k="is_intersection" v="True"', 'k="is_intersection" v="maybe"', 1))
    with pytest.raises(SourceError, match="is_intersection"):
        load_map(bad_bool)


def test_av2_with_centerlines() -> None:
    store = load_map(AV2_WITH_CL)
    c = store.counts()
    assert c["lane_centerline"] == 71 and c["drivable_area"] == 2 and c["crossing"] == 6
    assert 0 < c["lane_boundary"] < 142  # shared boundaries kept once
    assert not any(store.table.column("derived").to_pylist()[: c["lane_centerline"]])
    # Crossings are closed quadrilaterals built from the two edges.
    for r in store.rows(FeatureKind.CROSSING).tolist():
        assert store.geometry(r).shape == (4, 2)


def test_av2_derived_centerlines_lie_between_boundaries() -> None:
    store = load_map(AV2_NO_CL)
    assert store.map_id == "MIA_city_47894"
    c = store.counts()
    assert c["lane_centerline"] == 150 and c["drivable_area"] == 5 and c["crossing"] == 6
    rows = store.rows(FeatureKind.LANE_CENTERLINE)
    assert all(store.table.column("derived")[int(r)].as_py() for r in rows)
    # A derived centerline stays inside the lane: close to half the lane width from each boundary.
    cl = np.concatenate([store.geometry(int(r)) for r in rows])
    d = store.distance_to(FeatureKind.LANE_BOUNDARY, cl, max_dist=5.0)
    assert np.median(d) == pytest.approx(1.8, abs=0.6)
    assert np.isfinite(d).all()


def test_av2_derived_centerline_agrees_with_av1_survey() -> None:
    # Cross-check of two independent map surveys in the same MIA frame (shared SOURCE.md: median 0.4 m).
    npz = SHARED / "argoverse1/maps/lane_centerlines/derived/MIA_lane_centerlines.npz"
    if not npz.exists():
        pytest.skip(f"needs {npz}")
    av1 = load_map(npz)
    av2 = load_map(AV2_NO_CL)
    cl = np.concatenate([av2.geometry(int(r)) for r in av2.rows(FeatureKind.LANE_CENTERLINE)])
    d = av1.distance_to(FeatureKind.LANE_CENTERLINE, cl, max_dist=10.0)
    assert np.median(d[np.isfinite(d)]) < 0.6


def test_lanelet2_local_coordinates() -> None:
    store = load_map(DATA / "lanelet2_fixture.osm")
    c = store.counts()
    assert c == {"lane_centerline": 2, "lane_boundary": 3, "drivable_area": 3, "crossing": 1}
    a = _attrs(store, "-201")
    assert a["direction"] == "forward" and a["derived"] is True
    assert _attrs(store, "-202")["direction"] == "both"
    g = store.geometry(int(np.flatnonzero(np.array(store.feature_ids(range(len(store)))) == "-201")[0]))
    assert np.allclose(g[:, 1], 1.75) and g[0, 0] == pytest.approx(0.0) and g[-1, 0] == pytest.approx(40.0)
    marks = dict(
        zip(store.table.column("feature_id").to_pylist(), store.table.column("mark_type").to_pylist(), strict=True)
    )
    assert marks["-101"] == "curbstone/high"


def test_lanelet2_latlon_projection(tmp_path: Path) -> None:
    text = (DATA / "lanelet2_fixture.osm").read_text()
    stripped = "\n".join(ln for ln in text.splitlines() if "local_x" not in ln and "local_y" not in ln)
    osm = tmp_path / "no_local.osm"
    osm.write_text(stripped)
    store = l2.load(osm, origin=(49.0, 8.4))
    ref = load_map(DATA / "lanelet2_fixture.osm")
    assert len(store) == len(ref)
    for r in range(len(ref)):
        assert np.allclose(store.geometry(r), ref.geometry(r), atol=0.01)


def test_load_map_by_name_and_folder(tmp_path: Path) -> None:
    store = load_map("PIT", roots=[DATA])
    assert store.map_id == "PIT" and store.counts()["lane_centerline"] == 275
    folder = tmp_path / "map"
    folder.mkdir()
    shutil.copy(AV2_WITH_CL, folder)
    assert load_map(folder).counts()["drivable_area"] == 2
    with pytest.raises(DatasetError, match="no map named"):
        load_map("ATLANTIS", roots=[DATA])


def test_map_source_resolves_per_log_then_city() -> None:
    src = MapSource(roots=(DATA,), cache_size=2)
    assert src.resolve("austin", "0a1e6f0a-1817-4a98-b02e-db8c9327d151") == AV2_WITH_CL
    assert src.resolve("MIA", "2645") == DATA / "MIA_lane_centerlines_crop_2645.npz"
    assert src.resolve("nowhere", "nolog") is None
    assert src.resolve("MIA", "1") == DATA / "MIA_lane_centerlines_crop_2645.npz"  # not an AV2 uuid with a 1
    first = src.get("MIA", "2645")
    assert first is src.get("MIA", "2645")  # cached
    src.get("PIT", "3861")
    src.get("austin", "0a1e6f0a-1817-4a98-b02e-db8c9327d151")
    assert len(src._cache) == 2  # LRU bound holds
