"""SYNTHETIC pre-training traffic (logpipe.synthetic.pretrain and its roads / flow / rules / scenes): physically
plausible cars on the real lane graphs of every source (NGSIM lanelets, AV2 log maps, AV1 centerlines), each
behaviour present, deterministic for a seed, labelled synthetic, and read back by ingest + rasterise with each
source's own map and raster style."""

from __future__ import annotations

import gzip
from collections import Counter
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from lxml import etree

from logpipe.dataset.reader import Dataset
from logpipe.maps import FeatureKind, MapSource, load_map
from logpipe.stages.ingest import IngestOptions, ingest
from logpipe.stages.rasterise import rasterise_dataset
from logpipe.synthetic import scenes
from logpipe.synthetic.flow import FlowConfig, Tracks, simulate
from logpipe.synthetic.pretrain import DEMAND, HIGHWAY, Regime, car_jerks, main
from logpipe.synthetic.report import markdown, summarise
from logpipe.synthetic.roads import LaneExtras, Roads, build_roads

STEPS = 300
CFG = FlowConfig()
NGSIM = {"USA_Peach": "USA_Peach/USA_Peach-4_1_T-1.xml", "USA_Lanker": "USA_Lanker/USA_Lanker-2_10_T-1.xml",
         "USA_US101": "USA_US101/USA_US101-22_1_T-1.xml"}
AV2_MAP = "av2/sensor_logs/adcf7d18-0510-35b0-a2fa-b4cea13a6d76/map"

pytestmark = pytest.mark.shared


@pytest.fixture(scope="module")
def sources(shared: Path) -> dict[str, scenes.LaneletSource]:
    found = {loc: scenes.ngsim_source(shared / "commonroad" / "ngsim" / rel) for loc, rel in NGSIM.items()}
    found["USA_AV2"] = scenes.av2_source(next((shared / AV2_MAP).glob("log_map_archive_*.json")))
    return found


@pytest.fixture(scope="module")
def scenes_run(sources: dict[str, scenes.LaneletSource]) -> dict[str, tuple[Roads, Tracks, int]]:
    """One 30 s scene per CommonRoad source (US-101 with a denser demand, as pretrain gives it)."""
    out = {}
    for k, (loc, src) in enumerate(sorted(sources.items())):
        rng = np.random.default_rng([5, k])
        roads = build_roads(src.store, src.extras, src.default_limit, rng, src.real_id)
        cfg = FlowConfig(demand=(0.3, 0.5)) if loc == "USA_US101" else CFG
        tracks, dropped = scenes.remove_overlaps(simulate(roads, cfg, rng, STEPS))
        out[loc] = (roads, tracks, dropped)
    return out


def test_lane_graphs_carry_what_the_behaviours_need(sources: dict[str, scenes.LaneletSource],
                                                      scenes_run: dict[str, tuple[Roads, Tracks, int]]) -> None:
    peach = scenes_run["USA_Peach"][0]
    assert len(peach.signals) >= 10  # the real 2020a traffic lights and their cycles
    assert {round(v, 2) for v in sources["USA_Peach"].extras.limits.values()} == {11.18, 15.65}  # R2-1: 25, 35 mph
    for loc, (roads, _, _) in scenes_run.items():
        assert ((roads.left >= 0) | (roads.right >= 0)).sum() > 3, loc
        assert 2.5 < float(np.median(roads.widths)) < 5.0, loc
        for a, nxt in enumerate(roads.succ):
            for b in nxt:  # a link joins a lane's end to its successor's start
                gap = np.hypot(*(roads.pts[roads.start[b]] - roads.pts[roads.start[a] + roads.count[a] - 1]))
                assert gap < 2.5, (loc, roads.lane_ids[a], roads.lane_ids[b])
    assert scenes_run["USA_US101"][0].limits.max() == pytest.approx(29.0)


