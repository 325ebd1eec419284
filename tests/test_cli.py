"""The Typer CLI: help on every command, --version, --json summaries and one-line errors with exit code 2."""

from __future__ import annotations

import dataclasses
import json
import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import typer
from typer.testing import CliRunner

from logpipe import __version__
from logpipe.cli import app

runner = CliRunner()


def test_version() -> None:
    result = runner.invoke(app, ["--version"])
    assert result.exit_code == 0 and __version__ in result.stdout


@pytest.mark.parametrize("command", ["ingest", "index", "inspect", "export"])
def test_every_command_has_help(command: str) -> None:
    result = runner.invoke(app, [command, "--help"])
    assert result.exit_code == 0
    assert "Example:" in result.stdout


def _piped(*args: str, columns: str) -> subprocess.CompletedProcess[str]:
    """``logpipe ARGS`` with stdout and stderr pipes (as in CI) and a terminal width of ``columns``."""
    return subprocess.run([sys.executable, "-m", "logpipe.cli", *args], capture_output=True, text=True, check=False,
                          env={**os.environ, "COLUMNS": columns}, timeout=600)


@pytest.mark.parametrize("columns", ["40", "80"])
def test_piped_help_never_cuts_an_option_name(columns: str) -> None:
    result = _piped("predict", "--help", columns=columns)
    assert result.returncode == 0, result.stderr
    command = typer.main.get_command(app).commands["predict"]  # type: ignore[attr-defined]
    names = [name for param in command.params for name in (*param.opts, *param.secondary_opts)
             if name.startswith("-")]
    assert {"--constant-velocity-modes", "--context-max-neighbours", "--no-raster-images"} <= set(names)
    for name in names:
        assert re.search(rf"(?<![\w-]){re.escape(name)}(?![\w-])", result.stdout), f"{name} cut or missing"
    assert "…" not in result.stdout


def test_human_summaries_name_outputs_and_the_next_command_unwrapped(bundled: Path, tmp_path: Path) -> None:
    ds, run = tmp_path / "a", tmp_path / "p"
    ingest = _piped("ingest", str(bundled / "apolloscape"), "--out", str(ds), "--no-mcap", columns="40")
    assert ingest.returncode == 0, ingest.stderr
    # one line however narrow the terminal (it names a long tmp path)
    assert len([line for line in ingest.stderr.splitlines() if "inputs ingested" in line]) == 1
    assert f"  dataset: {ds} (now 2 logs" in ingest.stderr
    assert f"next: logpipe predict {ds} --out {ds}-pred" in ingest.stderr.splitlines()
    result = _piped("predict", str(ds), "--predictor", "cv", "--out", str(run), "--no-mcap", columns="40")
    assert result.returncode == 0, result.stderr
    assert result.stdout == ""
    lines = result.stderr.splitlines()
    assert not any(line.lstrip().startswith(("{", '"')) for line in lines)  # a few lines, not a JSON dump
    summary = [line for line in lines if not line.startswith("predict: ") or " by cv in " in line]
    assert re.fullmatch(r"predict: \d+ samples, \d+ agents x 20 modes by cv in [\d.]+ s", summary[0])
    assert f"  predictions: {run}/predictions/*.parquet" in result.stderr
    assert summary[-1] == f"next: logpipe score {run} --truth {ds} --out {run}-score"
    assert max(len(line) for line in lines) > 40  # long lines were not wrapped
    score = _piped("score", str(run), "--truth", str(ds), "--out", str(tmp_path / "s"), "--no-plots", columns="40")
    assert score.returncode == 0, score.stderr
    assert score.stderr.splitlines()[-1].startswith(f"next: open {tmp_path / 's' / 'report.md'}")


def test_json_errors_are_one_json_object_and_missing_maps_exit_2(bundled: Path, tmp_path: Path) -> None:
    missing = _piped("predict", str(tmp_path / "nothing"), "--out", str(tmp_path / "p"), "--json", columns="80")
    assert missing.returncode == 2
    error = json.loads(missing.stdout)
    assert error["exit_code"] == 2 and str(tmp_path / "nothing") in error["error"]
    assert missing.stderr.startswith("error: ")
    ds = tmp_path / "av1"
    assert runner.invoke(app, ["ingest", str(bundled / "driving" / "20.csv"), "--out", str(ds), "--no-mcap"]
                         ).exit_code == 0
    nomaps = runner.invoke(app, ["rasterise", str(ds), "--maps", str(tmp_path / "no" / "such")])
    assert nomaps.exit_code == 2 and "no such folder" in nomaps.output
    (tmp_path / "empty").mkdir()
    empty = runner.invoke(app, ["rasterise", str(ds), "--maps", str(tmp_path / "empty"), "--json"])
    assert empty.exit_code == 2
    assert "no map found for any of its 1 logs (20; map ids looked for: MIA)" in json.loads(empty.stdout)["error"]
    assert not (ds / "rasters").exists()


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


