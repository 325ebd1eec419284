"""The format is detected per file: a folder holding a ROS bag and an MCAP ingests both (two logs), a broken MCAP
beside a good bag neither hides the bag nor passes in silence, and a file of a format the dataset cannot hold is
named with the reason. Built from real files of ``../shared/data`` (``rosbags/datmo/intersection.bag``,
``mcap/evo/nav2_turtlebot.mcap``, the damaged ``mcap/keelson/2024-05-15.mcap``) and the bundled AV1 ``20.csv``."""

from __future__ import annotations

import json
import shutil
from pathlib import Path
from typing import Any

import pytest
from typer.testing import CliRunner

from logpipe.cli import app
from logpipe.dataset.reader import Dataset

runner = CliRunner()


def _folder(tmp_path: Path, *files: Path) -> Path:
    folder = tmp_path / "in"
    folder.mkdir()
    for f in files:
        shutil.copy(f, folder / f.name)
    return folder


def _ingest(folder: Path, out: Path, *extra: str) -> tuple[int, dict[str, Any], str]:
    result = runner.invoke(app, ["ingest", str(folder), "--out", str(out), "--no-mcap", *extra, "--json"])
    return result.exit_code, json.loads(result.stdout), result.stderr


def test_a_folder_with_a_bag_and_an_mcap_ingests_both(shared: Path, tmp_path: Path) -> None:
    folder = _folder(tmp_path, shared / "rosbags" / "datmo" / "intersection.bag",
                     shared / "mcap" / "evo" / "nav2_turtlebot.mcap")
    code, summary, _ = _ingest(folder, tmp_path / "ds")
    assert code == 0, summary
    assert summary["inputs_ingested"] == summary["logs"] == 2 and summary["skipped_inputs"] == []
    logs = Dataset.open(tmp_path / "ds").logs().to_pylist()
    assert {(r["log_id"], r["source_format"]) for r in logs} == {("intersection", "rosbag"),
                                                                 ("nav2_turtlebot", "mcap")}
    assert all(r["attributes"] and r["source_file"] for r in logs)


def test_a_broken_mcap_beside_a_good_bag_is_named_and_the_bag_still_lands(shared: Path, tmp_path: Path) -> None:
    folder = _folder(tmp_path, shared / "rosbags" / "datmo" / "intersection.bag",
                     shared / "mcap" / "keelson" / "2024-05-15.mcap")
    code, failed, _ = _ingest(folder, tmp_path / "strict")  # --on-error fail: the bad input is the error
    assert code == 2 and failed["error"].startswith("2024-05-15.mcap: not a readable MCAP file")
    code, summary, _ = _ingest(folder, tmp_path / "lenient", "--on-error", "skip")
    assert code == 0
    assert summary["logs"] == 1 and [q["path"] for q in summary["quarantined"]] == ["2024-05-15.mcap"]
    assert [r["log_id"] for r in Dataset.open(tmp_path / "lenient").logs().to_pylist()] == ["intersection"]


def test_a_file_of_another_format_is_named_with_why(bundled: Path, tmp_path: Path) -> None:
    folder = _folder(tmp_path, bundled / "rosbags" / "datmo" / "intersection.bag", bundled / "driving" / "20.csv")
    code, summary, stderr = _ingest(folder, tmp_path / "ds")
    assert code == 0 and summary["logs"] == 1
    [skipped] = summary["skipped_inputs"]
    kept = summary["format"]
    other = "rosbag" if kept == "argoverse1" else "argoverse1"
    assert skipped["format"] == other and skipped["path"] in ("intersection.bag", "20.csv")
    assert f"this dataset is {kept}" in skipped["why"]
    assert f"{skipped['path']}: skipped: a {other} input" in stderr  # a warning, counted in the summary
    assert any("skipped" in w for w in summary["warnings"])


@pytest.mark.parametrize("order", [("intersection.bag", "nav2_turtlebot.mcap"),
                                   ("nav2_turtlebot.mcap", "intersection.bag")])
def test_a_bag_and_an_mcap_given_as_files_are_one_dataset(shared: Path, tmp_path: Path,
                                                           order: tuple[str, str]) -> None:
    paths = {"intersection.bag": shared / "rosbags" / "datmo" / "intersection.bag",
             "nav2_turtlebot.mcap": shared / "mcap" / "evo" / "nav2_turtlebot.mcap"}
    result = runner.invoke(app, ["ingest", *(str(paths[n]) for n in order), "--out", str(tmp_path / "ds"),
                                 "--no-mcap", "--json"])
    assert result.exit_code == 0, result.output
    assert json.loads(result.stdout)["logs"] == 2
