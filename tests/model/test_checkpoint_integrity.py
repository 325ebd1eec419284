"""Issue 56, item 8: a checkpoint's whole metadata is under its checksum, damaged weights and absurd sizes are one
line before anything uses or allocates them."""

from __future__ import annotations

import json
import shutil
import time
from pathlib import Path

import pytest
from safetensors.torch import load_file, save_file

from logpipe.model.checkpoint.format import CheckpointError, stamped_meta
from logpipe.model.zhu2020.checkpoint import load_checkpoint
from logpipe.model.zhu2020.meta import read_meta
from logpipe.storage.io import sha256_file
from logpipe.verify import verify_tree

SHIPPED = Path(__file__).resolve().parents[2] / "model" / "checkpoints" / "ethucy" / "eth"


@pytest.fixture
def checkpoint(tmp_path: Path) -> Path:
    folder = tmp_path / "ck"
    folder.mkdir()
    for name in ("meta.json", "weights.safetensors"):
        shutil.copy(SHIPPED / name, folder / name)
    return folder


def _edit(folder: Path, change: dict[str, object], *, restamp: bool) -> None:
    meta = json.loads((folder / "meta.json").read_text())
    for dotted, value in change.items():
        *path, key = dotted.split(".")
        block = meta
        for part in path:
            block = block[part]
        block[key] = value
    (folder / "meta.json").write_text(json.dumps(stamped_meta(meta) if restamp else meta, indent=2))


def test_the_shipped_checkpoint_loads_and_verifies(checkpoint: Path) -> None:
    assert "checksum" in json.loads((checkpoint / "meta.json").read_text())
    load_checkpoint(checkpoint)
    assert verify_tree([checkpoint])["problems"] == []


def test_an_edited_inference_setting_is_found_by_verify_and_refused_by_load(checkpoint: Path) -> None:
    """The red-team report: inference.noise_scale edited, verify passed and predict used it."""
    _edit(checkpoint, {"inference.noise_scale": 7.5}, restamp=False)
    problems = verify_tree([checkpoint])["problems"]
    assert len(problems) == 1 and "differs from its checksum" in problems[0]
    with pytest.raises(CheckpointError, match=r"meta\.json: content differs from its checksum"):
        load_checkpoint(checkpoint)


def test_a_nan_weight_is_refused_on_load(checkpoint: Path) -> None:
    """The red-team report: one NaN in a weight tensor gave ``rows: 0`` with exit 0."""
    weights = checkpoint / "weights.safetensors"
    tensors = load_file(str(weights))
    name = sorted(n for n, t in tensors.items() if t.is_floating_point() and t.numel() > 1)[0]
    tensors[name].view(-1)[1] = float("nan")
    save_file(tensors, str(weights))
    _edit(checkpoint, {"weights_sha256": sha256_file(weights)}, restamp=True)  # a consistent, damaged checkpoint
    with pytest.raises(CheckpointError, match=f"tensor '{name}' holds NaN"):
        load_checkpoint(checkpoint)


@pytest.mark.parametrize(("field", "value"), [("lstm_dim", 200_000), ("embed_dim", 10**9), ("pred_len", 10**7)])
def test_absurd_model_sizes_are_refused_before_any_allocation(checkpoint: Path, field: str, value: int) -> None:
    """The red-team report: lstm_dim 200000 in meta.json tried a 640 GB allocation (a traceback)."""
    _edit(checkpoint, {f"config.model.{field}": value}, restamp=True)
    started = time.perf_counter()
    with pytest.raises(CheckpointError, match=f"model.{field} must be at most"):
        read_meta(checkpoint)
    with pytest.raises(CheckpointError, match=f"model.{field} must be at most"):
        load_checkpoint(checkpoint)
    assert time.perf_counter() - started < 5
