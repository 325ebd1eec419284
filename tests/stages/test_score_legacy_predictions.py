"""Predictions of the version 1 layout (one row per future step; tests/data/predictions_v1) are still read:
the same forecasts as their rows hold, the same report as the logpipe that wrote them gave, and the same report
as the same forecasts in the current layout; a run folder of that layout is never resumed into."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from logpipe.errors import LogpipeError
from logpipe.prediction.runs import PredictionRun, dense_forecasts, is_long
from logpipe.prediction.table import SampleForecast, build_table
from logpipe.stages.ingest import IngestOptions, ingest
from logpipe.stages.predict import predict_dataset
from logpipe.stages.score import score

K, T = 6, 30
REPORT_BLOCKS = ("overall", "by_type", "by_log", "counts", "ks", "checkpoint_ids")


@pytest.fixture(scope="module")
def legacy(bundled: Path) -> Path:
    return bundled / "predictions_v1" / "av1_cv_sampler"


@pytest.fixture(scope="module")
def av1(bundled: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("legacy") / "av1"
    ingest([bundled / "argoverse1"], IngestOptions(out=out, write_mcap=False))
    return out


def _pivot(path: Path) -> dict[tuple[str, str], np.ndarray]:
    """The long rows as {(sample, track): (K, T, 2)}, by plain Python (independent of the reader)."""
    rows = pq.read_table(path).to_pydict()
    out: dict[tuple[str, str], np.ndarray] = {}
    for i in range(len(rows["x"])):
        grid = out.setdefault((rows["sample_id"][i], rows["track_id"][i]), np.full((K, T, 2), np.nan))
        grid[rows["mode"][i], rows["step"][i] - 1] = (rows["x"][i], rows["y"][i])
    return out


def test_long_rows_become_the_same_forecasts(legacy: Path) -> None:
    part = legacy / "predictions" / "part-00000.parquet"
    assert is_long(pq.read_table(part))
    run = PredictionRun.open(legacy)
    table = run.table()
    assert not is_long(table) and table.num_rows == 6 * K
    assert table.schema.field("x").type == pa.list_(pa.float64(), T)
    dense = run.dense()
    want = _pivot(part)
    assert sorted(want) == list(zip(dense.sample_ids.tolist(), dense.track_ids.tolist(), strict=True))
    assert np.array_equal(np.stack([want[key] for key in sorted(want)]), dense.pred)  # bit for bit
    assert dense.checkpoint_ids == [run.meta.checkpoint_id]
    assert len({float(v) for v in dense.pred[0, :, -1, 0]}) == K  # the modes differ, so their order is tested
    # A bare file of the old layout reads the same, through its Parquet metadata.
    alone = dense_forecasts(pq.read_table(part), K, T, str(part))
    assert np.array_equal(alone.pred, dense.pred) and alone.checkpoint_ids == dense.checkpoint_ids


def test_score_equals_the_old_logpipe_and_the_current_layout(legacy: Path, av1: Path, tmp_path: Path) -> None:
    expected = json.loads((legacy.parent / "av1_cv_sampler.report_v1.json").read_text())
    old = score([legacy], av1, tmp_path / "old", plots=False)["methods"]["cv_sampler"]
    assert {k: old[k] for k in REPORT_BLOCKS} == expected  # the same floats as the writer's logpipe reported
    # The same forecasts written in the current layout score the same.
    run = PredictionRun.open(legacy)
    dense = run.dense()
    table = run.table()
    log_of = dict(zip(table.column("sample_id").to_pylist(), table.column("log_id").to_pylist(), strict=True))
    ts = table.column("timestamp_ns").combine_chunks().flatten().to_numpy().reshape(-1, K, T)[:, 0]
    forecasts = [SampleForecast(log_id=log_of[s], sample_id=s, track_ids=[t], object_types=[o], futures=p[None],
                                scores=None, step_ns=step)
                 for s, t, o, p, step in zip(dense.sample_ids.tolist(), dense.track_ids.tolist(),
                                             dense.object_types.tolist(), dense.pred, ts, strict=True)]
    pq.write_table(build_table(run.meta, forecasts), tmp_path / "wide.parquet")
    new = score([tmp_path / "wide.parquet"], av1, tmp_path / "new", plots=False)["methods"]["cv_sampler"]
    assert {k: new[k] for k in REPORT_BLOCKS} == expected


def test_a_run_folder_of_the_old_layout_is_not_resumed(legacy: Path, av1: Path, tmp_path: Path) -> None:
    copy = tmp_path / "run"
    shutil.copytree(legacy, copy)
    before = {p.name: p.read_bytes() for p in copy.rglob("*") if p.is_file()}
    with pytest.raises(LogpipeError, match="run format 1"):
        predict_dataset(av1, copy, predictor="cv_sampler", write_mcap=False, threads=1)
    assert {p.name: p.read_bytes() for p in copy.rglob("*") if p.is_file()} == before
    assert PredictionRun.open(copy).dense().pred.shape == (6, K, T, 2)
