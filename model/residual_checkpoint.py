"""Checkpoints of the residual driving model: ``weights.safetensors`` and ``meta.json`` in one folder, never a
pickle, replaced whole (``logpipe.storage.folder_swap``) so a crash leaves the old folder or the new one.

``meta.json`` holds the format and ``model_kind`` (``prior_residual``), the full ``ResidualConfig``, the dataset
kind and manifest hash, ``TrainingData`` (what it was trained and validated on), the validation metrics, the
distribution of its training inputs (``ood``: what ``logpipe predict`` scores targets against), the weights'
sha256 and the logpipe version. Weights load only when their sha256 is the one ``meta.json`` names, and only
finite weights are accepted.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from safetensors import SafetensorError
from safetensors.torch import load_file, save_file

from logpipe.storage.folder_swap import recover_folder, replace_folder, staging_folder_for

from .checkpoint_meta import CHECKPOINT_FORMAT, CheckpointError, TrainingData, logpipe_version
from .residual_config import MODEL_KIND, ResidualConfig, ResidualConfigError
from .residual_net import ResidualNet

FORMAT_VERSION = 1
WEIGHTS = "weights.safetensors"
META = "meta.json"


@dataclass
class ResidualMeta:
    """``meta.json`` of a residual checkpoint (see the module docstring)."""

    config: ResidualConfig
    dataset_kind: str
    manifest_hash: str
    epoch: int
    metrics: dict[str, float]
    ood: dict[str, Any]
    weights_sha256: str = ""
    training_data: TrainingData | None = None
    logpipe_version: str = ""
    created_unix: float = 0.0

    def to_dict(self) -> dict[str, Any]:
        """The JSON document."""
        return {"format": CHECKPOINT_FORMAT, "format_version": FORMAT_VERSION, "model_kind": MODEL_KIND,
                "residual": self.config.to_dict(), "dataset_kind": self.dataset_kind,
                "manifest_hash": self.manifest_hash, "epoch": self.epoch, "metrics": self.metrics, "ood": self.ood,
                "weights_sha256": self.weights_sha256, "logpipe_version": self.logpipe_version,
                "created_unix": self.created_unix,
                **({"training_data": self.training_data.to_dict()} if self.training_data is not None else {})}


def model_kind(folder: Path) -> str | None:
    """The ``model_kind`` a checkpoint folder's ``meta.json`` names (None when unreadable)."""
    try:
        data = json.loads((folder / META).read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    kind = data.get("model_kind") if isinstance(data, dict) else None
    return kind if isinstance(kind, str) else None


def read_residual_meta(folder: Path) -> ResidualMeta:
    """Parse ``meta.json`` of a residual checkpoint.

    Raises:
        CheckpointError: unreadable, of another format or kind, or with a malformed config.
    """
    path = folder / META
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError) as exc:
        raise CheckpointError(f"{path}: not a readable checkpoint: {exc}") from None
    if not isinstance(data, dict) or data.get("format") != CHECKPOINT_FORMAT or data.get("model_kind") != MODEL_KIND:
        raise CheckpointError(f"{path}: not a {MODEL_KIND} {CHECKPOINT_FORMAT}")
    if data.get("format_version") != FORMAT_VERSION:
        raise CheckpointError(f"{path}: residual checkpoint version {data.get('format_version')} is not "
                              f"{FORMAT_VERSION}")
    try:
        config = ResidualConfig.from_dict(dict(data["residual"]), str(path))
        training = data.get("training_data")
        return ResidualMeta(config=config, dataset_kind=str(data["dataset_kind"]),
                            manifest_hash=str(data["manifest_hash"]), epoch=int(data["epoch"]),
                            metrics={str(k): float(v) for k, v in dict(data.get("metrics", {})).items()},
                            ood=dict(data.get("ood") or {}), weights_sha256=str(data["weights_sha256"]),
                            training_data=None if training is None else TrainingData.from_dict(training, path),
                            logpipe_version=str(data.get("logpipe_version", "")),
                            created_unix=float(data.get("created_unix", 0.0)))
    except (KeyError, TypeError, ValueError, ResidualConfigError) as exc:
        raise CheckpointError(f"{path}: malformed residual checkpoint metadata: {exc}") from None


def _sha256(path: Path) -> str:
    digest = hashlib.sha256()
    with path.open("rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def save_residual(folder: Path, net: ResidualNet, meta: ResidualMeta) -> Path:
    """Write the checkpoint folder (replacing one that is there), ``meta.json`` last, naming the weights' sha256."""
    recover_folder(folder)
    staging = staging_folder_for(folder)
    try:
        staging.mkdir(parents=True, exist_ok=True)
        weights = staging / WEIGHTS
        save_file({k: v.detach().cpu().contiguous().clone() for k, v in net.state_dict().items()}, str(weights))
        meta.weights_sha256 = _sha256(weights)
        meta.logpipe_version, meta.created_unix = logpipe_version(), time.time()
        tmp = staging / (META + ".tmp")
        tmp.write_text(json.dumps(meta.to_dict(), indent=2, sort_keys=True) + "\n", encoding="utf-8")
        os.replace(tmp, staging / META)
        replace_folder(staging, folder)
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    return folder


def load_residual(folder: Path) -> tuple[ResidualNet, ResidualMeta]:
    """The network (eval mode) and metadata of a checkpoint folder.

    Raises:
        CheckpointError: metadata as in ``read_residual_meta``; weights missing, not matching their sha256, not
            fitting the config, or not finite.
    """
    meta = read_residual_meta(folder)
    weights = folder / WEIGHTS
    if not weights.is_file() or _sha256(weights) != meta.weights_sha256:
        raise CheckpointError(f"{weights}: missing or does not match the sha256 in meta.json")
    try:
        state = load_file(str(weights))
    except (SafetensorError, OSError) as exc:
        raise CheckpointError(f"{weights}: unreadable weights: {exc}") from None
    bad = sorted(k for k, v in state.items() if v.is_floating_point() and not bool(torch.isfinite(v).all()))
    if bad:
        raise CheckpointError(f"{weights}: non-finite values in {bad[:3]}")
    net = ResidualNet(meta.config)
    try:
        net.load_state_dict(state)
    except RuntimeError as exc:
        raise CheckpointError(f"{weights}: weights do not fit the residual config in meta.json: "
                              f"{str(exc).splitlines()[0]}") from None
    return net.eval(), meta