def test_physically_plausible(scenes_run: dict[str, tuple[Roads, Tracks, int]]) -> None:
    for loc, (_, tracks, dropped) in scenes_run.items():
        assert len(tracks.vid) > 2000, loc
        assert tracks.speed.min() >= 0.0 and tracks.speed.max() <= CFG.v_cap + 1e-9
        assert tracks.accel.min() >= -CFG.b_max - 1e-9 and tracks.accel.max() <= CFG.a_max + 1e-9
        assert np.abs(car_jerks(tracks)).max() <= 4 * CFG.jerk + 1e-6  # emergency braking builds up 4x faster
        # speeds read back from positions agree with the state speeds (no teleporting at lane joins)
        order = np.lexsort((tracks.step, tracks.vid))
        same = tracks.vid[order][1:] == tracks.vid[order][:-1]
        moved = np.hypot(*np.diff(tracks.xy[order], axis=0).T)[same] / 0.1
        gap = np.abs(moved - tracks.speed[order][1:][same])
        # the lateral part of lane changes adds to the travelled distance; a rare joint mid-change jumps a little
        assert np.quantile(gap, 0.999) < 2.0 and gap.max() < 6.0, (loc, np.quantile(gap, 0.999), gap.max())
        assert len(scenes.overlapping_pairs(tracks)) == 0
        cars = len(np.unique(tracks.vid))
        assert dropped <= 0.1 * (cars + dropped), (loc, dropped, cars)  # misses at merges and lane changes
    us101 = scenes_run["USA_US101"][1]
    assert us101.speed.max() > 25.0  # highway speeds where the road is a highway


def test_each_behaviour_is_present(scenes_run: dict[str, tuple[Roads, Tracks, int]]) -> None:
    counts: Counter[str] = Counter()
    for roads, tracks, _ in scenes_run.values():
        counts.update(e[2] for e in tracks.events)
        speed = {(k, v): s for k, v, s in zip(tracks.step.tolist(), tracks.vid.tolist(), tracks.speed, strict=True)}
        for k, vid, kind in tracks.events:
            if kind in ("junction_stop", "red_light_stop", "stop_and_go") and k < tracks.steps:
                assert speed[(k, vid)] < 0.3  # a stop is a standstill
        del roads
    for kind in ("lane_change", "turn", "merge", "red_light_stop", "junction_stop", "stop_and_go"):
        assert counts[kind] >= 3, (kind, counts)


def test_turning_cars_turn(scenes_run: dict[str, tuple[Roads, Tracks, int]]) -> None:
    _, tracks, _ = scenes_run["USA_Peach"]
    turned = {v for _, v, kind in tracks.events if kind == "turn"}
    changes = []
    for vid in turned:
        h = np.unwrap(tracks.heading[np.flatnonzero(tracks.vid == vid)])
        changes.append(abs(float(h[-1] - h[0])))
    assert turned and np.median(changes) > np.radians(30)


def _write_cr(sources: dict[str, scenes.LaneletSource], folder: Path, seed: int) -> list[Path]:
    written = []
    for k, (loc, src) in enumerate(sorted(sources.items())):
        rng = np.random.default_rng([seed, k])
        roads = build_roads(src.store, src.extras, src.default_limit, rng, src.real_id)
        tracks, _ = scenes.remove_overlaps(simulate(roads, CFG, rng, 120, warmup=40))
        path = folder / loc / f"synthetic_{src.real_id}_{k}.xml.gz"
        scenes.write_commonroad(path, src, k, tracks, 0.05, rng)
        written.append(path)
    return written


