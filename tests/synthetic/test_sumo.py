"""SYNTHETIC highway-speed traffic from SUMO (logpipe.synthetic.sumo / sumo_net) on a real NGSIM lanelet network:
the network converts in the map's own frame, a 20 s scene runs at highway speeds with no two cars overlapping,
the written file ingests as synthetic at its real location, and the same seed gives the same bytes."""

from __future__ import annotations

import gzip
import json
from pathlib import Path

import numpy as np
import pytest
from lxml import etree
from typer.testing import CliRunner

from logpipe.cli import app
from logpipe.dataset.reader import Dataset
from logpipe.maps import FeatureKind
from logpipe.synthetic import scenes
from logpipe.synthetic.flow import Tracks
from logpipe.synthetic.roads import Roads, build_roads

pytest.importorskip("libsumo", reason="the [sumo] extra (in dev) is not installed")
sumolib = pytest.importorskip("sumolib")

from logpipe.synthetic import sumo, sumo_net  # noqa: E402  after the optional-extra check

MAP = "commonroad/ngsim/USA_Lanker/USA_Lanker-2_10_T-1.xml"
STEPS = 200  # 20 s

pytestmark = pytest.mark.shared


@pytest.fixture(scope="module")
def lanker(shared: Path) -> tuple[scenes.LaneletSource, Roads]:
    src = scenes.ngsim_source(shared / MAP)
    return src, build_roads(src.store, src.extras, src.default_limit, np.random.default_rng(0), src.real_id)


@pytest.fixture(scope="module")
def net(lanker: tuple[scenes.LaneletSource, Roads], tmp_path_factory: pytest.TempPathFactory) -> sumo_net.SumoNet:
    return sumo_net.convert(lanker[1], tmp_path_factory.mktemp("net"))


@pytest.fixture(scope="module")
def scene(net: sumo_net.SumoNet) -> tuple[Tracks, Tracks, int]:
    raw = sumo.simulate(net, sumo.read_graph(net), np.random.default_rng([0, 1, 0]), STEPS)
    kept, dropped = scenes.remove_overlaps(raw)
    return raw, kept, dropped


def test_real_lanelet_network_converts_in_the_maps_frame(lanker: tuple[scenes.LaneletSource, Roads],
                                                         net: sumo_net.SumoNet) -> None:
    roads = lanker[1]
    sn = sumolib.net.readNet(str(net.path))
    assert len(net.edge_of_lane) + net.dropped_lanes + net.junction_lanes == len(roads)
    assert net.junction_lanes >= 10 and net.dropped_lanes <= 0.1 * len(roads)  # the intersection became a junction
    assert max(e.getLaneNumber() for e in sn.getEdges()) >= 3  # neighbours became lanes of one edge
    gaps = []
    for lane, (edge, index) in net.edge_of_lane.items():
        shape = np.array(sn.getEdge(edge).getLane(index).getShape())
        line = sumo_net.lane_points(roads, lane)
        gaps.append(np.hypot(shape[:, None, 0] - line[None, :, 0], shape[:, None, 1] - line[None, :, 1]).min(1))
    # netconvert trims lanes back at junctions but keeps the real centerline and no offset
    assert np.quantile(np.concatenate(gaps), 0.95) < 0.5
    built = net.path.stat().st_mtime_ns
    assert sumo_net.convert(roads, net.path.parent).path.stat().st_mtime_ns == built  # same map: reused
    (net.path.parent / "net.sha256").write_text("from another converter")
    assert sumo_net.convert(roads, net.path.parent).path.stat().st_mtime_ns != built  # rebuilt
    links = sum(len(sumo_net.through(roads, a, net.edge_of_lane)) for a in net.edge_of_lane)
    made = sum(len(lane.getOutgoing()) for e in sn.getEdges() for lane in e.getLanes())
    assert made >= 0.9 * links


