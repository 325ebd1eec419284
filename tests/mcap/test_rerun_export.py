"""``logpipe export --format rrd``: every viewer draws the scene. Prediction runs over an Argoverse 1 log (with its
lane raster), an ETH/UCY log and a ROS bag are exported, each ``.rrd`` is read back with ``rerun-sdk`` and what it
draws is counted per entity: agent boxes, history / truth / forecast line strips, current-position points, lane
strips and the raster image; its timeline is checked against the log's own clock (the dataset's track times and
frame rate), its blueprint and labels are read back; the Foxglove side (the prediction MCAP's own channels) is
checked on the same runs."""

from __future__ import annotations

import json
from collections import Counter
from pathlib import Path

import pytest
from foxglove_schemas_protobuf.SceneUpdate_pb2 import SceneUpdate
from mcap.reader import make_reader
from typer.testing import CliRunner

from logpipe.cli import app
from logpipe.dataset.reader import Dataset
from logpipe.mcap.forecast_scene import TRUTH_RGBA
from logpipe.mcap.raster_image import raster_rgb
from logpipe.mcap.rerun_export import TIMELINE

rerun_chunk = pytest.importorskip("rerun.chunk")  # in the dev extra: CI runs this test
runner = CliRunner()

_INSTANCES = {"Boxes3D:centers", "LineStrips3D:strips", "Points3D:positions", "EncodedImage:blob",
              "TextDocument:text"}


def _cli(*args: str) -> dict[str, object]:
    result = runner.invoke(app, [*args, "--json"])
    assert result.exit_code == 0, result.output
    summary: dict[str, object] = json.loads(result.stdout)
    return summary


def drawn(rrd: Path) -> Counter[str]:
    """Instances drawn per entity over the whole recording (boxes, strips, points, images, texts), read back with
    rerun-sdk's own reader."""
    counts: Counter[str] = Counter()
    for chunk in rerun_chunk.RrdReader(rrd).store().stream():
        batch = chunk.to_record_batch()
        for name in batch.schema.names:
            if name in _INSTANCES:
                rows = batch.column(name).to_pylist()
                counts[chunk.entity_path] += sum(len(r) if isinstance(r, list) else 1 for r in rows if r is not None)
    return counts


@pytest.fixture(scope="module")
def runs(bundled: Path, tmp_path_factory: pytest.TempPathFactory) -> dict[str, tuple[Path, Path]]:
    """(dataset, constant-velocity prediction run) of one AV1 log with its lane raster, the ETH/UCY sample's ETH
    test log, and the bundled ROS bag."""
    root = tmp_path_factory.mktemp("viewers")
    driving = bundled / "driving"
    _cli("ingest", str(driving / "20.csv"), "--out", str(root / "av1"))
    _cli("rasterise", str(root / "av1"), "--map", f"MIA={driving / 'MIA_lane_centerlines_crop_20.npz'}", "--rotate")
    _cli("predict", str(root / "av1"), "--predictor", "cv", "--out", str(root / "av1-pred"))
    _cli("ingest", str(bundled / "ethucy" / "eth" / "test"), "--out", str(root / "eth"))
    _cli("predict", str(root / "eth"), "--predictor", "cv", "--out", str(root / "eth-pred"))
    bags = bundled / "rosbags" / "datmo"
    _cli("ingest", str(bags / "intersection.bag"), "--out", str(root / "ros"))
    _cli("predict", str(root / "ros"), "--predictor", "cv", "--inputs", str(bags), "--out", str(root / "ros-pred"))
    return {name: (root / name, root / f"{name}-pred") for name in ("av1", "eth", "ros")}


def _export(run: Path, out: Path) -> dict[str, Path]:
    summary = _cli("export", str(run), "--format", "rrd", "--out", str(out))
    files = summary["files"]
    assert isinstance(files, list) and files
    return {Path(f["rrd"]).stem: Path(f["rrd"]) for f in files}


def test_rerun_draws_agents_forecasts_truth_and_lanes_of_an_av1_log(runs: dict[str, tuple[Path, Path]],
                                                                     tmp_path: Path) -> None:
    rrds = _export(runs["av1"][1], tmp_path)
    assert sorted(rrds) == ["20"]
    counts = drawn(rrds["20"])
    samples = 1  # Argoverse: one window per log, its AGENT the target
    assert counts["/agents"] >= 50 * 10  # boxes of every agent at each of the log's 50 steps
    assert counts["/forecasts/history"] == counts["/forecasts/truth"] == counts["/forecasts/current"] == samples
    assert counts["/forecasts/modes"] == 6 * samples
    cells = _lane_cells(next((runs["av1"][1] / "mcap").rglob("20.mcap")))
    assert cells > 1000  # lane and boundary cells of the raster ...
    assert 0 < counts["/lanes"] < cells / 20  # ... drawn as strips along them, not a point per cell
    assert counts["/raster"] == samples and counts["/legend"] == 1


def test_rerun_draws_pedestrians_and_their_forecasts_of_an_eth_log(runs: dict[str, tuple[Path, Path]],
                                                                   tmp_path: Path) -> None:
    rrds = _export(runs["eth"][1], tmp_path)
    counts = drawn(rrds["biwi_eth"])
    targets = sum(len(t) for t in _targets(runs["eth"][0], "biwi_eth"))
    assert counts["/agents"] > 1000
    assert counts["/forecasts/truth"] == counts["/forecasts/current"] == targets > 0
    assert counts["/forecasts/modes"] == 20 * targets
    assert "/lanes" not in counts and "/raster" not in counts  # ETH/UCY has no map


