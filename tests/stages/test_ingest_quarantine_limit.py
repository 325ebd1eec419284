"""``ingest --on-error skip`` must not let a job pass with an empty dataset: quarantining every new input exits 2
(after the commit, with the summary naming each quarantined file), and ``--max-quarantined N`` exits 2 when more
than N are quarantined. The bad inputs are real Argoverse 1 files of ``tests/data/argoverse1`` cut mid-line."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest
from typer.testing import CliRunner

from logpipe import api
from logpipe.cli import app
from logpipe.dataset.reader import Dataset
from logpipe.errors import QuarantineLimitError

runner = CliRunner()


def _cut(src: Path, dst: Path) -> None:
    """``src`` cut in the middle of its third line (a short row: a bad input)."""
    lines = src.read_text().splitlines(keepends=True)
    dst.write_text("".join(lines[:2]) + lines[2][: len(lines[2]) // 2] + "\n")


@pytest.fixture
def inputs(bundled: Path, tmp_path: Path) -> Path:
    """A folder of two cut AV1 files (``bad/``) and one with two good and one cut file (``mixed/``)."""
    av1 = sorted((bundled / "argoverse1").glob("*.csv"))
    (tmp_path / "bad").mkdir()
    (tmp_path / "mixed").mkdir()
    for src in av1[:2]:
        _cut(src, tmp_path / "bad" / src.name)
    for src in av1[2:4]:
        shutil.copy(src, tmp_path / "mixed" / src.name)
    _cut(av1[4], tmp_path / "mixed" / av1[4].name)
    return tmp_path


def test_skip_that_quarantines_every_input_exits_2(inputs: Path) -> None:
    out = inputs / "out"
    result = runner.invoke(app, ["ingest", str(inputs / "bad"), "--out", str(out), "--on-error", "skip", "--json"])
    assert result.exit_code == 2, result.output
    summary = json.loads(result.stdout)  # one JSON object: the summary, with the error in it
    assert summary["exit_code"] == 2 and summary["error"].startswith("nothing ingested: all 2 new inputs")
    assert summary["inputs_ingested"] == 0 and len(summary["quarantined"]) == 2
    assert "error: nothing ingested" in result.stderr
    assert Dataset.open(out).manifest["totals"]["quarantined"] == 2  # committed: a rerun skips them


def test_human_output_lists_the_quarantined_files_before_the_error(inputs: Path) -> None:
    result = runner.invoke(app, ["ingest", str(inputs / "bad"), "--out", str(inputs / "out"), "--on-error", "skip"])
    assert result.exit_code == 2
    lines = result.stderr.splitlines()
    quarantined = [i for i, line in enumerate(lines) if line.lstrip().startswith("quarantined ")]
    error = next(i for i, line in enumerate(lines) if line.startswith("error: nothing ingested"))
    assert len(quarantined) == 2 and max(quarantined) < error


def test_max_quarantined_is_a_threshold_and_what_was_read_stays(inputs: Path) -> None:
    args = ["ingest", str(inputs / "mixed"), "--on-error", "skip", "--json"]
    over = runner.invoke(app, [*args, "--out", str(inputs / "strict"), "--max-quarantined", "0"])
    assert over.exit_code == 2
    summary = json.loads(over.stdout)
    assert summary["error"] == ("1 inputs quarantined, more than --max-quarantined 0 (2 ingested and committed)")
    assert Dataset.open(inputs / "strict").manifest["totals"]["logs"] == 2
    within = runner.invoke(app, [*args, "--out", str(inputs / "lenient"), "--max-quarantined", "1"])
    assert within.exit_code == 0, within.output
    assert "error" not in json.loads(within.stdout)


def test_the_api_raises_with_the_summary(inputs: Path) -> None:
    with pytest.raises(QuarantineLimitError) as info:
        api.ingest(inputs / "bad", out=inputs / "out", on_error="skip", mcap=False)
    summary = info.value.summary
    assert summary["inputs_ingested"] == 0 and len(summary["quarantined"]) == summary["totals"]["quarantined"] == 2
    with pytest.raises(QuarantineLimitError, match="holds no log: its 2 inputs are quarantined"):
        api.ingest(inputs / "bad", out=inputs / "out", on_error="skip", mcap=False)  # a rerun: still empty
