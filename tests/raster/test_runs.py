"""``find_raster_run``, the one rule for choosing a raster run, on runs rendered from the bundled AV1 maps."""

from __future__ import annotations

from pathlib import Path

import pytest

from logpipe.errors import DatasetError
from logpipe.maps import MapSource
from logpipe.raster.rasteriser import RasterSpec
from logpipe.raster.runs import find_raster_run
from logpipe.stages.ingest import IngestOptions, ingest
from logpipe.stages.rasterise import rasterise_dataset

DATA = Path(__file__).resolve().parents[1] / "data" / "maps"


def test_named_run_else_the_only_one_else_an_error_naming_them(tmp_path: Path) -> None:
    src = tmp_path / "csv"
    src.mkdir()
    for name in ("2645.csv", "3861.csv"):
        (src / name).write_text((DATA / name).read_text())
    ds = tmp_path / "ds"
    ingest([src], IngestOptions(out=ds, format="argoverse1", write_mcap=False, workers=1))
    maps = MapSource(roots=(DATA,))
    channels = len(RasterSpec().channels)

    assert find_raster_run(ds, None, None) is None  # no run: each caller decides whether it needs one
    first = Path(rasterise_dataset(ds, maps, rotate=True)["run_dir"]).name
    only = find_raster_run(ds, None, None)
    assert only is not None and only.run_dir.name == first and only.spec.rotate
    assert find_raster_run(ds, None, channels + 1) is None  # no run renders that many channels

    second = Path(rasterise_dataset(ds, maps, rotate=False)["run_dir"]).name
    for wanted in (None, channels):
        with pytest.raises(DatasetError, match="several raster runs fit") as err:
            find_raster_run(ds, None, wanted)
        assert first in str(err.value) and second in str(err.value) and "--raster-run" in str(err.value)
    named = find_raster_run(ds, second, channels)
    assert named is not None and named.run_dir.name == second and not named.spec.rotate
    with pytest.raises(DatasetError, match="no finished raster run 'nosuch'"):
        find_raster_run(ds, "nosuch", None)
