"""The rasterise stage on a dataset ingested from the AV1 fixture CSVs."""

from __future__ import annotations

import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from logpipe.errors import DatasetError
from logpipe.maps import MapSource, load_map
from logpipe.raster.rasteriser import Rasteriser, RasterSpec, heading_from_motion
from logpipe.raster.runs import RasterShards
from logpipe.stages.ingest import IngestOptions, ingest
from logpipe.stages.rasterise import rasterise_dataset
from logpipe.storage.artifact import read_manifest
from logpipe.storage.io import sha256_file

DATA = Path(__file__).parents[1] / "data" / "maps"


def _dataset(tmp: Path, drop_av_in: str | None = None) -> Path:
    src = tmp / "csv"
    src.mkdir()
    for name in ("2645.csv", "3861.csv"):
        text = (DATA / name).read_text()
        if name == drop_av_in:  # a log without an ego
            text = "\n".join(ln for ln in text.splitlines() if ",AV," not in ln) + "\n"
        (src / name).write_text(text)
    out = tmp / "ds"
    ingest([src], IngestOptions(out=out, format="argoverse1", write_mcap=False, workers=1))
    return out


@pytest.fixture(scope="module")
def dataset(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return _dataset(tmp_path_factory.mktemp("stage"))


def test_stage_writes_index_shards_and_previews(dataset: Path) -> None:
    maps = MapSource(roots=(DATA,))
    summary = rasterise_dataset(dataset, maps, centre="ego", rotate=True, preview=2, shard_size=1)
    assert summary["samples"] == 2 and summary["rendered"] == 2 and summary["empty"] == 0
    assert summary["centre_role"] == {"ego": 2, "focal": 0, "target": 0}
    run = Path(summary["run_dir"])
    assert [s["rows"] for s in read_manifest(run)["shards"]] == [1, 1]  # type: ignore[index]
    assert len(list(run.glob("shard-*.npy"))) == 2
    for png in summary["previews"]:
        img = cv2.imread(png)
        assert img is not None and img.shape == (672, 672, 3)

    shards = RasterShards.open(dataset, RasterSpec(rotate=True), centre="ego")
    assert len(shards) == 2
    for sid, log_id in zip(
        shards.index.column("sample_id").to_pylist(), shards.index.column("log_id").to_pylist(), strict=True
    ):
        image, affine = shards.get(sid)
        assert image.shape == RasterSpec().shape and image.dtype == np.uint8
        # Same pixels as rendering the AV at step 19 directly, rotated to its motion.
        csv = (DATA / f"{log_id}.csv").read_text().splitlines()[1:]
        av = [ln.split(",") for ln in csv if ",AV," in ln]
        xy = np.array([[float(r[3]), float(r[4])] for r in sorted(av, key=lambda r: float(r[0]))])[:20]
        city = av[0][5]
        store = load_map(city, roots=[DATA])
        h = heading_from_motion(xy)
        if h is None:
            h = store.lane_direction_at(*xy[-1])
        ref = Rasteriser(store, RasterSpec(rotate=True)).render(*xy[-1], h)
        assert np.array_equal(image, ref.image)
        assert np.allclose(affine, ref.affine)

    with pytest.raises(DatasetError, match="no finished raster run"):
        RasterShards.open(dataset, RasterSpec(rotate=True, extent_m=80.0))
    with pytest.raises(DatasetError, match="no finished raster run"):
        RasterShards.open(dataset, RasterSpec(rotate=False))


def test_rerun_skips_and_repairs_identically(dataset: Path) -> None:
    maps = MapSource(roots=(DATA,))
    first = rasterise_dataset(dataset, maps, centre="ego", rotate=False, shard_size=1)
    run = Path(first["run_dir"])
    before = {p.name: sha256_file(p) for p in run.iterdir() if p.is_file()}
    again = rasterise_dataset(dataset, maps, centre="ego", rotate=False, shard_size=1)
    assert again["skipped_existing"] == 2 and again["rendered"] == 0
    assert {p.name: sha256_file(p) for p in run.iterdir() if p.is_file()} == before
    assert not list(run.glob(".*.tmp"))
    # Another shard size is another set of files: refused, not mixed with the committed ones.
    with pytest.raises(DatasetError, match=r"shard_size \(shard size was 1\)"):
        rasterise_dataset(dataset, maps, centre="ego", rotate=False, shard_size=2)
    resharded = rasterise_dataset(dataset, maps, centre="ego", rotate=False, shard_size=2, force=True)
    assert resharded["rendered"] == 2 and len(list(run.glob("shard-*.npy"))) == 1
    assert len(RasterShards.open(dataset, RasterSpec(rotate=False), centre="ego")) == 2
    # A committed shard that disappears is damage: the reader refuses it instead of reading fewer rasters.
    next(run.glob("shard-*.npy")).unlink()
    with pytest.raises(DatasetError, match="missing"):
        RasterShards.open(dataset, RasterSpec(rotate=False), centre="ego")


def test_stale_run_is_refused_then_replaced_with_force(dataset: Path, tmp_path: Path) -> None:
    maps = MapSource(roots=(DATA,))
    rasterise_dataset(dataset, maps, centre="focal", rotate=False)
    moved = tmp_path / "moved"
    moved.mkdir()
    other = tmp_path / "maps"
    other.mkdir()
    for name in ("MIA_lane_centerlines_crop_2645.npz", "PIT_lane_centerlines_crop_3861.npz"):
        shutil.copy(DATA / name, moved / name)
        shutil.copy(DATA / name, other / name.replace("crop", "copy"))
    # the same map files reached by another path are the same inputs: nothing to redo, no refusal
    again = rasterise_dataset(dataset, MapSource(roots=(moved,)), centre="focal", rotate=False)
    assert again["rendered"] == 0 and again["skipped_existing"] == 2
    # two files that swapped their contents are not
    mia, pit = moved / "MIA_lane_centerlines_crop_2645.npz", moved / "PIT_lane_centerlines_crop_3861.npz"
    mia_bytes = mia.read_bytes()
    mia.write_bytes(pit.read_bytes())
    pit.write_bytes(mia_bytes)
    with pytest.raises(DatasetError, match="made with other maps"):
        rasterise_dataset(dataset, MapSource(roots=(moved,)), centre="focal", rotate=False)
    with np.load(other / "PIT_lane_centerlines_copy_3861.npz") as z:
        arrays = {k: z[k] for k in z.files}
    arrays["points"] = arrays["points"] + 0.5  # a different survey of the city
    np.savez(other / "PIT_lane_centerlines_copy_3861.npz", **arrays)
    with pytest.raises(DatasetError, match="made with other maps"):
        rasterise_dataset(dataset, MapSource(roots=(other,)), centre="focal", rotate=False)
    summary = rasterise_dataset(dataset, MapSource(roots=(other,)), centre="focal", rotate=False, force=True)
    assert summary["rendered"] == 2 and summary["centre_role"] == {"ego": 0, "focal": 2, "target": 0}


def test_log_without_ego_centres_on_focal_and_missing_map_is_empty(tmp_path: Path) -> None:
    ds = _dataset(tmp_path, drop_av_in="3861.csv")
    summary = rasterise_dataset(ds, MapSource(roots=(DATA,)), centre="ego", rotate=True)
    assert summary["centre_role"] == {"ego": 1, "focal": 1, "target": 0}
    # One log's map only: its raster is drawn, the other log's is blank, counted and named in a warning.
    half = rasterise_dataset(ds, MapSource(files={"MIA": DATA / "MIA_lane_centerlines_crop_2645.npz"}),
                             centre="ego", rotate=True, force=True)
    assert half["empty"] == 1 and half["logs_without_map"] == 1 and half["blank_with_map"] == 0
    assert half["warnings"] == ["1 logs have no map, their rasters are blank (e.g. 3861)"]


def test_maps_that_cover_no_log_are_an_error_naming_logs_and_map_ids(dataset: Path, tmp_path: Path) -> None:
    before = sorted((dataset / "rasters").rglob("*")) if (dataset / "rasters").exists() else []
    with pytest.raises(DatasetError, match=r"--maps .*/no/such: no such folder"):
        rasterise_dataset(dataset, MapSource(roots=(tmp_path / "no" / "such",)))
    (tmp_path / "empty").mkdir()
    with pytest.raises(DatasetError, match=r"no map found for any of its 2 logs \(2645, 3861; map ids looked for: "
                                           r"MIA, PIT\) under --maps .*/empty"):
        rasterise_dataset(dataset, MapSource(roots=(tmp_path / "empty",)))
    after = sorted((dataset / "rasters").rglob("*")) if (dataset / "rasters").exists() else []
    assert after == before  # refused before any run folder was made


def _run_files(run: Path) -> dict[str, bytes]:
    return {str(p.relative_to(run)): p.read_bytes() for p in sorted(run.rglob("*")) if p.is_file()}


def _parallel_matches_inline(tmp_path: Path, **kw: object) -> None:
    # Two byte-identical ingests; one rasterised inline, the other by workers: every file of the run folder
    # (shards, indexes, previews, manifest) must be the same bytes.
    inline_ds = _dataset(tmp_path / "a")
    other_ds = _dataset(tmp_path / "b")
    maps = MapSource(roots=(DATA,))
    inline = rasterise_dataset(inline_ds, maps, rotate=True, preview=2, shard_size=1)
    other = rasterise_dataset(other_ds, maps, rotate=True, preview=2, shard_size=1, **kw)  # type: ignore[arg-type]
    assert other["rendered"] == inline["rendered"] == 2
    for key in ("empty", "no_centre", "heading_source", "centre_role"):
        assert other[key] == inline[key]
    assert len(other["previews"]) == 2
    a, b = _run_files(Path(inline["run_dir"])), _run_files(Path(other["run_dir"]))
    assert sorted(a) == sorted(b) and all(a[k] == b[k] for k in a)


def test_process_pool_writes_the_same_run_as_inline(tmp_path: Path) -> None:
    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    _parallel_matches_inline(tmp_path, workers=2)


def test_ray_backend_writes_the_same_run_as_inline(tmp_path: Path) -> None:
    ray = pytest.importorskip("ray", reason="Ray is a dev dependency; install logpipe[dev]")
    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    try:
        _parallel_matches_inline(tmp_path, workers=2, backend="ray")
    finally:
        ray.shutdown()


def test_cli_rasterise_workers_and_backend_options(tmp_path: Path) -> None:
    import json

    from typer.testing import CliRunner

    from logpipe.cli import app

    ds = _dataset(tmp_path)
    runner = CliRunner()
    ok = runner.invoke(app, ["rasterise", str(ds), "--maps", str(DATA), "--rotate", "--shard-size", "1",
                             "--workers", "2", "--json"])
    assert ok.exit_code == 0, ok.output
    assert json.loads(ok.stdout)["rendered"] == 2
    bad = runner.invoke(app, ["rasterise", str(ds), "--maps", str(DATA), "--backend", "spark"])
    assert bad.exit_code == 2 and "local or ray" in bad.output


def test_predict_refuses_the_environment_net_on_blank_rasters_unless_told(tmp_path: Path) -> None:
    """Log 32's map is not given: its raster is blank, so the shipped driving model (which reads the rasters)
    refuses the run before any output, naming the count and the option; --allow-blank-rasters lets it run."""
    import logpipe
    from logpipe.errors import LogpipeError

    driving = Path(__file__).parents[1] / "data" / "driving"
    ds = tmp_path / "av1"
    logpipe.ingest([driving / "20.csv", driving / "32.csv"], out=ds, mcap=False)
    summary = logpipe.rasterise(ds, map_file=[f"MIA={driving / 'MIA_lane_centerlines_crop_20.npz'}"], rotate=True)
    assert summary["empty"] == 1 and summary["logs_without_map"] == 1
    with pytest.raises(LogpipeError, match=r"1 of the 2 selected samples have a blank raster .*--allow-blank-rasters"):
        logpipe.predict(ds, out=tmp_path / "refused", mcap=False)
    assert not (tmp_path / "refused").exists()
    assert logpipe.predict(ds, out=tmp_path / "p", mcap=False, filters=["log=20"])["samples"] == 1  # 20 has its map
    allowed = logpipe.predict(ds, out=tmp_path / "all", mcap=False, allow_blank_rasters=True)
    assert allowed["samples"] == 2