def test_rerun_and_foxglove_draw_the_agents_of_a_ros_bag(runs: dict[str, tuple[Path, Path]], tmp_path: Path) -> None:
    rrds = _export(runs["ros"][1], tmp_path)
    counts = drawn(rrds["intersection"])
    assert counts["/agents"] > 0 and counts["/forecasts/truth"] > 0 and counts["/forecasts/modes"] > 0
    # Foxglove: the prediction MCAP adds the agents' boxes (the bag itself has none) and a legend
    mcap = next((runs["ros"][1] / "mcap").rglob("intersection.mcap"))
    boxes, legend = 0, []
    with mcap.open("rb") as fh:
        for _schema, channel, message in make_reader(fh).iter_messages():
            if channel.topic == "/logpipe/scene":
                boxes += sum(len(e.cubes) for e in SceneUpdate.FromString(message.data).entities)
            elif channel.topic == "/logpipe/legend":
                legend += [t.text for e in SceneUpdate.FromString(message.data).entities for t in e.texts]
    assert boxes == counts["/agents"]
    assert legend == ["history", "truth", "forecasts", "lanes"]


def _column(rrd: Path, entity: str, name: str) -> list[object]:
    """Every value of column ``name`` of ``entity``'s chunks in the recording store of ``rrd``."""
    values: list[object] = []
    for chunk in rerun_chunk.RrdReader(rrd).store().stream():
        batch = chunk.to_record_batch()
        if chunk.entity_path == entity and name in batch.schema.names:
            values += batch.column(name).to_pylist()
    return values


@pytest.mark.parametrize("name,log_id", [("av1", "20"), ("ros", "intersection")])
def test_rerun_timeline_keeps_the_logs_own_clock_and_rate(runs: dict[str, tuple[Path, Path]], tmp_path: Path,
                                                         name: str, log_id: str) -> None:
    """The boxes' times read back from the .rrd are the log's own track times, every step of it, so
    its sensor rate too (AV1's uneven ~0.1 s steps, the bag resampled to 10 Hz); Rerun's ``log_time`` would hold the
    export's wall clock."""
    dataset, run = runs[name]
    rrd = _export(run, tmp_path)[log_id]
    times = sorted({int(t.value) for t in _column(rrd, "/agents", TIMELINE)})  # type: ignore[attr-defined]
    ds = Dataset.open(dataset)
    stamps = [t for shard in ds.shard_paths
              for t, log in zip(*_track_times(shard), strict=True) if log == log_id]
    assert times == sorted(set(stamps))
    assert times[-1] - times[0] > 4e9  # seconds of log, where the wall clock of an export spans ~0.02 s
    assert not _column(rrd, "/agents", "log_time")


def test_rerun_labels_are_short_and_opens_a_3d_view_beside_the_raster(runs: dict[str, tuple[Path, Path]],
                                                                     tmp_path: Path) -> None:
    rrd = _export(runs["av1"][1], tmp_path)["20"]
    labels = _column(rrd, "/agents", "Boxes3D:labels")
    ids = _column(rrd, "/agents", "track_id")
    assert labels and len(labels) == len(ids)
    for step_labels, step_ids in zip(labels, ids, strict=True):
        assert isinstance(step_labels, list) and isinstance(step_ids, list)
        assert max(len(x) for x in step_ids) == 36  # AV1's UUID-shaped track ids ...
        assert max(len(x) for x in step_labels) <= 10  # ... labelled by their end
        assert len(set(step_labels)) == len(step_labels)
        assert all(i.endswith(short) for i, short in zip(step_ids, step_labels, strict=True))
    reader = rerun_chunk.RrdReader(rrd)
    views: dict[str, str] = {}
    timeline: list[str] = []
    for chunk in reader.store(store=reader.blueprints()[0]).stream():
        row = chunk.to_record_batch().to_pylist()[0]
        if "ViewBlueprint:class_identifier" in row:
            views[row["ViewBlueprint:class_identifier"][0]] = row["ViewBlueprint:space_origin"][0]
        timeline += row.get("TimePanelBlueprint:timeline") or []
    assert views == {"3D": "/", "2D": "/raster", "TextDocument": "/legend"}
    assert timeline == [TIMELINE]


def _track_times(shard: Path) -> tuple[list[int], list[str]]:
    import pyarrow.compute as pc
    import pyarrow.parquet as pq

    table = pq.read_table(shard, columns=["timestamp_ns", "log_id"])
    return table.column("timestamp_ns").to_pylist(), pc.cast(table.column("log_id"), "string").to_pylist()


def _lane_cells(mcap: Path) -> int:
    """Cells with a lane or boundary drawn in the raster grids of a prediction MCAP."""
    import numpy as np
    from foxglove_schemas_protobuf.Grid_pb2 import Grid

    cells = 0
    with mcap.open("rb") as fh:
        for _schema, channel, message in make_reader(fh).iter_messages():
            if channel.topic == "/logpipe/raster/grid":
                grid = Grid.FromString(message.data)
                data = np.frombuffer(grid.data, np.uint8).reshape(-1, grid.column_count, grid.cell_stride)
                offsets = {f.name: f.offset for f in grid.fields}
                cells += int(((data[..., offsets["green"]] > 0) | (data[..., offsets["blue"]] > 0)).sum())
    return cells


def test_truth_is_drawn_apart_from_the_lanes_colour() -> None:
    import numpy as np

    lanes = raster_rgb(np.full((1, 2, 2), 255, np.uint8), ["lane_centerline"])[0, 0] / 255
    truth = np.array(TRUTH_RGBA[:3])
    assert np.abs(lanes - truth).sum() > 1.0  # not green on green


def _targets(dataset: Path, log_id: str) -> list[list[str]]:
    samples = Dataset.open(dataset).samples().to_pylist()
    return [s["target_track_ids"] for s in samples if s["log_id"] == log_id]
