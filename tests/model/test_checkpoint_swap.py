"""A checkpoint folder is replaced whole: a crash while saving leaves the previous checkpoint or the new one,
never new weights beside old metadata (which no reader could load)."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest
import torch

from logpipe.model.zhu2020.checkpoint import load_checkpoint, save_checkpoint
from logpipe.model.zhu2020.config import Features, ModelConfig, TrainConfig
from logpipe.model.zhu2020.network import TrajectoryNet
from logpipe.storage import folder_swap

CONFIG = TrainConfig(model=ModelConfig(features=Features(False, False, False, False, False), embed_dim=8, gru_dim=8,
                                       lstm_dim=8, obs_len=8, pred_len=12))


def _net(value: float) -> TrajectoryNet:
    net = TrajectoryNet(CONFIG.model, load_backbone=False)
    with torch.no_grad():
        for p in net.parameters():
            p.fill_(value)
    return net


def _first_weight(folder: Path) -> float:
    loaded = load_checkpoint(folder)
    return float(next(iter(loaded.net.parameters())).detach().flatten()[0])


def _save(folder: Path, value: float, step: int) -> None:
    save_checkpoint(folder, _net(value), CONFIG, dataset_kind="ethucy", manifest_hash="0" * 64, step=step)


def test_rewrite_replaces_the_whole_folder(tmp_path: Path) -> None:
    _save(tmp_path / "best", 0.25, 1)
    _save(tmp_path / "best", 0.5, 2)
    assert _first_weight(tmp_path / "best") == 0.5
    assert sorted(p.name for p in tmp_path.iterdir()) == ["best"]  # no staging or old folder left


@pytest.mark.parametrize("point", ["before swap best", "after swap best"])
def test_kill_while_saving_leaves_old_or_new(tmp_path: Path, point: str) -> None:
    _save(tmp_path / "best", 0.25, 1)
    script = textwrap.dedent(f"""
        import sys
        sys.path.insert(0, {str(Path(__file__).parent)!r})
        from test_checkpoint_swap import _save
        from pathlib import Path
        _save(Path({str(tmp_path / "best")!r}), 0.5, 2)
    """)
    trace = tmp_path / "trace.tsv"
    subprocess.run([sys.executable, "-c", script], env={**os.environ, "LOGPIPE_CRASH_TRACE": str(trace)},
                   check=True, timeout=120)
    _save(tmp_path / "best", 0.25, 1)
    steps = [line.split("\t", 1)[1] for line in trace.read_text().splitlines()]
    killed = subprocess.run([sys.executable, "-c", script],
                            env={**os.environ, "LOGPIPE_CRASH_AT": str(steps.index(point) + 1)}, timeout=120,
                            check=False)
    assert killed.returncode == -9
    assert _first_weight(tmp_path / "best") == (0.25 if point.startswith("before") else 0.5)
    _save(tmp_path / "best", 0.75, 3)  # the next save clears what the killed one left
    assert _first_weight(tmp_path / "best") == 0.75
    assert sorted(p.name for p in tmp_path.iterdir() if p.name != "trace.tsv") == ["best"]


def test_fallback_without_exchange_recovers_a_cut_between_renames(tmp_path: Path,
                                                                   monkeypatch: pytest.MonkeyPatch) -> None:
    _save(tmp_path / "best", 0.25, 1)
    monkeypatch.setattr(folder_swap, "_exchange", lambda a, b: False)
    _save(tmp_path / "best", 0.5, 2)
    assert _first_weight(tmp_path / "best") == 0.5
    (tmp_path / "best").rename(tmp_path / ".best.old")  # as if killed between the two renames
    assert _first_weight(tmp_path / "best") == 0.5
