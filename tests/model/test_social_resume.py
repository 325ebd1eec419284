"""Resuming a social baseline's training (issue 63, round two): a run stopped and resumed with ``logpipe train
--resume`` ends with the same weights, optimiser states, log and best checkpoint as the run left alone; a resume
that would not continue the run (another config, a damaged training state) is refused in one line."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch
from safetensors.torch import load_file
from typer.testing import CliRunner

from logpipe.cli import app

ETHUCY = Path(__file__).resolve().parents[1] / "data" / "ethucy"
runner = CliRunner()


@pytest.fixture(scope="module")
def dataset(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("resume") / "ethucy"
    assert runner.invoke(app, ["-q", "ingest", str(ETHUCY), "--out", str(out), "--no-mcap"]).exit_code == 0
    return out


def _train(dataset: Path, preset: str, config: Path, run: Path, steps: int, *extra: str) -> dict[str, object]:
    result = runner.invoke(app, ["train", str(dataset), "--train-split", "eth/train", "--val-split", "hotel/test",
                                 "--preset", preset, "--config", str(config), "--steps", str(steps), "--out",
                                 str(run), "--json", *extra])
    assert result.exit_code == 0, result.output
    summary: dict[str, object] = json.loads(result.stdout)
    return summary


def _log(run: Path) -> list[dict[str, float]]:
    rows = [json.loads(line) for line in (run / "train_log.jsonl").read_text().splitlines()]
    return [{k: v for k, v in r.items() if k != "seconds"} for r in rows]


@pytest.mark.parametrize("preset", ["social_lstm", "social_gan_20vp"])
def test_stop_and_resume_equals_the_uninterrupted_run(preset: str, dataset: Path, tmp_path: Path) -> None:
    table = "social_lstm" if preset == "social_lstm" else "social_gan"
    config = tmp_path / "small.toml"
    small = "hidden_dim = 16\nembedding_dim = 8\n" if table == "social_lstm" else ""
    config.write_text(f"[{table}]\nbatch_size = 4\nval_every = 2\nval_windows = 6\npatience = 0\n{small}")
    whole, parts = tmp_path / "whole", tmp_path / "parts"
    _train(dataset, preset, config, whole, 6)
    first = _train(dataset, preset, config, parts, 4)
    assert first["steps"] == 4 and "resumed_at_step" not in first
    resumed = _train(dataset, preset, config, parts, 6, "--resume")
    assert resumed["steps"] == 6 and resumed["resumed_at_step"] == 4

    for folder in ("last", "best"):
        a, b = (load_file(str(r / folder / "weights.safetensors")) for r in (whole, parts))
        assert a.keys() == b.keys() and all(bool((a[k] == b[k]).all()) for k in a), folder
    a, b = (json.loads((r / "last" / "meta.json").read_text()) for r in (whole, parts))
    assert a["step"] == b["step"] == 6 and a["metrics"] == b["metrics"]
    # the optimisers' moments and the random states too: a further part of both would go on alike
    sa, sb = (torch.load(r / "last" / "train_state.pt", weights_only=True) for r in (whole, parts))
    assert torch.equal(sa["torch_rng"], sb["torch_rng"]) and sa["batches"] == sb["batches"]
    for name, opt in sa["optimizers"].items():
        for index, moments in opt["state"].items():
            assert all(torch.equal(v, sb["optimizers"][name]["state"][index][k]) for k, v in moments.items())
    assert _log(whole) == _log(parts) and [r["step"] for r in _log(parts)] == [2, 4, 6]
    # the run left alone moved: equality above is not two untrained copies
    first_log = _log(whole)
    assert first_log[0] != first_log[-1]


def test_a_resume_that_would_not_continue_the_run_is_refused(dataset: Path, tmp_path: Path) -> None:
    config = tmp_path / "small.toml"
    config.write_text("[social_gan]\nbatch_size = 4\nval_every = 2\nval_windows = 6\n")
    run = tmp_path / "run"
    _train(dataset, "social_gan_20v", config, run, 2)
    other = tmp_path / "other.toml"
    other.write_text("[social_gan]\nbatch_size = 8\nval_every = 2\nval_windows = 6\n")
    result = runner.invoke(app, ["-q", "train", str(dataset), "--train-split", "eth/train", "--val-split", "hotel/test",
                                 "--preset", "social_gan_20v", "--config", str(other), "--steps", "4", "--out",
                                 str(run), "--resume"])
    assert result.exit_code == 2 and "batch_size" in result.output and result.output.count("\n") == 1
    state = run / "last" / "train_state.pt"
    state.write_bytes(state.read_bytes()[:-10])
    result = runner.invoke(app, ["-q", "train", str(dataset), "--train-split", "eth/train", "--val-split", "hotel/test",
                                 "--preset", "social_gan_20v", "--config", str(config), "--steps", "4", "--out",
                                 str(run), "--resume"])
    assert result.exit_code == 2 and "train_state.pt" in result.output and "sha256" in result.output
    assert result.output.count("\n") == 1
