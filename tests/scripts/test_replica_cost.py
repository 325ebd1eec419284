"""``scripts/replica_cost.py``: a small replica runs every stage and the cost file adds up."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from scripts.replica_cost import FULL_SETS, main, make_replica

pytestmark = pytest.mark.slow  # minutes of end-to-end work


def test_replicas_differ_in_content_but_keep_the_real_rows(tmp_path: Path) -> None:
    source = Path(__file__).resolve().parents[1] / "data" / "argoverse1"
    assert make_replica(source, tmp_path, 8) == 8
    files = sorted(tmp_path.glob("*.csv"))
    blobs = [f.read_bytes() for f in files]
    assert len(set(blobs)) == 8  # distinct AV ids: content hashing keeps them apart
    originals = sorted(source.glob("*.csv"))
    assert blobs[0].count(b"\n") == originals[0].read_bytes().count(b"\n")


@pytest.mark.shared
def test_every_stage_is_timed_and_projected(shared: Path, tmp_path: Path) -> None:
    code = main(["--source", str(shared / "argoverse1" / "data"), "--maps", str(shared / "argoverse1" / "maps"),
                 "--sequences", "24", "--train-steps", "2", "--work", str(tmp_path / "work"),
                 "--results", str(tmp_path / "res")])
    assert code == 0
    m = json.loads((tmp_path / "res" / "argoverse_cost.json").read_text())
    assert m["samples"] == m["predict_samples"] == 24
    for key in ("ingest_w1_s", "rasterise_w1_s", "predict_full_t1_s", "predict_cv_t1_s", "train_s"):
        assert m[key] > 0
    assert 1e8 < m["flops"]["predict"] < m["flops"]["train"]
    text = (tmp_path / "res" / "argoverse_cost.md").read_text()
    assert all(name in text for name in FULL_SETS)
    core_hours = 205_942 + 39_472 + 78_143
    expected = m["predict_full_t1_s"] / 24 * core_hours / 3600
    assert f"| predict, full model, K = 6 | {expected:,.1f} |" in text
