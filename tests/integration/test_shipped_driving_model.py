"""The shipped driving model (``model/checkpoints/argoverse/residual``) is ``logpipe predict``'s default for
Argoverse 1, Argoverse 2 and CommonRoad datasets, runs over the lane rasters as in ``make demo``, writes them under
the forecasts in its MCAP, and its environment net reads them: the forecasts move when the raster is blanked. The
paper's network (``argoverse/paper``) stays shipped for comparison, and its environment net reads the map too."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
from mcap.reader import make_reader
from typer.testing import CliRunner

from logpipe.cli import app
from logpipe.dataset.reader import Dataset
from logpipe.model.registry import default_checkpoint
from logpipe.model.residual.meta import read_residual_meta
from logpipe.model.residual.predictor import ResidualPredictor
from logpipe.model.zhu2020.predictor import NetPredictor
from logpipe.raster.runs import find_raster_run
from logpipe.stages.train import scene_samples

MAPS = Path(__file__).resolve().parents[1] / "data" / "driving"
runner = CliRunner()


def _run(*args: str) -> str:
    result = runner.invoke(app, ["-q", *args])
    assert result.exit_code == 0, result.output
    return result.stdout


def test_argoverse_default_is_the_shipped_driving_model_and_reads_the_map(tmp_path: Path) -> None:
    shipped = default_checkpoint("argoverse1", None)
    assert shipped == default_checkpoint("argoverse2", None) == default_checkpoint("commonroad", None)
    assert shipped.parts[-2:] == ("argoverse", "residual")
    meta = read_residual_meta(shipped)
    assert meta.config.environment and meta.ood["targets"] > 1000
    assert meta.training_data is not None and len(meta.training_data.train_sources) == 101  # AV1, AV2, NGSIM files

    data = tmp_path / "av1"
    _run("ingest", str(MAPS / "20.csv"), str(MAPS / "32.csv"), "--out", str(data))
    _run("rasterise", str(data), "--map", f"MIA={MAPS / 'MIA_lane_centerlines_crop_20.npz'}", "--map",
         f"PIT={MAPS / 'PIT_lane_centerlines_crop_32.npz'}", "--rotate")
    summary = json.loads(_run("predict", str(data), "--out", str(tmp_path / "pred"), "--json"))
    assert summary["predictor"] == "residual" and Path(summary["checkpoint"]) == shipped
    # both sequences are in hash/test: the model never saw them (no warning says it did)
    assert not any("trained" in w for w in summary["warnings"]), summary["warnings"]
    assert summary["samples"] == 2 and summary["raster_run"]

    topics: dict[str, int] = {}
    for mcap in sorted((tmp_path / "pred").rglob("*.mcap")):
        with mcap.open("rb") as fh:
            for _, channel, _ in make_reader(fh).iter_messages():
                topics[channel.topic] = topics.get(channel.topic, 0) + 1
    assert topics.get("/logpipe/raster", 0) == 2 and topics.get("/logpipe/raster/grid", 0) == 2
    assert topics.get("/logpipe/predictions/scene", 0) >= 2

    ds = Dataset.open(data)
    samples = scene_samples(ds, "hash/test", rasters=find_raster_run(ds.root, None, None))
    assert all(s.raster is not None and s.raster.any() for s in samples)
    blank = [dataclasses.replace(s, raster=np.zeros_like(s.raster)) for s in samples]
    for net in (ResidualPredictor.from_checkpoint(shipped),
                NetPredictor.from_checkpoint(shipped.parent / "paper", expect_kind=ds.kind)):
        with_map, without_map = net.predict(samples, 6, seed=0), net.predict(blank, 6, seed=0)
        moved = [float(np.nanmax(np.abs(a - b))) for a, b in zip(with_map, without_map, strict=True)]
        assert min(moved) > 0.05, (net.name, moved)  # metres: the lanes change every forecast
