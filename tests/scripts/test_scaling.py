"""``scripts/scaling.py``: how a stage is timed and its memory measured, and that ``docs/scaling.md`` is what its
measurements render to."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

from scripts.locations import REPO
from scripts.scaling import _descendants_rss, render, run_stage

DATA = Path(__file__).resolve().parents[1] / "data"


def test_memory_of_the_process_tree_counts_children() -> None:
    alone = _descendants_rss(os.getpid())
    child = subprocess.Popen([sys.executable, "-c", "b = bytearray(300 * 2**20); import time; time.sleep(30)"])
    try:
        deadline = time.monotonic() + 20
        grown = 0
        while time.monotonic() < deadline and grown < 250 * 2**20:
            time.sleep(0.2)
            grown = _descendants_rss(os.getpid()) - alone
        assert grown >= 250 * 2**20  # the child's 300 MB buffer, touched by bytearray's zero fill
    finally:
        child.kill()
        child.wait()


def test_a_stage_runs_as_its_own_process_with_its_summary(tmp_path: Path) -> None:
    csvs = sorted((DATA / "argoverse1").glob("*.csv"))
    m = run_stage(["ingest", str(DATA / "argoverse1"), "--out", str(tmp_path / "ds"), "--protocol", "argoverse",
                   "--no-mcap", "-j", "1"])
    assert m["summary"]["logs"] == len(csvs)
    assert m["seconds"] > 0 and m["peak_mb"] > 20  # a Python process with pyarrow loaded


def test_the_shipped_report_is_its_measurements_rendered() -> None:
    measured = json.loads((REPO / "docs" / "scaling.json").read_text())
    assert (REPO / "docs" / "scaling.md").read_text() == render(measured)
    assert measured["logs"] == 50_000 and len(measured["runs"]) == 4
