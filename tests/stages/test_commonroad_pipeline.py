"""CommonRoad end to end: ingest (tracks, maps in the dataset, lanes in the MCAP, shared tracks, per-location counts),
rasterise without --maps, predict and score; bad files through the CLI; the 51 real NGSIM scenarios."""

from __future__ import annotations

import itertools
import json
import re
import xml.etree.ElementTree as ET
from collections.abc import Callable
from pathlib import Path

import pytest
from foxglove_schemas_protobuf.SceneUpdate_pb2 import SceneUpdate
from mcap.reader import make_reader
from typer.testing import CliRunner

from logpipe.cli import app
from logpipe.cli.data import ingest_lines
from logpipe.dataset.reader import Dataset
from logpipe.maps import MapSource, MapStore
from logpipe.stages.ingest import IngestOptions, ingest
from logpipe.stages.predict import predict_dataset
from logpipe.stages.rasterise import rasterise_dataset

DATA = Path(__file__).resolve().parents[1] / "data" / "commonroad"
V2018 = DATA / "USA_Peach-3_1_T-1.xml"
V2020 = DATA / "USA_Peach-4_8_T-1.xml"
runner = CliRunner()


def _cars(path: Path) -> int:
    root = ET.parse(path).getroot()
    return len([*root.iter("dynamicObstacle"), *(o for o in root.iter("obstacle") if o.findtext("role") == "dynamic")])


def test_bundled_scenarios_ingest_rasterise_and_predict(tmp_path: Path,
                                                        folder_digests: Callable[[Path], dict[str, str]]) -> None:
    out = tmp_path / "cr"
    summary = ingest([DATA], IngestOptions(out=out))
    assert summary["format"] == "commonroad" and summary["logs"] == 2
    ds = Dataset.open(out)
    targets = sum(len(t) for t in ds.samples().column("target_track_ids").to_pylist())
    assert summary["by_location"] == {"USA_Peach": {"logs": 2, "tracks": _cars(V2018) + _cars(V2020),
                                                    "windows": summary["samples"], "targets": targets}}
    assert summary["samples"] == 3  # 51 steps: one 50-step window; 61 steps: two (stride 10)
    assert "shared_tracks" not in summary  # two different recordings

    # each log's map is in the dataset, and its MCAP draws every lane boundary and centerline under the agents
    own = ds.own_maps()
    assert sorted(own) == ["USA_Peach-3_1_T-1", "USA_Peach-4_8_T-1"]
    store = MapStore.read(own["USA_Peach-4_8_T-1"])
    with ds.mcap_path("USA_Peach-4_8_T-1").open("rb") as fh:
        maps = [m for _, c, m in make_reader(fh).iter_messages(topics=["/logpipe/map"])]
    assert len(maps) == 1
    entities = {e.id: e for e in SceneUpdate.FromString(maps[0].data).entities}
    assert len(entities["lanes/boundaries"].lines) == store.counts()["lane_boundary"]
    assert len(entities["lanes/centerlines"].lines) == store.counts()["lane_centerline"]
    assert all(e.frame_id == "world" for e in entities.values())

    # rasterise finds the maps itself; the rasters put the recorded cars on the road
    raster = rasterise_dataset(out, _no_maps(), rotate=True)
    assert raster["logs_without_map"] == 0 and raster["empty"] == 0 and raster["no_centre"] == 0
    assert raster["centre_role"]["target"] == summary["samples"]
    assert raster["road_vehicles"]["observed"] > 300 and raster["road_vehicles"]["share"] >= 0.95

    predicted = predict_dataset(out, tmp_path / "pred", predictor="cv", modes=1)
    assert predicted["samples"] == 3 and predicted["targets"] == targets

    again = ingest([DATA], IngestOptions(out=out))
    assert again["inputs_skipped_already_ingested"] == 2 and again["logs"] == 0
    before = folder_digests(out)
    second = tmp_path / "second"
    ingest([DATA], IngestOptions(out=second))
    assert {k: v for k, v in folder_digests(second).items() if not k.startswith("rasters/")} == \
        {k: v for k, v in before.items() if not k.startswith("rasters/")}


def _no_maps() -> MapSource:
    return MapSource()  # no --maps, no --map: each log's own map from the dataset


def _moving_cars(path: Path) -> int:
    """Cars that travel at least 1 m within some 10 consecutive states (what counts as evidence of one car)."""
    moving = 0
    for obstacle in ET.parse(path).getroot().iter("dynamicObstacle"):
        states = [obstacle.find("initialState"), *obstacle.iter("state")]
        xy = [(float(s.findtext("position/point/x")), float(s.findtext("position/point/y"))) for s in states]
        steps = [((b[0] - a[0]) ** 2 + (b[1] - a[1]) ** 2) ** 0.5 for a, b in itertools.pairwise(xy)]
        moving += any(sum(steps[i:i + 9]) >= 1.0 for i in range(len(steps) - 8))
    return moving