def test_protocol_overrides_change_the_formats_own_preset(bundled: Path, tmp_path: Path) -> None:
    """`--targets` alone keeps Argoverse's 20 + 30 steps (it used to fall back to a generic 8 + 12 preset)."""
    result = runner.invoke(app, ["ingest", str(bundled / "argoverse1"), "--out", str(tmp_path / "a"), "--no-mcap",
                                 "--targets", "fully_observed_no_ego", "--json"])
    assert result.exit_code == 0, result.output
    protocol = json.loads(result.stdout)["protocol"]
    assert (protocol["name"], protocol["obs_len"], protocol["pred_len"], protocol["window"]) == \
        ("argoverse-custom", 20, 30, "first")
    assert protocol["targets"] == "fully_observed_no_ego"


def test_inspect_json_names_the_track_topics(bundled: Path) -> None:
    result = runner.invoke(app, ["inspect", str(bundled / "rosbags" / "datmo" / "intersection.bag"), "--json"])
    assert result.exit_code == 0, result.output
    report = json.loads(result.stdout)[0]
    roles = {t["topic"]: t.get("role") for t in report["topics"]}
    assert roles["/ego_pose"] == "ego" and roles["/red_pose"] == "agent"


def test_ingest_bag_with_mapping_overrides_and_rate(bundled: Path, tmp_path: Path) -> None:
    bag = str(bundled / "rosbags" / "datmo" / "intersection.bag")
    result = runner.invoke(app, ["ingest", bag, "--out", str(tmp_path / "b"), "--set", "ego=/red_pose",
                                 "--set", "agent=/ego_pose:blue", "--hz", "5", "--json"])
    assert result.exit_code == 0, result.output
    summary = json.loads(result.stdout)
    assert summary["format"] == "rosbag" and summary["logs"] == 1
    from logpipe.dataset.reader import Dataset

    tracks = Dataset.open(tmp_path / "b").tracks()
    assert sorted(set(tracks.column("track_id").to_pylist())) == ["blue", "ego"]
    ts = sorted(set(tracks.column("timestamp_ns").to_pylist()))
    assert set(np.diff(ts)) == {200_000_000}


def test_option_a_format_does_not_take_is_refused(bundled: Path, tmp_path: Path) -> None:
    result = runner.invoke(app, ["ingest", str(bundled / "argoverse1"), "--out", str(tmp_path / "a"), "--hz", "5"])
    assert result.exit_code == 2
    assert "format 'argoverse1' takes no option(s) hz" in result.output


def test_train_a_few_steps_writes_a_loadable_checkpoint(bundled: Path, tmp_path: Path) -> None:
    runner.invoke(app, ["ingest", str(bundled / "ethucy"), "--out", str(tmp_path / "e"), "--no-mcap"])
    config = tmp_path / "c.toml"
    config.write_text("[train]\nsteps = 4\neval_every = 2\nval_max_samples = 16\nnum_threads = 1\n")
    result = runner.invoke(app, ["train", str(tmp_path / "e"), "--train-split", "eth/train", "--val-split",
                                 "hotel/test", "--config", str(config), "--out", str(tmp_path / "run"), "--json"])
    assert result.exit_code == 0, result.output
    summary = json.loads(result.stdout)
    assert summary["steps"] == 4 and summary["train_samples"] > 0
    assert np.isfinite(summary["best_val_ade"])
    from logpipe.model.zhu2020.checkpoint import load_checkpoint

    loaded = load_checkpoint(Path(summary["best_checkpoint"]), expect_kind="ethucy")
    assert loaded.net.config.obs_len == 8
    again = runner.invoke(app, ["train", str(tmp_path / "e"), "--train-split", "eth/train", "--val-split", "none",
                                "--config", str(config), "--out", str(tmp_path / "run")])
    assert again.exit_code == 2  # an existing run is not overwritten without --resume
    assert "resumed_at_step" not in summary
    resumed = runner.invoke(app, ["train", str(tmp_path / "e"), "--train-split", "eth/train", "--val-split",
                                  "hotel/test", "--config", str(config), "--out", str(tmp_path / "run"), "--steps", "6",
                                  "--resume", "--json"])
    assert resumed.exit_code == 0, resumed.output
    more = json.loads(resumed.stdout)
    assert more["steps"] == 6 and more["resumed_at_step"] == 4
    # both parts' training time (the model tests check it against each part), within both calls' wall time
    assert 0 < more["seconds_total"] <= summary["seconds"] + more["seconds"] + 0.1


