"""The Python API (``logpipe.ingest`` ...): the same outputs as the CLI, paths as str or Path, LogpipeError
instead of an exit; and summaries whose counts explain themselves (copies of inputs, logs without samples)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pyarrow.parquet as pq
import pytest
from typer.testing import CliRunner

import logpipe
from logpipe import api
from logpipe.cli import app
from logpipe.cli.data import summary_notes
from logpipe.dataset.reader import Dataset
from logpipe.errors import LogpipeError, SourceError

runner = CliRunner()
VOLATILE = {"seconds", "dataset", "out", "model_seconds", "io_seconds", "io_wait_seconds", "io_busy_seconds",
            "samples_per_s"}


def _cli(*args: str) -> dict[str, Any]:
    result = runner.invoke(app, [*args, "--json"])
    assert result.exit_code == 0, result.output
    summary: dict[str, Any] = json.loads(result.stdout)
    return summary


def _stable(summary: Any) -> dict[str, Any]:
    return {k: v for k, v in dict(summary).items() if k not in VOLATILE}


def _committed_bytes(folder: Path) -> dict[str, bytes]:
    """Every file the folder's manifest names, and the manifest itself, by relative path."""
    manifest = json.loads((folder / "manifest.json").read_text())
    return {name: (folder / name).read_bytes() for name in [*manifest["files"], "manifest.json"]}


def test_api_and_cli_write_the_same_bytes_from_ingest_to_score(bundled: Path, tmp_path: Path) -> None:
    """ingest → predict cv → score, once through the CLI, once through the API (str paths for the dataset,
    Path for the rest): the same summaries (less times and output paths) and the same committed files."""
    cli_ds, api_ds = tmp_path / "cli" / "ds", tmp_path / "api" / "ds"
    cli_ingest = _cli("ingest", str(bundled / "ethucy"), "--out", str(cli_ds), "--no-mcap", "-j", "1")
    api_ingest = logpipe.ingest(str(bundled / "ethucy"), out=str(api_ds), mcap=False, workers=1)
    assert _stable(api_ingest) == _stable(cli_ingest)
    assert _committed_bytes(api_ds) == _committed_bytes(cli_ds)
    assert api_ingest["samples"] > 0

    cli_pred, api_pred = tmp_path / "cli" / "pred", tmp_path / "api" / "pred"
    cli_predict = _cli("predict", str(cli_ds), "--predictor", "cv", "--out", str(cli_pred), "--no-mcap",
                       "--filter", "split=eth/test")
    api_predict = logpipe.predict(api_ds, out=api_pred, predictor="cv", mcap=False, filters=["split=eth/test"])
    assert _stable(api_predict) == _stable(cli_predict) and api_predict["samples"] > 0
    assert _committed_bytes(api_pred) == _committed_bytes(cli_pred)

    cli_score = _cli("score", str(cli_pred), "--truth", str(cli_ds), "--out", str(tmp_path / "cli" / "score"),
                     "--no-plots", "--split", "eth/test")
    api_score = logpipe.score([api_pred], truth=api_ds, out=tmp_path / "api" / "score", plots=False,
                              split="eth/test")
    # The same report once each run's folder is named alike (the report names its inputs).
    cli_text = json.dumps(_stable(cli_score), sort_keys=True).replace(str(tmp_path / "cli"), "RUN")
    api_text = json.dumps(_stable(api_score), sort_keys=True).replace(str(tmp_path / "api"), "RUN")
    assert api_text == cli_text
    assert api_score["methods"]["cv"]["overall"]["k1"]["ade"] > 0

    verified = api.verify([str(api_ds), api_pred])
    assert verified["problems"] == [] and verified["files_checked"] > 0


