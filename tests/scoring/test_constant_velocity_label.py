"""A K=1 that is constant velocity is labelled: the shipped ETH/UCY checkpoint keeps constant velocity as its first
mode (``constant_velocity_modes: 1`` in its ``meta.json``), so its K=1 row equals the CV baseline's; ``score``'s
printed summary and ``report.md`` say so. Run on the bundled ETH/UCY sample's eth/test log."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from typer.testing import CliRunner

from logpipe.cli import app

runner = CliRunner()


def _run(*args: str) -> str:
    result = runner.invoke(app, list(args))
    assert result.exit_code == 0, result.output
    return result.stderr


@pytest.fixture(scope="module")
def scored(bundled: Path, tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, str]:
    """(score folder, its printed summary) of the shipped eth checkpoint and the CV baseline side by side."""
    root = tmp_path_factory.mktemp("cvlabel")
    _run("ingest", str(bundled / "ethucy"), "--out", str(root / "ds"), "--no-mcap")
    split = ["--filter", "split=eth/test", "--no-mcap"]
    _run("predict", str(root / "ds"), *split, "--out", str(root / "net"))
    _run("predict", str(root / "ds"), *split, "--predictor", "cv", "--out", str(root / "cv"))
    printed = _run("score", str(root / "net"), str(root / "cv"), "--truth", str(root / "ds"), "--split", "eth/test",
                   "--out", str(root / "score"))
    return root / "score", printed


def test_the_checkpoints_k1_is_constant_velocity(scored: tuple[Path, str]) -> None:
    report = json.loads((scored[0] / "report.json").read_text())
    net, cv = report["methods"]["zhu2020"], report["methods"]["cv"]
    assert net["metadata"]["constant_velocity_modes"] == 1
    for key in ("ade", "fde"):
        assert net["overall"]["k1"][key] == pytest.approx(cv["overall"]["k1"][key], rel=1e-6)  # float32 net
    assert net["overall"]["k20"]["ade"] < net["overall"]["k1"]["ade"]  # the other modes are the network's


def test_score_summary_and_report_say_mode_0_is_constant_velocity(scored: tuple[Path, str]) -> None:
    folder, printed = scored
    net_line = next(line for line in printed.splitlines() if line.startswith("score: zhu2020:"))
    assert "K=1 (constant velocity) " in net_line and "K=20 (constant" not in net_line
    assert "  zhu2020: mode 0 is the constant-velocity forecast (constant_velocity_modes: 1)" in printed
    cv_line = next(line for line in printed.splitlines() if line.startswith("score: cv:"))
    assert "constant velocity" not in cv_line  # the baseline is what it says
    md = (folder / "report.md").read_text()
    assert "| zhu2020 | 1 (constant velocity) |" in md and "| zhu2020 | 20 |" in md
    assert "Note: zhu2020: mode 0 is the constant-velocity forecast" in md
