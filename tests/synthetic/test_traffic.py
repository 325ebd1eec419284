"""SYNTHETIC traffic on real AV1 lane graphs (logpipe.synthetic.traffic): the vehicles follow the lanes and their
successor links, respect their speed and acceleration bounds, split at forks, keep out of the held-out box when
training, are deterministic for a seed, and the CSVs go through ingest and rasterise like real AV1 files."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from logpipe.dataset.reader import Dataset
from logpipe.maps import FeatureKind, MapSource, load_map
from logpipe.raster.runs import find_raster_run
from logpipe.stages.ingest import IngestOptions, ingest
from logpipe.stages.rasterise import rasterise_dataset
from logpipe.synthetic.driving import SimConfig, SimWindow, simulate_window
from logpipe.synthetic.lanes import LaneGraph
from logpipe.synthetic.traffic import city_maps, generate, main, plan_city

CFG = SimConfig()
HALF_LANE_M = 1.85
"""Half a 3.7 m lane: a vehicle farther than this from every centerline has left the road."""


@pytest.fixture(scope="module")
def mia_crop(bundled: Path) -> Path:
    return bundled / "maps" / "MIA_lane_centerlines_crop_2645.npz"


@pytest.fixture(scope="module")
def crop_windows(mia_crop: Path) -> tuple[LaneGraph, list[SimWindow]]:
    graph = LaneGraph.from_path(mia_crop)
    allowed = np.ones(len(graph), dtype=bool)
    wins = [simulate_window(graph, allowed, np.random.default_rng([7, k]), CFG) for k in range(80)]
    assert all(w is not None for w in wins)
    return graph, [w for w in wins if w is not None]


def _check_window_physics(graph: LaneGraph, store_path: Path, wins: list[SimWindow]) -> None:
    store = load_map(store_path)
    for w in wins:
        assert w.positions.shape[1:] == (CFG.steps, 2) and np.isfinite(w.positions).all()
        d = store.distance_to(FeatureKind.LANE_CENTERLINE, w.positions.reshape(-1, 2), max_dist=5.0)
        assert d.max() < HALF_LANE_M
        for r in w.routes:
            for a, b in zip(r.lanes[:-1], r.lanes[1:], strict=True):
                assert b in graph.successors[a]
        assert (w.speeds >= 0).all() and w.speeds.max() <= CFG.v_desired[1] + 1e-9
        assert w.accels.min() >= -CFG.b_max - 1e-9 and w.accels.max() <= CFG.a_max + 1e-9
        # Speeds read back from the written positions (the lateral wander adds a little).
        step = np.hypot(*np.diff(w.positions, axis=1).transpose(2, 0, 1)) / CFG.dt
        assert step.max() < CFG.v_desired[1] + 1.0
        assert w.min_gap >= 0.0  # two vehicles on one lane never overlap


def test_derived_successors_join_end_to_start(crop_windows: tuple[LaneGraph, list[SimWindow]]) -> None:
    graph, _ = crop_windows
    assert graph.derived_links and len(graph.forks) > 5
    for a, succ in enumerate(graph.successors):
        for b in succ:
            assert np.hypot(*(graph.lines[b][0] - graph.lines[a][-1])) < 1.0


def test_vehicles_follow_lanes_within_bounds(mia_crop: Path, crop_windows: tuple[LaneGraph, list[SimWindow]]) -> None:
    graph, wins = crop_windows
    _check_window_physics(graph, mia_crop, wins)
    assert np.mean([len(w.routes) for w in wins]) > 5  # traffic, not a lone car


def test_forks_split(crop_windows: tuple[LaneGraph, list[SimWindow]]) -> None:
    _, wins = crop_windows
    chosen: dict[str, set[str]] = {}
    for w in wins:
        for fork, succ in w.fork_choices:
            chosen.setdefault(fork, set()).add(succ)
    assert sum(len(s) >= 2 for s in chosen.values()) >= 3


def _points(folder: Path) -> tuple[list[Path], np.ndarray]:
    files = sorted(folder.glob("*.csv"))
    xy = np.concatenate([pd.read_csv(f)[["X", "Y"]].to_numpy() for f in files]) if files else np.zeros((0, 2))
    return files, xy


def test_holdout_determinism_and_ingest(bundled: Path, tmp_path: Path) -> None:
    maps = bundled / "maps"
    kwargs = {"test_fraction": 0.25, "holdout_fraction": 0.35, "holdout_margin": 20.0, "progress": False}
    summary = generate(maps, tmp_path / "a", 24, seed=3, **kwargs)  # type: ignore[arg-type]
    generate(maps, tmp_path / "b", 24, seed=3, **kwargs)  # type: ignore[arg-type]
    generate(maps, tmp_path / "c", 24, seed=4, **kwargs)  # type: ignore[arg-type]
    assert summary["windows_written"] == 24 and summary["windows_failed"] == 0
    a_files = sorted(p.relative_to(tmp_path / "a") for p in (tmp_path / "a").rglob("*.csv"))
    assert a_files == sorted(p.relative_to(tmp_path / "b") for p in (tmp_path / "b").rglob("*.csv"))
    assert all((tmp_path / "a" / f).read_bytes() == (tmp_path / "b" / f).read_bytes() for f in a_files)
    assert any((tmp_path / "a" / f).read_bytes() != (tmp_path / "c" / f).read_bytes() for f in a_files)
    assert all(f.name.startswith("synthetic_") for f in a_files)
    assert "SYNTHETIC" in (tmp_path / "a" / "README.md").read_text()
    for f in a_files:  # the AV1 layout: one AV and one AGENT over all 50 steps, one city
        frame = pd.read_csv(tmp_path / "a" / f)
        kinds = frame.groupby("OBJECT_TYPE")["TRACK_ID"].agg(["nunique", "size"])
        assert kinds.loc["AV"].tolist() == [1, 50] and kinds.loc["AGENT"].tolist() == [1, 50]
        assert frame["TIMESTAMP"].nunique() == 50 and frame["CITY_NAME"].nunique() == 1

    for city, path in city_maps(maps).items():
        plan = plan_city(path, 0.35, 20.0)
        train_files, train_xy = _points(tmp_path / "a" / "train")
        test_files, test_xy = _points(tmp_path / "a" / "test")
        own_train = np.concatenate([pd.read_csv(f)[["X", "Y"]].to_numpy() for f in train_files if city in f.name])
        own_test = np.concatenate([pd.read_csv(f)[["X", "Y"]].to_numpy() for f in test_files if city in f.name])
        assert plan.holdout.clear(own_train).all()
        assert plan.holdout.inside(own_test).all()
        assert len(train_xy) and len(test_xy)

    out = tmp_path / "ds"
    result = ingest([tmp_path / "a" / "train", tmp_path / "a" / "test"],
                    IngestOptions(out=out, workers=1, write_mcap=False))
    assert result["logs"] == 24 and result["samples"] == 24
    ds = Dataset.open(out)
    assert all(str(log).split("/")[-1].startswith("synthetic_") for log in ds.logs().column("log_id").to_pylist())
    sample = next(ds.iter_scene_samples())
    assert sample.ego_index >= 0 and sample.positions.shape[1:] == (50, 2) and sample.target_mask.sum() == 1
    rasterise_dataset(out, MapSource(roots=(maps,)), rotate=True)
    run = find_raster_run(out, None, None)
    assert run is not None and len(run) == 24
    raster, _ = run.get(sample.sample_id)
    assert raster.any()  # the crop's lanes are drawn under the synthetic window


def test_cli_writes_train_and_test(bundled: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    code = main(["--maps", str(bundled / "maps"), "--out", str(tmp_path), "--windows", "10", "--seed", "1",
                 "--holdout-fraction", "0.35", "--holdout-margin", "20", "--cities", "PIT"])
    assert code == 0
    assert len(list((tmp_path / "train").glob("synthetic_PIT_*.csv"))) == 8
    assert len(list((tmp_path / "test").glob("synthetic_PIT_*.csv"))) == 2
    assert "windows/s" in capsys.readouterr().err


@pytest.mark.shared
def test_real_city_graphs(shared: Path) -> None:
    maps = city_maps(shared / "argoverse1" / "maps")
    assert set(maps) == {"MIA", "PIT"}
    for path in maps.values():
        plan = plan_city(path, 0.15, 75.0)
        graph = plan.graph
        assert len(graph.forks) > 500 and plan.test.sum() > 500 and plan.train.sum() > 3000
        assert not (plan.train & plan.test).any()
        wins = [simulate_window(graph, plan.train, np.random.default_rng([0, k]), CFG) for k in range(15)]
        done = [w for w in wins if w is not None]
        assert len(done) == 15
        _check_window_physics(graph, path, done)
        assert all(plan.holdout.clear(w.positions).all() for w in done)
        test_wins = [simulate_window(graph, plan.test, np.random.default_rng([1, k]), CFG) for k in range(5)]
        assert all(w is not None and plan.holdout.inside(w.positions).all() for w in test_wins)
