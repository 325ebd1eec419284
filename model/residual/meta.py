"""``meta.json`` of a residual driving-model checkpoint, readable without torch (``logpipe predict`` of a baseline
never loads it): the format and ``model_kind`` (``prior_residual``), the full ``ResidualConfig``, the dataset kind
and manifest hash, ``TrainingData`` (what it was trained and validated on), the validation metrics, the
distribution of its training inputs (``ood``: what ``logpipe predict`` scores targets against), the weights'
sha256 and the logpipe version. ``model.residual.checkpoint`` writes and loads the folder.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

from logpipe.storage.io import read_json

from ..checkpoint.format import (
    CHECKPOINT_FORMAT,
    CheckpointError,
    TrainingData,
    meta_checksum_problem,
    stamped_meta,
)
from .config import MODEL_KIND, ResidualConfig, ResidualConfigError

WEIGHTS = "weights.safetensors"
META = "meta.json"
FORMAT_VERSION = 1


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
        """The JSON document, with the ``checksum`` of all the rest (``model.checkpoint.format.stamped_meta``)."""
        return stamped_meta({"format": CHECKPOINT_FORMAT, "format_version": FORMAT_VERSION, "model_kind": MODEL_KIND,
                "residual": self.config.to_dict(), "dataset_kind": self.dataset_kind,
                "manifest_hash": self.manifest_hash, "epoch": self.epoch, "metrics": self.metrics, "ood": self.ood,
                "weights_sha256": self.weights_sha256, "logpipe_version": self.logpipe_version,
                "created_unix": self.created_unix,
                **({"training_data": self.training_data.to_dict()} if self.training_data is not None else {})})


def model_kind(folder: Path) -> str | None:
    """The ``model_kind`` a checkpoint folder's ``meta.json`` names (None when unreadable)."""
    try:
        data = read_json(folder / META)
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
        data = read_json(path)
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
        meta = ResidualMeta(config=config, dataset_kind=str(data["dataset_kind"]),
                            manifest_hash=str(data["manifest_hash"]), epoch=int(data["epoch"]),
                            metrics={str(k): float(v) for k, v in dict(data.get("metrics", {})).items()},
                            ood=dict(data.get("ood") or {}), weights_sha256=str(data["weights_sha256"]),
                            training_data=None if training is None else TrainingData.from_dict(training, path),
                            logpipe_version=str(data.get("logpipe_version", "")),
                            created_unix=float(data.get("created_unix", 0.0)))
    except (KeyError, TypeError, ValueError, ResidualConfigError) as exc:
        raise CheckpointError(f"{path}: malformed residual checkpoint metadata: {exc}") from None
    problem = meta_checksum_problem(data)
    if problem:
        raise CheckpointError(f"{path}: {problem}")
    return meta
