"""The shipped ZARA1 checkpoints of the social baselines (issue 63) reproduce their rows of
``docs/results/ethucy_social.md`` through plain ``logpipe predict`` + ``logpipe score``: every figure of the row,
recomputed on the real ZARA1 test file and rounded as the table prints it. Needs ``../shared/data/ethucy``."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest
from typer.testing import CliRunner

from logpipe.cli import app
from logpipe.storage.io import sha256_file

REPO = Path(__file__).resolve().parents[2]
SHIPPED = REPO / "model" / "checkpoints" / "ethucy" / "zara1"
RESULTS = REPO / "docs" / "results" / "ethucy_social.md"
# the ones better than the first round's (docs/results/ethucy_social.md)
SHIPPED_PRESETS = ["social_lstm", "social_gan_20vp"]
LABELS = {"social_lstm": "Social-LSTM", "social_gan_20v": "Social-GAN 20V-20", "social_gan_20vp": "Social-GAN 20VP-20"}
runner = CliRunner()


def reported_rows(label: str, scene: str = "ZARA1") -> dict[str, str]:
    """Rule -> the 'ours' cell (``ADE/FDE``) of ``label``'s rows for ``scene`` in the results table."""
    rows = {}
    for line in RESULTS.read_text(encoding="utf-8").splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if len(cells) > 3 and cells[0] == label and cells[2] == scene:
            rows[cells[1]] = cells[3]
    return rows


@pytest.fixture(scope="module")
def dataset(shared: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("zara1") / "ethucy"
    result = runner.invoke(app, ["-q", "ingest", str(shared / "ethucy"), "--out", str(out), "--no-mcap"])
    assert result.exit_code == 0, result.output
    return out


def _predict_and_score(dataset: Path, checkpoint: Path, out: Path, *modes: str) -> dict[str, Any]:
    result = runner.invoke(app, ["-q", "predict", str(dataset), "--checkpoint", str(checkpoint), "--filter",
                                 "split=zara1/test", "--out", str(out / "pred"), "--no-mcap", *modes])
    assert result.exit_code == 0, result.output
    result = runner.invoke(app, ["score", str(out / "pred"), "--truth", str(dataset), "--split", "zara1/test",
                                 "--min-agents", "2", "--no-plots", "--out", str(out / "score"), "--json"])
    assert result.exit_code == 0, result.output
    report: dict[str, Any] = json.loads(result.stdout)
    return report


def _cell(block: dict[str, float], joint: bool = False) -> str:
    ade, fde = (block["ade_joint"], block["fde_joint"]) if joint else (block["ade"], block["fde"])
    return f"{ade:.2f}/{fde:.2f}"


@pytest.mark.shared
@pytest.mark.parametrize("preset", SHIPPED_PRESETS)
def test_the_shipped_zara1_checkpoint_reproduces_its_rows(preset: str, dataset: Path, shared: Path,
                                                          tmp_path: Path) -> None:
    dataset_files = shared / "ethucy"
    checkpoint = SHIPPED / preset
    reported = reported_rows(LABELS[preset])
    assert len(reported) == 3, f"{RESULTS} has no ZARA1 rows of {LABELS[preset]}"
    table = "social_lstm" if preset == "social_lstm" else "social_gan"
    report = _predict_and_score(dataset, checkpoint, tmp_path / "k20")
    method = report["methods"][table]
    assert method["counts"]["agents_missing"] == 0 and method["counts"]["agents_expected"] > 2000
    k20 = method["overall"]["k20"]
    if preset == "social_lstm":
        mean = _predict_and_score(dataset, checkpoint, tmp_path / "k1", "--modes", "1")["methods"][table]
        ours = {"K=1 (mean forecast; the published rule)": _cell(mean["overall"]["k1"]),
                "best-of-20 per agent": _cell(k20), "best-of-20 joint": _cell(k20, joint=True)}
    else:
        ours = {"best-of-20 joint (the published rule)": _cell(k20, joint=True), "best-of-20 per agent": _cell(k20),
                "K=1 (first sample)": _cell(method["overall"]["k1"])}
    assert ours == reported
    # the checkpoint never saw ZARA1's test file: meta.json names the files (sha256) it trained and validated on
    meta = json.loads((checkpoint / "meta.json").read_text())
    seen = {*meta["training_data"]["train_sources"], *meta["training_data"]["val_sources"]}
    assert len(seen) == 14 and sha256_file(dataset_files / "zara1" / "test" / "crowds_zara01.txt") not in seen


def test_every_shipped_social_checkpoint_has_its_reproduction_and_rows() -> None:
    assert sorted(p.name for p in SHIPPED.glob("social_*")) == sorted(SHIPPED_PRESETS)
    for preset in SHIPPED_PRESETS:
        assert (SHIPPED / preset / "weights.safetensors").stat().st_size < 4 * 2**20  # small enough to ship
        assert len(reported_rows(LABELS[preset])) == 3