def _shifted_copy(source: Path, target: Path, benchmark: str, dx: float, dy: float, dt: int) -> None:
    """``source`` with another benchmark id, every x/y moved by (dx, dy) and every time step by dt: the same
    recording in another local frame and clock, as overlapping NGSIM files are."""
    tree = ET.parse(source)
    root = tree.getroot()
    root.set("benchmarkID", benchmark)
    for point in root.iter("point"):
        point.find("x").text = repr(float(point.findtext("x")) + dx)
        point.find("y").text = repr(float(point.findtext("y")) + dy)
    for obstacle in root.iter("dynamicObstacle"):
        for time in obstacle.iter("time"):
            time.find("exact").text = str(int(time.findtext("exact")) + dt)
    tree.write(target)


def test_the_same_cars_in_two_files_are_flagged_with_the_frame_offset(tmp_path: Path) -> None:
    inputs = tmp_path / "in"
    inputs.mkdir()
    (inputs / "a.xml").write_bytes(V2020.read_bytes())
    _shifted_copy(V2020, inputs / "b.xml", "USA_Peach-9_9_T-1", dx=100.5, dy=-20.25, dt=7)
    summary = ingest([inputs], IngestOptions(out=tmp_path / "ds", write_mcap=False))
    moving = _moving_cars(V2020)
    assert 0 < moving < _cars(V2020)  # the others never travel 1 m in 1 s: not evidence of being the same car
    assert summary["shared_tracks"] == {"tracks": moving, "logs": 1, "pairs": 1}
    logs = Dataset.open(tmp_path / "ds").logs().to_pylist()
    later = json.loads(next(r for r in logs if r["log_id"] == "USA_Peach-9_9_T-1")["attributes"])
    shared = later["shared_tracks"]["USA_Peach-4_8_T-1"]
    assert len(shared["tracks"]) == moving
    assert shared["offset_m"] == [-100.5, 20.25] and shared["offset_s"] == -0.7
    earlier = json.loads(next(r for r in logs if r["log_id"] == "USA_Peach-4_8_T-1")["attributes"])
    assert "shared_tracks" not in earlier

    # the human summary says the same, per location, and that rasterise needs no --maps for these logs
    text = "\n".join(ingest_lines(summary))
    assert f"USA_Peach: 2 logs, {2 * _cars(V2020)} tracks" in text
    assert f"{moving} tracks recur in another log of their location (1 log pairs)" in text
    assert f"next: logpipe rasterise {tmp_path / 'ds'} --rotate" in text


def test_bad_file_exits_2_with_one_line_or_is_quarantined(tmp_path: Path) -> None:
    inputs = tmp_path / "in"
    inputs.mkdir()
    (inputs / "good.xml").write_bytes(V2020.read_bytes())
    text = V2018.read_text()
    (inputs / "bad.xml").write_text(re.sub(r"<type>car</type>", "<type>hovercraft</type>", text, count=1))
    failed = runner.invoke(app, ["ingest", str(inputs), "--out", str(tmp_path / "ds")])
    assert failed.exit_code == 2
    line = failed.output.strip().splitlines()[-1]
    assert "bad.xml:" in line and "field 'type'" in line and "obstacle 405" in line and "hovercraft" in line
    assert not (tmp_path / "ds" / "manifest.json").exists()
    skipped = runner.invoke(app, ["-q", "ingest", str(inputs), "--out", str(tmp_path / "ds"), "--on-error", "skip",
                                  "--json"])
    assert skipped.exit_code == 0, skipped.output
    report = json.loads(skipped.stdout)
    assert report["logs"] == 1 and [q["path"] for q in report["quarantined"]] == ["bad.xml"]
    assert report["quarantined"][0]["error"]["field"] == "type"


@pytest.mark.slow
@pytest.mark.shared
def test_real_ngsim_scenarios(shared: Path, tmp_path: Path) -> None:
    ngsim = shared / "commonroad" / "ngsim"
    summary = ingest([ngsim], IngestOptions(out=tmp_path / "ngsim", write_mcap=False))
    files = sorted(ngsim.rglob("*.xml"))
    assert summary["logs"] == len(files) == 51
    cars = {loc.name: sum(_cars(p) for p in loc.glob("*.xml")) for loc in ngsim.iterdir()}
    assert cars == {"USA_US101": 992, "USA_Lanker": 984, "USA_Peach": 83}  # ../shared/data/commonroad/SOURCE.md
    assert {k: v["tracks"] for k, v in summary["by_location"].items()} == cars
    assert {k: v["logs"] for k, v in summary["by_location"].items()} == {"USA_Lanker": 16, "USA_Peach": 7,
                                                                         "USA_US101": 28}
    assert summary["shared_tracks"]["tracks"] > 0
    ds = Dataset.open(tmp_path / "ngsim")
    logs = {r["log_id"]: json.loads(r["attributes"]) for r in ds.logs().to_pylist()}
    # a pair found by hand: Lankershim 2_13 and 2_14 show the same cars 2 s apart in frames (7.25, -5.21) m apart
    pair = logs["USA_Lanker-2_14_T-1"]["shared_tracks"]["USA_Lanker-2_13_T-1"]
    assert len(pair["tracks"]) >= 20 and pair["offset_m"] == [7.2528, -5.2104] and pair["offset_s"] == 2.0
    raster = rasterise_dataset(tmp_path / "ngsim", _no_maps(), rotate=True)
    assert raster["empty"] == 0 and raster["road_vehicles"]["share"] >= 0.95
    assert isinstance(MapStore.read(next(iter(ds.own_maps().values()))), MapStore)