@pytest.mark.parametrize(("preset", "noise", "modes", "held"), [("lstm", 0, 1, 0), ("baseline", 16, 20, 1)])
def test_train_preset_trains_a_baseline_with_the_same_schedule(bundled: Path, tmp_path: Path, preset: str, noise: int,
                                                                modes: int, held: int) -> None:
    runner.invoke(app, ["ingest", str(bundled / "ethucy"), "--out", str(tmp_path / "e"), "--no-mcap"])
    config = tmp_path / "c.toml"
    config.write_text("[train]\nsteps = 2\neval_every = 2\nval_max_samples = 8\nnum_threads = 1\n"
                      "augment_rotate = true\n[model]\nstep_output = \"agent_velocity_change\"\n"
                      "constant_velocity_modes = 1\n")
    result = runner.invoke(app, ["train", str(tmp_path / "e"), "--train-split", "eth/train", "--val-split",
                                 "hotel/test", "--config", str(config), "--preset", preset, "--out",
                                 str(tmp_path / "run"), "--json"])
    assert result.exit_code == 0, result.output
    from logpipe.model.zhu2020.meta import read_meta

    meta = read_meta(Path(json.loads(result.stdout)["best_checkpoint"]))
    assert not any(dataclasses.asdict(meta.config.model.features).values())  # no AIN, no environment net
    assert meta.config.model.noise_dim == noise and meta.config.num_modes == modes
    assert meta.config.model.constant_velocity_modes == held  # one draw: none held at constant velocity
    assert meta.config.augment_rotate and meta.config.steps == 2  # everything else as configured


def test_train_uses_the_raster_run_for_the_environment_net(bundled: Path, tmp_path: Path) -> None:
    maps = bundled / "maps"
    runner.invoke(app, ["ingest", str(maps / "2645.csv"), str(maps / "3861.csv"), "--out", str(tmp_path / "a")])
    raster = runner.invoke(app, ["rasterise", str(tmp_path / "a"), "--map",
                                 f"MIA={maps / 'MIA_lane_centerlines_crop_2645.npz'}", "--map",
                                 f"PIT={maps / 'PIT_lane_centerlines_crop_3861.npz'}", "--rotate"])
    assert raster.exit_code == 0, raster.output
    config = tmp_path / "c.toml"
    config.write_text("[train]\nsteps = 2\nbatch_size = 2\nnum_modes = 2\nval_modes = 2\neval_every = 2\n"
                      "num_threads = 1\n[model]\nobs_len = 20\npred_len = 30\n")
    result = runner.invoke(app, ["train", str(tmp_path / "a"), "--train-split", "all", "--val-split", "all",
                                 "--config", str(config), "--out", str(tmp_path / "run"), "--json"])
    assert result.exit_code == 0, result.output
    summary = json.loads(result.stdout)
    assert summary["environment_net"] is True and summary["raster_run"]
    from logpipe.model.zhu2020.checkpoint import load_checkpoint

    net = load_checkpoint(Path(summary["best_checkpoint"]), expect_kind="argoverse1").net
    assert net.config.features.environment and net.config.raster_channels == 7


def test_train_streams_from_the_shards_with_loader_workers(bundled: Path, tmp_path: Path) -> None:
    runner.invoke(app, ["ingest", str(bundled / "ethucy"), "--out", str(tmp_path / "e"), "--no-mcap"])
    config = tmp_path / "c.toml"
    config.write_text("[train]\nsteps = 3\neval_every = 3\nval_max_samples = 8\nnum_threads = 1\n")
    result = runner.invoke(app, ["train", str(tmp_path / "e"), "--train-split", "eth/train", "--val-split",
                                 "hotel/test", "--config", str(config), "--out", str(tmp_path / "run"),
                                 "--loader-workers", "2", "--json"])
    assert result.exit_code == 0, result.output
    summary = json.loads(result.stdout)
    assert summary["train_samples"] == "streamed" and summary["steps"] == 3
    assert np.isfinite(summary["best_val_ade"])


