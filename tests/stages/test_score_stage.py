"""``logpipe.stages.score`` end to end on small datasets with known answers."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
import pytest

from logpipe.dataset.reader import Dataset
from logpipe.errors import LogpipeError, ScoreError
from logpipe.model.kinematic.constant_velocity import ConstantVelocity, ConstantVelocitySampler
from logpipe.prediction.runs import PredictionMeta
from logpipe.prediction.table import samples_table
from logpipe.scoring.method_forecasts import load_method
from logpipe.stages.ingest import IngestOptions, ingest
from logpipe.stages.score import score
from logpipe.stages.train import scene_samples
from logpipe.storage.io import write_parquet
from logpipe.types import SceneSample


@pytest.fixture(scope="module")
def walkers(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """An ETH/UCY-format scene of pedestrians on straight lines at constant speed.

    Ped 1 walks frames 0..290 (30 steps), ped 2 frames 0..200 (21), ped 3 frames 0..190 (20): window 0 has
    3 fully observed peds, window 1 has 2, windows 2..10 have 1 (so ``min_agents`` 1 vs 2 differ).
    """
    root = tmp_path_factory.mktemp("walkers")
    rows = []
    for ped, last, v, start in ((1, 290, (0.5, 0.1), (0.0, 0.0)), (2, 200, (-0.3, 0.4), (10.0, 0.0)),
                                (3, 190, (0.0, -0.6), (5.0, 20.0))):
        for k, frame in enumerate(range(0, last + 10, 10)):
            rows.append((frame, ped, start[0] + k * v[0], start[1] + k * v[1]))
    rows.sort()
    folder = root / "raw" / "walk" / "test"
    folder.mkdir(parents=True)
    (folder / "walk.txt").write_text("".join(f"{f}\t{p}.0\t{x:.6f}\t{y:.6f}\n" for f, p, x, y in rows))
    ingest([root / "raw"], IngestOptions(out=root / "ds", format="ethucy", write_mcap=False))
    return root / "ds"


def forecasts_to_table(samples: list[SceneSample], forecasts: list[np.ndarray], *, predictor: str,
                       checkpoint_id: str, pred_len: int) -> pa.Table:
    meta = PredictionMeta(predictor=predictor, checkpoint_id=checkpoint_id, protocol=None, obs_len=8 if pred_len == 12
                          else 20, pred_len=pred_len, num_modes=forecasts[0].shape[1])
    return samples_table(meta, samples, forecasts)


def _write(table: pa.Table, path: Path) -> Path:
    write_parquet(table, path)
    return path


def _cv_table(ds_dir: Path, k: int = 1, offset: tuple[float, float] = (0.0, 0.0)) -> pa.Table:
    ds = Dataset.open(ds_dir)
    samples = scene_samples(ds, "walk/test")
    forecasts = [f + np.asarray(offset) for f in ConstantVelocity(pred_len=12).predict(samples, k, 0)]
    return forecasts_to_table(samples, forecasts, predictor="cv", checkpoint_id="constant_velocity", pred_len=12)


def test_constant_velocity_is_exact_on_straight_walkers_and_counts_follow_min_agents(
        walkers: Path, tmp_path: Path) -> None:
    pred = _write(_cv_table(walkers), tmp_path / "cv.parquet")
    every = score([pred], walkers, tmp_path / "r1", split="walk/test", min_agents=1, plots=False)
    overall = every["methods"]["cv"]["overall"]
    assert (overall["samples"], overall["agents"]) == (11, 14)
    assert overall["k1"]["ade"] == pytest.approx(0.0, abs=1e-9)
    assert overall["k1"]["fde"] == pytest.approx(0.0, abs=1e-9)
    literal = score([pred], walkers, tmp_path / "r2", split="walk/test", min_agents=2, plots=False)
    m = literal["methods"]["cv"]
    assert (m["overall"]["samples"], m["overall"]["agents"]) == (2, 5)
    assert m["counts"]["samples_below_min_agents"] == 9
    assert m["counts"]["agents_not_counted"] == 9  # forecasts exist for the dropped windows but do not count
    assert m["protocol"]["min_agents"] == 2 and m["protocol"]["step_s"] == pytest.approx(0.4)


def test_known_offset_gate_and_report_files(walkers: Path, tmp_path: Path) -> None:
    pred = _write(_cv_table(walkers, offset=(0.3, 0.4)), tmp_path / "off.parquet")
    report = score([pred], walkers, tmp_path / "r", split="walk/test", fail_above={"k1.ade": 0.45, "k1.fde": 0.6},
                   plots=False)
    k1 = report["methods"]["cv"]["overall"]["k1"]
    for key in ("ade", "fde", "ade_joint", "fde_joint", "argo_ade", "argo_fde"):
        assert k1[key] == pytest.approx(0.5)
    np.testing.assert_allclose(k1["error_by_step"], 0.5)
    assert k1["miss_rate"] == 0.0
    assert report["gate"]["failed"]
    assert [(v["metric"], v["method"]) for v in report["gate"]["violations"]] == [("k1.ade", "cv")]
    on_disk = json.loads((tmp_path / "r" / "report.json").read_text())
    assert set(on_disk) >= {"report_version", "protocol", "conventions", "methods", "gate", "plots"}
    assert set(on_disk["methods"]["cv"]) >= {"overall", "by_type", "by_log", "counts", "protocol", "ks"}
    assert on_disk["methods"]["cv"]["by_type"]["pedestrian"]["agents"] == 14
    md = (tmp_path / "r" / "report.md").read_text()
    assert "| cv | 1 | 11 | 14 | 0.50/0.50 |" in md and "FAILED: cv k1.ade" in md
    passed = score([pred], walkers, tmp_path / "r2", split="walk/test", fail_above={"k1.ade": 0.6}, plots=False)
    assert not passed["gate"]["failed"]
    with pytest.raises(ScoreError, match=r"kN\.METRIC"):
        score([pred], walkers, tmp_path / "r3", fail_above={"ade": 1.0}, plots=False)


def test_several_methods_side_by_side_with_plots(walkers: Path, tmp_path: Path) -> None:
    ds = Dataset.open(walkers)
    samples = scene_samples(ds, "walk/test")
    sampler = ConstantVelocitySampler(pred_len=12, heading_std_rad=0.2, speed_std_frac=0.2)
    sampled = forecasts_to_table(samples, sampler.predict(samples, 5, 1), predictor="cv_sampler",
                                 checkpoint_id="s", pred_len=12)
    files = [_write(_cv_table(walkers), tmp_path / "a.parquet"), _write(sampled, tmp_path / "b.parquet")]
    report = score(files, walkers, tmp_path / "r", split="walk/test", plots=True, plot_samples=4)
    assert list(report["methods"]) == ["cv", "cv_sampler"]
    s = report["methods"]["cv_sampler"]
    assert s["ks"] == [1, 5]
    # More modes never hurt the per-agent minimum; the joint minimum lies between per-agent and K=1.
    assert s["overall"]["k5"]["ade"] <= s["overall"]["k5"]["ade_joint"] <= s["overall"]["k1"]["ade"] + 1e-12
    assert s["overall"]["k5"]["argo_fde"] <= s["overall"]["k1"]["argo_fde"]
    for name in ("horizon.png", "scenes_cv.png", "scenes_cv_sampler.png"):
        assert (tmp_path / "r" / name).stat().st_size > 5000
    labelled = score(files, walkers, tmp_path / "r2", split="walk/test", plots=False, labels=["CV", "Sampler"])
    assert list(labelled["methods"]) == ["CV", "Sampler"]


def test_missing_or_broken_forecasts_are_errors_not_silent(walkers: Path, tmp_path: Path) -> None:
    table = _cv_table(walkers)
    drop = pc.and_(pc.equal(table.column("sample_id"), "walk:0"), pc.equal(table.column("track_id"), "3"))
    partial = _write(table.filter(pc.invert(drop)), tmp_path / "partial.parquet")
    with pytest.raises(ScoreError, match="1 of the 14 agents"):
        score([partial], walkers, tmp_path / "r", split="walk/test", plots=False)
    report = score([partial], walkers, tmp_path / "r", split="walk/test", plots=False, allow_missing=True)
    assert report["methods"]["cv"]["counts"]["agents_missing"] == 1
    assert report["methods"]["cv"]["overall"]["agents"] == 13
    doubled = _write(pa.concat_tables([table, table.slice(0, 1)]), tmp_path / "dup.parquet")
    with pytest.raises(LogpipeError, match=r"not agents x 1 modes x 12 steps|duplicated or missing"):
        load_method(doubled)
    with pytest.raises(LogpipeError, match="not found"):
        load_method(tmp_path / "nope.parquet")


def test_focal_agents_on_argoverse_with_k1_and_k6(bundled: Path, tmp_path: Path) -> None:
    ingest([bundled / "argoverse1"], IngestOptions(out=tmp_path / "av1", write_mcap=False))
    ds = Dataset.open(tmp_path / "av1")
    samples = list(ds.iter_scene_samples())
    sampler = ConstantVelocitySampler(pred_len=30, heading_std_rad=0.1, speed_std_frac=0.2)
    table = forecasts_to_table(samples, sampler.predict(samples, 6, 0), predictor="cv_sampler", checkpoint_id="s",
                               pred_len=30)
    report = score([_write(table, tmp_path / "p.parquet")], ds.root, tmp_path / "r", agents="focal", plots=False)
    o = report["methods"]["cv_sampler"]["overall"]
    assert o["agents"] == o["samples"] == len(samples)
    assert o["k6"]["argo_fde"] <= o["k1"]["argo_fde"]
    assert 0.0 <= o["k6"]["miss_rate"] <= o["k1"]["miss_rate"] <= 1.0
    assert report["protocol"]["horizon_s"][9] == pytest.approx(1.0)  # 10 Hz: step 10 is 1 s