def test_commonroad_output_is_labelled_deterministic_and_round_trips(
        sources: dict[str, scenes.LaneletSource], shared: Path, tmp_path: Path) -> None:
    a = _write_cr(sources, tmp_path / "a", 1)
    b = _write_cr(sources, tmp_path / "b", 1)
    c = _write_cr(sources, tmp_path / "c", 2)
    assert [p.read_bytes() for p in a] == [p.read_bytes() for p in b]
    assert all(p.read_bytes() != q.read_bytes() for p, q in zip(a, c, strict=True))
    for path in a:
        root = etree.fromstring(gzip.decompress(path.read_bytes()))
        assert path.name.startswith("synthetic_") and root.get("benchmarkID", "").startswith("synthetic_")
        assert root.get("source", "").startswith("SYNTHETIC") and root.get("commonRoadVersion") == "2020a"
    real = etree.parse(str(shared / "commonroad" / "ngsim" / NGSIM["USA_Peach"]))
    copy = etree.fromstring(gzip.decompress(next(p for p in a if "Peach" in p.name).read_bytes()))
    assert [etree.tostring(e) for e in real.getroot().iterchildren("lanelet")] == \
        [etree.tostring(e) for e in copy.iterchildren("lanelet")]  # the lanelet network verbatim

    out = tmp_path / "ds"
    result = ingest([tmp_path / "a"], IngestOptions(out=out, workers=1, write_mcap=False))
    assert result["logs"] == 4 and result["samples"] == 4 * 8  # 12 s each: a window a second
    ds = Dataset.open(out)
    logs = ds.logs().to_pylist()
    assert {str(r["log_id"]).split("/")[-1][:10] for r in logs} == {"synthetic_"}
    locations = {m for r in logs for m in r["memberships"] if m.startswith("location/")}
    assert locations == {"location/USA_AV2", "location/USA_Lanker", "location/USA_Peach", "location/USA_US101"}
    assert all("synthetic" in r["memberships"] for r in logs)
    summary = rasterise_dataset(out, MapSource(), rotate=True)
    road = summary["road_vehicles"]
    assert road["observed"] > 1000 and road["share"] >= 0.99


def test_av1_csvs_round_trip_with_the_city_map(bundled: Path, tmp_path: Path) -> None:
    crop = bundled / "maps" / "MIA_lane_centerlines_crop_2645.npz"
    rng = np.random.default_rng(3)
    roads = build_roads(load_map(crop), LaneExtras(), scenes.CITY_LIMIT, rng, "MIA")
    tracks, _ = scenes.remove_overlaps(simulate(roads, FlowConfig(fill=0.8), rng, 200, warmup=40))
    folder = tmp_path / "csv"
    folder.mkdir()
    files = scenes.av1_windows(tracks, "MIA", "synthetic_MIA_000000", folder, rng, 20, 0.05, 5e8)
    assert files >= 5
    for f in folder.glob("*.csv"):
        frame = pd.read_csv(f)
        kinds = frame.groupby("OBJECT_TYPE")["TRACK_ID"].agg(["nunique", "size"])
        assert kinds.loc["AV"].tolist() == [1, 50] and kinds.loc["AGENT"].tolist() == [1, 50]
        assert set(frame["CITY_NAME"]) == {"MIA"} and f.name.startswith("synthetic_MIA_")
    out = tmp_path / "ds"
    result = ingest([folder], IngestOptions(out=out, workers=1, write_mcap=False))
    assert result["samples"] == files
    summary = rasterise_dataset(out, MapSource(files={"MIA": crop}), rotate=True)
    assert summary["rendered"] == files and summary["empty"] == 0
    # AV1 centerline maps have no drivable-area polygons (road_vehicles has nothing to count on): every written
    # position lies within half a lane (plus the tracking noise) of a centerline instead
    xy = np.concatenate([pd.read_csv(f)[["X", "Y"]].to_numpy() for f in folder.glob("*.csv")])
    store = load_map(crop)
    assert np.mean(store.distance_to(FeatureKind.LANE_CENTERLINE, xy, max_dist=5.0) < 1.85 + 0.15) >= 0.99