def test_train_holds_out_a_scene_with_a_split_expression(bundled: Path, tmp_path: Path) -> None:
    """``--train-split`` takes + and - terms; then ``--val-split`` must be given (no /val to guess)."""
    runner.invoke(app, ["ingest", str(bundled / "ethucy"), "--out", str(tmp_path / "e"), "--no-mcap"])
    config = tmp_path / "c.toml"
    config.write_text("[train]\nsteps = 2\neval_every = 2\nval_max_samples = 8\nnum_threads = 1\n")
    base = ["train", str(tmp_path / "e"), "--config", str(config), "--preset", "lstm", "--json"]
    result = runner.invoke(app, [*base, "--train-split", "all-eth/test-hotel/test", "--out", str(tmp_path / "a")])
    assert result.exit_code == 2 and "--val-split" in result.output
    result = runner.invoke(app, [*base, "--train-split", "all-eth/test-hotel/test", "--val-split", "biwi_hotel",
                                 "--out", str(tmp_path / "b")])
    assert result.exit_code == 0, result.output
    summary = json.loads(result.stdout)
    assert summary["train_split"] == "all-eth/test-hotel/test" and summary["val_split"] == "biwi_hotel"
    assert summary["train_samples"] > 0 and summary["val_samples"] > 0


def test_train_init_from_warm_starts_the_full_model_from_a_noise_lstm(bundled: Path, tmp_path: Path) -> None:
    runner.invoke(app, ["ingest", str(bundled / "ethucy"), "--out", str(tmp_path / "e"), "--no-mcap"])
    config = tmp_path / "c.toml"
    config.write_text("[train]\nsteps = 2\neval_every = 2\nval_max_samples = 8\nnum_threads = 1\n")
    args = ["train", str(tmp_path / "e"), "--train-split", "eth/train", "--val-split", "hotel/test", "--config",
            str(config), "--json"]
    base = runner.invoke(app, [*args, "--preset", "baseline", "--out", str(tmp_path / "nl")])
    assert base.exit_code == 0, base.output
    source = json.loads(base.stdout)["best_checkpoint"]
    warm = runner.invoke(app, [*args, "--init-from", source, "--out", str(tmp_path / "ours")])
    assert warm.exit_code == 0, warm.output
    assert json.loads(warm.stdout)["init_from"] == source
    start = json.loads((tmp_path / "ours" / "train_log.jsonl").read_text().splitlines()[0])
    assert start["init_from"]["widened"] and start["init_from"]["source"] == source
    missing = runner.invoke(app, [*args, "--init-from", str(tmp_path / "nowhere"), "--out", str(tmp_path / "x")])
    assert missing.exit_code != 0 and "nowhere" in missing.output
    assert not (tmp_path / "x").exists()  # nothing made for a run that cannot start


def test_retry_quarantined_reads_a_fixed_input_again(bundled: Path, tmp_path: Path) -> None:
    bag, ds = bundled / "rosbags" / "datmo" / "intersection.bag", tmp_path / "ds"
    wrong = runner.invoke(app, ["ingest", str(bag), "--out", str(ds), "--on-error", "skip", "--set", "ego=/nope",
                                "--json"])
    assert wrong.exit_code == 2, wrong.output  # committed, but nothing was ingested: a job must not pass
    assert "/nope" in json.loads(wrong.stdout)["quarantined"][0]["error"]["reason"]
    again = runner.invoke(app, ["ingest", str(bag), "--out", str(ds)])  # a plain rerun skips it, and says why
    assert again.exit_code == 2 and "1 inputs quarantined by an earlier run are skipped" in again.output
    assert "error: the dataset" in again.output and "holds no log" in again.output
    fixed = runner.invoke(app, ["ingest", str(bag), "--out", str(ds), "--retry-quarantined", "--json"])
    assert fixed.exit_code == 0, fixed.output
    summary = json.loads(fixed.stdout)
    assert summary["inputs_retried"] == 1 and summary["inputs_ingested"] == 1 and summary["logs"] == 1
    assert summary["totals"]["quarantined"] == 0 and summary["totals"]["rows"] == summary["rows"] > 0
    manifest = json.loads((ds / "manifest.json").read_text())
    assert manifest["quarantined"] == [] and [i["path"] for i in manifest["inputs"]] == ["intersection.bag"]


def test_piped_inspect_never_cuts_a_topic_or_type_name(bundled: Path) -> None:
    bag = bundled / "rosbags" / "datmo" / "intersection.bag"
    result = _piped("inspect", str(bag), columns="40")
    assert result.returncode == 0, result.stderr
    for name in ("geometry_msgs/msg/PoseStamped", "tf2_msgs/msg/TFMessage", "/wheel_speeds", "barc/msg/Encoder"):
        assert name in result.stdout, name
    assert "…" not in result.stdout
    assert f"next: logpipe ingest {bag} --out out/NAME" in result.stderr
