"""The Typer CLI: help on every command, --version, --json summaries and one-line errors with exit code 2."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from typer.testing import CliRunner

from logpipe import __version__
from logpipe.cli import app

runner = CliRunner()


def test_version() -> None:
    result = runner.invoke(app, ["--version"])
    assert result.exit_code == 0 and __version__ in result.stdout


@pytest.mark.parametrize("command", ["ingest", "index"])
def test_every_command_has_help(command: str) -> None:
    result = runner.invoke(app, [command, "--help"])
    assert result.exit_code == 0
    assert "Example:" in result.stdout


def test_ingest_json_summary_and_rerun(bundled: Path, tmp_path: Path) -> None:
    args = ["ingest", str(bundled / "apolloscape"), "--out", str(tmp_path / "ds"), "--json"]
    first = runner.invoke(app, args)
    assert first.exit_code == 0, first.output
    summary = json.loads(first.stdout)
    assert summary["logs"] == 2 and summary["rows"] == 1046 and summary["format"] == "apolloscape"
    second = json.loads(runner.invoke(app, args).stdout)
    assert second["inputs_skipped_already_ingested"] == 2 and second["totals"]["rows"] == 1046


def test_bad_input_is_one_line_with_location_and_exit_2(tmp_path: Path) -> None:
    (tmp_path / "in").mkdir()
    (tmp_path / "in" / "1.csv").write_text("TIMESTAMP,TRACK_ID,OBJECT_TYPE,X,Y,CITY_NAME\n1.0,a,AV,oops,2.0,MIA\n")
    result = runner.invoke(app, ["ingest", str(tmp_path / "in"), "--out", str(tmp_path / "o"), "-f", "argoverse1"])
    assert result.exit_code == 2
    assert "1.csv:2: field 'X': not a number: 'oops'" in result.output
    assert "Traceback" not in result.output
    assert not (tmp_path / "o").exists()


def test_index_changes_protocol(bundled: Path, tmp_path: Path) -> None:
    runner.invoke(app, ["ingest", str(bundled / "ethucy"), "--out", str(tmp_path / "e")])
    loose = json.loads(runner.invoke(app, ["index", str(tmp_path / "e"), "--min-targets", "1", "--json"]).stdout)
    strict = json.loads(runner.invoke(app, ["index", str(tmp_path / "e"), "--min-targets", "2", "--json"]).stdout)
    assert strict["protocol"]["obs_len"] == 8 and strict["protocol"]["pred_len"] == 12
    assert 0 < strict["samples"] < loose["samples"]