def test_cli_small_set(shared: Path, tmp_path: Path) -> None:
    assert main(["--shared", str(shared), "--out", str(tmp_path), "--scale", "0.001", "--scene-seconds", "10",
                 "--locations", "USA_Peach"]) == 0
    files = sorted((tmp_path / "commonroad" / "USA_Peach").glob("synthetic_USA_Peach-*.xml.gz"))
    assert len(files) == 6  # 35 windows at 6 a 10 s scene: 6 scenes, cycling over Peachtree's 7 real maps
    assert "SYNTHETIC" in (tmp_path / "README.md").read_text()
    summary = summarise(tmp_path)
    assert summary["windows"] == 36 and summary["locations"]["USA_Peach"]["scenes"] == 6
    assert "| USA_Peach | 6 | 36 |" in markdown(summary)
    assert main(["--shared", str(shared), "--out", str(tmp_path), "--scale", "0.001", "--scene-seconds", "10",
                 "--locations", "USA_Peach"]) == 0  # resumes: every scene is already there
    assert sorted((tmp_path / "commonroad" / "USA_Peach").glob("*.xml.gz")) == files


def test_av1_neighbours_and_invented_lights(bundled: Path) -> None:
    crop = bundled / "maps" / "MIA_lane_centerlines_crop_2645.npz"
    roads = build_roads(load_map(crop), LaneExtras(), scenes.CITY_LIMIT, np.random.default_rng(0), "MIA")
    pairs = [(a, int(b)) for a, b in enumerate(roads.left) if b >= 0] + \
        [(a, int(b)) for a, b in enumerate(roads.right) if b >= 0]
    assert len(pairs) > 50
    for a, b in pairs:  # a derived neighbour runs alongside, one lane over, the same way
        mid = roads.pts[roads.start[a] + roads.count[a] // 2]
        s_b = roads.project(b, mid)
        there, h_b = roads.at(np.array([b]), np.array([s_b]))
        assert 2.4 < float(np.hypot(*(there[0] - mid))) < 4.9
        h_a = roads.heading[roads.start[a] + roads.count[a] // 2]
        assert abs((h_b[0] - h_a + np.pi) % (2 * np.pi) - np.pi) < np.radians(15)
    # crossing approaches of one invented junction never show green together
    ends = {a: roads.heading[roads.start[a] + roads.count[a] - 1] for a in roads.signals}
    crossing = [(a, b) for a in roads.signals for b in roads.signals
                if a < b and abs(np.sin(ends[a] - ends[b])) > np.sin(np.radians(45))
                and np.hypot(*(roads.pts[roads.start[a] + roads.count[a] - 1]
                               - roads.pts[roads.start[b] + roads.count[b] - 1])) < 40.0
                and roads.signals[a].green_s == roads.signals[b].red_s]
    assert crossing
    for a, b in crossing:
        greens = [t for t in np.arange(0.0, 200.0, 0.5)
                  if not roads.signals[a].is_red(t) and not roads.signals[b].is_red(t)]
        assert not greens, (a, b, greens[:3])


def test_the_highway_regime_drives_the_real_freeway_at_speeds_no_recording_shows(
        sources: dict[str, scenes.LaneletSource]) -> None:
    src = sources["USA_US101"]
    roads = build_roads(src.store, src.extras, src.default_limit, np.random.default_rng(0), src.real_id)
    speeds = {}
    for name, regime in (("default", Regime()), ("highway", HIGHWAY)):
        rng = np.random.default_rng([7, 1])
        lanes, cfg = regime.scene(roads, FlowConfig(demand=DEMAND["USA_US101"]), rng)
        speeds[name] = simulate(lanes, cfg, rng, STEPS).speed
    real_top = 20.2  # the fastest 1 % of US-101's recorded targets move at 20.2 m/s and below (driving_lolo)
    fast = {name: float(np.mean(v >= 25.0)) for name, v in speeds.items()}
    assert fast["highway"] > 1.2 * fast["default"] and np.mean(speeds["highway"] > real_top) > 0.25
    assert speeds["highway"].max() <= HIGHWAY.v_cap + 1e-6
    assert np.mean(speeds["highway"] < 1.0) < 0.05  # free flow: lights off, light demand, cars enter at speed
    lanes, _ = HIGHWAY.scene(roads, CFG, np.random.default_rng(0))
    assert not lanes.signals and not lanes.stops and len(lanes) == len(roads)
    assert Regime().scene(roads, CFG, np.random.default_rng(0))[0] is roads  # the default set is unchanged