def test_str_and_path_give_the_same_dataset(bundled: Path, tmp_path: Path) -> None:
    as_str = logpipe.ingest([str(bundled / "apolloscape")], out=str(tmp_path / "s"), mcap=False, workers=1)
    as_path = logpipe.ingest(bundled / "apolloscape", out=tmp_path / "p", mcap=False, workers=1)
    assert _stable(as_str) == _stable(as_path) and as_str["logs"] == 2
    assert _committed_bytes(tmp_path / "s") == _committed_bytes(tmp_path / "p")
    assert logpipe.index(str(tmp_path / "s"), min_targets=2)["samples"] == \
        logpipe.index(tmp_path / "p", min_targets=2)["samples"]


def test_bad_input_and_bad_options_raise_logpipe_errors(bundled: Path, tmp_path: Path) -> None:
    (tmp_path / "in").mkdir()
    (tmp_path / "in" / "1.csv").write_text("TIMESTAMP,TRACK_ID,OBJECT_TYPE,X,Y,CITY_NAME\n1.0,a,AV,oops,2.0,MIA\n")
    with pytest.raises(SourceError, match="field 'X': not a number") as caught:
        logpipe.ingest(tmp_path / "in", out=tmp_path / "o", format="argoverse1")
    assert caught.value.line == 2 and not (tmp_path / "o").exists()
    with pytest.raises(LogpipeError, match="--on-error must be fail or skip"):
        logpipe.ingest(bundled / "apolloscape", out=tmp_path / "o", on_error="ignore")
    with pytest.raises(LogpipeError, match="no such file"):
        logpipe.ingest(tmp_path / "missing", out=tmp_path / "o", format="argoverse1")
    logpipe.ingest(bundled / "apolloscape", out=tmp_path / "ds", mcap=False, workers=1)
    with pytest.raises(LogpipeError, match="give --protocol"):
        logpipe.index(tmp_path / "ds")
    with pytest.raises(LogpipeError, match=r"expected kN\.METRIC=NUMBER"):
        logpipe.score([tmp_path / "nothing"], truth=tmp_path / "ds", out=tmp_path / "r", fail_above=["k1.ade"])
    with pytest.raises(LogpipeError, match="unknown raster channels"):
        logpipe.rasterise(tmp_path / "ds", channels="no_such_channel")


def test_import_logpipe_loads_no_stage() -> None:
    """``import logpipe`` stays cheap: the API and the stages load on first use (checked in a fresh process)."""
    import subprocess
    import sys

    code = ("import sys, logpipe; assert 'logpipe.api' not in sys.modules; logpipe.ingest; "
            "assert 'logpipe.api' in sys.modules and 'logpipe.stages.ingest' not in sys.modules; "
            "assert 'numpy' not in sys.modules")
    subprocess.run([sys.executable, "-c", code], check=True)
    assert logpipe.ingest is api.ingest and logpipe.score is api.score and "score" in logpipe.__all__
    with pytest.raises(AttributeError):
        _ = logpipe.no_such_command


def test_identical_copies_are_counted_and_named(bundled: Path, tmp_path: Path) -> None:
    """tests/data/ethucy holds crowds_zara01_train.txt under eth/train and hotel/train (byte-identical): four
    files, three inputs, and the summary says which file was the copy of which."""
    files = sorted(p.relative_to(bundled / "ethucy").as_posix() for p in (bundled / "ethucy").rglob("*.txt"))
    s = logpipe.ingest(bundled / "ethucy", out=tmp_path / "e", mcap=False, workers=1)
    assert s["inputs_found"] + s["duplicates"] == len(files) == 4
    assert s["duplicate_inputs"] == [{"path": "hotel/train/crowds_zara01_train.txt",
                                      "same_as": "eth/train/crowds_zara01_train.txt"}]
    copy = s["duplicate_inputs"][0]
    assert (bundled / "ethucy" / copy["path"]).read_bytes() == (bundled / "ethucy" / copy["same_as"]).read_bytes()
    assert summary_notes(s)[0].startswith("1 inputs were identical copies")
    again = logpipe.ingest(bundled / "ethucy", out=tmp_path / "e", mcap=False, workers=1)
    assert again["inputs_skipped_already_ingested"] == 3 and again["duplicates"] == 1
    result = runner.invoke(app, ["ingest", str(bundled / "ethucy"), "--out", str(tmp_path / "h"), "--no-mcap"])
    assert result.exit_code == 0 and "1 inputs were identical copies" in result.output


