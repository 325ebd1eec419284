"""The ``next:`` line of a re-run ``ingest`` follows the dataset's state: with rasters drawn and no new log, it is
``predict`` (the rasters cover every log), not ``rasterise`` again. On the bundled AV1 sequences."""

from __future__ import annotations

import shutil
from pathlib import Path

from typer.testing import CliRunner

from logpipe.cli import app

runner = CliRunner()


def _next(*args: str) -> str:
    result = runner.invoke(app, list(args))
    assert result.exit_code == 0, result.output
    return result.stderr.splitlines()[-1]


def test_rerun_after_rasterise_suggests_predict(bundled: Path, driving_rasterised: Path, tmp_path: Path) -> None:
    dataset = tmp_path / "av1"
    shutil.copytree(driving_rasterised, dataset)  # the fixture is shared: rerun on a copy
    inputs = [str(bundled / "driving" / n) for n in ("20.csv", "32.csv")]
    assert _next("ingest", *inputs, "--out", str(dataset)) == (
        f"next: logpipe predict {dataset} --out {dataset}-pred   (no new log; its rasters are current)")


def test_a_first_ingest_of_a_map_format_suggests_rasterise(bundled: Path, tmp_path: Path) -> None:
    dataset = tmp_path / "fresh"
    first = _next("ingest", str(bundled / "driving" / "20.csv"), "--out", str(dataset))
    assert first.startswith(f"next: logpipe rasterise {dataset} --maps MAPS_FOLDER")
    assert _next("ingest", str(bundled / "driving" / "20.csv"), "--out", str(dataset)) == first  # no rasters yet