def test_scene_drives_highway_speeds_on_the_lanes(lanker: tuple[scenes.LaneletSource, Roads],
                                                  scene: tuple[Tracks, Tracks, int]) -> None:
    raw, kept, dropped = scene
    cars = len(np.unique(raw.vid))
    assert cars >= 20 and set(np.unique(raw.step).tolist()) == set(range(STEPS))
    assert kept.speed.max() >= 25.0 and kept.speed.max() <= sumo.DESIRED[1] + 1.0
    # crossing lanes meet in SUMO junctions (foe links), so few cars need dropping for overlaps
    assert len(scenes.overlapping_pairs(kept)) == 0 and dropped <= 0.1 * cars
    # centres (not SUMO's front bumpers) lie on the real lanes, headings point where the cars go
    store = lanker[0].store
    near = store.distance_to(FeatureKind.LANE_CENTERLINE, kept.xy, max_dist=10.0) < 2.5
    assert near.mean() >= 0.97
    order = np.lexsort((kept.step, kept.vid))
    v, xy, h, s = kept.vid[order], kept.xy[order], kept.heading[order], kept.speed[order]
    moving = (v[1:] == v[:-1]) & (s[:-1] > 5.0)
    step = np.diff(xy, axis=0)[moving]
    cos = (step[:, 0] * np.cos(h[:-1][moving]) + step[:, 1] * np.sin(h[:-1][moving])) / np.hypot(*step.T)
    assert np.quantile(cos, 0.02) > 0.95
    speed_from_xy = np.hypot(*step.T) / 0.1
    assert np.median(np.abs(speed_from_xy - s[:-1][moving])) < 0.5


def test_written_scene_ingests_as_synthetic_and_is_seeded(shared: Path, tmp_path: Path) -> None:
    args = ["--shared", str(shared), "--locations", "USA_Peach", "--windows", "16", "--scene-seconds", "12"]
    assert sumo.main([*args, "--out", str(tmp_path / "a")]) == 0
    assert sumo.main([*args, "--out", str(tmp_path / "b")]) == 0
    files = sorted((tmp_path / "a" / "commonroad" / "USA_Peach").glob("*.xml.gz"))
    assert [p.name for p in files] == ["synthetic_sumo_USA_Peach-2_1_T-1_0.xml.gz",
                                       "synthetic_sumo_USA_Peach-3_1_T-1_1.xml.gz"]
    assert all(p.read_bytes() == (tmp_path / "b" / p.relative_to(tmp_path / "a")).read_bytes() for p in files)
    root = etree.fromstring(gzip.decompress(files[0].read_bytes()))
    assert root.get("source", "").startswith("SYNTHETIC") and len(root.findall("dynamicObstacle")) >= 5
    summary = json.loads((tmp_path / "a" / "generation.json").read_text())
    assert summary["windows"] == 16 and summary["scenes"] == 2 and summary["scene_cpu_s"] > 0
    hist = np.array(summary["speed_hist_1ms"])
    assert hist.sum() == summary["locations"]["USA_Peach"]["car_steps"]

    stats = tmp_path / "a" / "stats" / "USA_Peach" / "000000.json"
    before = stats.stat().st_mtime_ns
    assert sumo.main([*args, "--out", str(tmp_path / "a")]) == 0  # resumes: nothing simulated again
    assert stats.stat().st_mtime_ns == before

    out = tmp_path / "ds"
    cli = CliRunner().invoke(app, ["-q", "ingest", str(tmp_path / "a" / "commonroad"), "--out", str(out),
                                   "--no-mcap", "--workers", "1"])
    assert cli.exit_code == 0, cli.output
    ds = Dataset.open(out)
    assert ds.samples().num_rows == 16  # 12 s scenes: 8 windows each
    logs = ds.logs().to_pylist()
    assert sorted(r["log_id"] for r in logs) == ["synthetic_USA_Peach-2_1_T-1_sumo_0",
                                                 "synthetic_USA_Peach-3_1_T-1_sumo_1"]
    assert all(set(r["memberships"]) >= {"synthetic", "location/USA_Peach"} for r in logs)


def test_missing_maps_are_one_line_and_exit_2(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert sumo.main(["--shared", str(tmp_path), "--out", str(tmp_path / "o"), "--windows", "1",
                      "--locations", "USA_Peach"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "USA_Peach" in err and str(tmp_path) in err