def _logs_without_samples(folder: Path) -> int:
    ds = Dataset.open(folder)
    sampled = set(pq.read_table(ds.root / ds.manifest["tables"]["samples"]["file"]).column("log_id").to_pylist())
    return int(ds.manifest["totals"]["logs"]) - len(sampled)


def test_logs_without_samples_say_why(bundled: Path, tmp_path: Path) -> None:
    """Every log without a sample is counted under one reason, and the reason is the rule that failed."""
    ds = tmp_path / "ap"
    first = logpipe.ingest(bundled / "apolloscape", out=ds, mcap=False, workers=1)
    assert first["logs_without_samples"] == {} and _logs_without_samples(ds) == 0  # both logs give samples
    long = logpipe.index(ds, obs=60, pred=60)
    assert long["logs_without_samples"] == {"too short for 60+60 steps": 2} and long["samples"] == 0
    # Both logs have agents observed over 6 + 6 steps (above); one has no bus or truck among them.
    buses = logpipe.index(ds, protocol="apolloscape", target_types="bus_truck")
    assert buses["logs_without_samples"] == {"no target of the selected types (bus_truck)": 1}
    assert _logs_without_samples(ds) == 1
    pickier = logpipe.index(ds, protocol="apolloscape", min_targets=1000)
    assert pickier["logs_without_samples"] == {"fewer than 1000 targets in every window": 2}
    result = runner.invoke(app, ["index", str(ds), "--obs", "60", "--pred", "60"])
    assert result.exit_code == 0 and "2 logs gave no sample: too short for 60+60 steps" in result.output


def test_windows_no_agent_spans(bundled: Path, tmp_path: Path) -> None:
    """ETH/UCY with 400 + 400 steps: logs shorter than 800 steps are too short; in the longer ones no pedestrian
    is seen for 800 steps (checked on the track table); each log is counted once."""
    ds = tmp_path / "e"
    logpipe.ingest(bundled / "ethucy", out=ds, mcap=False, workers=1)
    dataset = Dataset.open(ds)
    steps = {r["log_id"]: r["num_steps"] for r in dataset.logs().to_pylist()}
    longest = dataset.tracks().group_by(["log_id", "track_id"]).aggregate([("step", "count")])
    assert max(longest.column("step_count").to_pylist()) < 800
    s = logpipe.index(ds, obs=400, pred=400)
    assert s["samples"] == 0 and _logs_without_samples(ds) == len(steps) == 3
    assert s["logs_without_samples"] == {
        "no agent observed over the whole window": sum(n >= 800 for n in steps.values()),
        "too short for 400+400 steps": sum(n < 800 for n in steps.values()),
    }
    assert set(s["logs_without_samples"].values()) == {1, 2}


@pytest.mark.shared
def test_av2_sensor_logs_have_no_focal_track(shared: Path, tmp_path: Path) -> None:
    """AV2 sensor logs mark no focal agent, and the argoverse2 preset predicts only the focal track: 0 samples,
    with that reason; --targets fully_observed gives each log its sample."""
    s = logpipe.ingest(shared / "av2" / "sensor_logs", out=tmp_path / "a", mcap=False, workers=1)
    assert s["logs"] == 4 and s["samples"] == 0
    ((reason, count),) = s["logs_without_samples"].items()
    assert count == 4 and reason.startswith("no focal track")
    tracks = Dataset.open(tmp_path / "a").tracks()
    assert "focal" not in set(tracks.column("role").to_pylist())
    fixed = logpipe.index(tmp_path / "a", protocol="argoverse2", targets="fully_observed")
    assert fixed["samples"] == 4 and fixed["logs_without_samples"] == {}
