"""Ingest → rasterise on the real Argoverse 1 and Argoverse 2 data with their real maps."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from logpipe.maps import MapSource
from logpipe.raster.rasteriser import RasterSpec
from logpipe.raster.runs import RasterShards
from logpipe.stages.ingest import IngestOptions, ingest
from logpipe.stages.rasterise import rasterise_dataset
from logpipe.types import PROTOCOLS


def test_av2_scenario_and_sensor_logs_rasterise_with_their_maps(shared: Path, tmp_path: Path) -> None:
    av2 = shared / "av2"
    scenario = ingest([next(av2.glob("scenario_*.parquet"))], IngestOptions(out=tmp_path / "scenario"))
    assert scenario["samples"] == 1
    logs = ingest([av2 / "sensor_logs"], IngestOptions(out=tmp_path / "sensor", protocol=PROTOCOLS["rosbag"]))
    assert logs["logs"] == 4 and logs["samples"] > 0
    for name, roots in (("scenario", (av2,)), ("sensor", (av2 / "sensor_logs",))):
        summary = rasterise_dataset(tmp_path / name, MapSource(roots=roots), rotate=True)
        assert summary["rendered"] == summary["samples"] > 0
        assert summary["empty"] == 0 and summary["logs_without_map"] == 0
        shards = RasterShards.open(tmp_path / name, RasterSpec(rotate=True))
        image, _ = shards.get(shards.index.column("sample_id")[0].as_py())
        drivable = list(shards.spec.channels).index("drivable_area")
        assert image[drivable].mean() > 5  # AV2 maps carry drivable areas: the ego stands on road


def test_all_argoverse1_samples_rasterise_on_lanes(shared: Path, tmp_path: Path) -> None:
    ingest([shared / "argoverse1" / "data"], IngestOptions(out=tmp_path / "av1", write_mcap=False))
    summary = rasterise_dataset(tmp_path / "av1", MapSource(roots=(shared / "argoverse1" / "maps",)), rotate=True)
    assert summary["rendered"] == 69 and summary["empty"] == 0
    shards = RasterShards.open(tmp_path / "av1", RasterSpec(rotate=True))
    lanes = [i for i, c in enumerate(shards.spec.channels) if c.startswith("lane_") and c != "lane_boundary"]
    for sample_id in shards.index.column("sample_id").to_pylist():
        image, _ = shards.get(sample_id)
        centre = image[lanes, 100:124, 100:124].max()
        assert centre > 0, sample_id  # the ego (at the centre) is on or within ~5 m of a drawn lane
    assert np.isfinite(shards.get("1:0")[1]).all()
