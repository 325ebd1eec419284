"""``meta.json`` of a checkpoint of the paper's network (and its LSTM / Noise-LSTM presets): the full TrainConfig,
normalisation, dataset kind and manifest hash, ``TrainingData`` and the ``InferenceSettings`` chosen on validation;
parsing it (``read_meta``), comparing it with what a caller expects (``check_meta``) and amending the entries that
may change after training (``amend_meta``). What every family's ``meta.json`` shares is ``model.checkpoint.format``;
``model.zhu2020.checkpoint`` writes and loads the folder around it.
"""

from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from logpipe.storage.folder_lock import FolderLock
from logpipe.storage.io import atomic_path, read_json

from ..checkpoint.format import (
    CHECKPOINT_FORMAT,
    CheckpointError,
    CheckpointMismatchError,
    InferenceSettings,
    TrainingData,
    config_differences,
    kind_accepts,
    meta_checksum_problem,
    stamped_meta,
)
from .config import ConfigError, ModelConfig, TrainConfig, config_to_dict, train_config_from_dict

FORMAT_VERSION = 1
MODEL_KIND = "zhu2020"


@dataclass
class CheckpointMeta:
    """Contents of ``meta.json``.

    Attributes:
        config: the full training config (its ``model`` rebuilds the network).
        dataset_kind: dataset family the model was trained on (``ethucy``, ``argoverse``, ...); formats joined
            by ``+`` when trained on datasets of several (``combined_kind``).
        manifest_hash: hash of the training dataset's manifest, as given by the caller (``combined_manifest_hash``
            of the manifests, in order, for several datasets).
        logpipe_version: version of the code that wrote the checkpoint.
        step: optimiser steps done.
        metrics: e.g. ``val_ade``/``val_fde`` (metres) at this step.
        weights_sha256: digest of ``weights.safetensors``.
        created_unix: wall-clock seconds when written.
        training_data: the splits and recordings trained / validated on (None in older checkpoints).
        inference: settings chosen on validation, predict's defaults (None: as trained).
    """

    config: TrainConfig
    dataset_kind: str
    manifest_hash: str
    logpipe_version: str
    step: int
    metrics: dict[str, float]
    weights_sha256: str
    created_unix: float
    training_data: TrainingData | None = None
    inference: InferenceSettings | None = None

    @property
    def normalisation(self) -> dict[str, Any]:
        """Frame and scales that define model-frame coordinates (see ``batching``)."""
        m = self.config.model
        return {"frame": m.frame, "pos_scale_m": m.pos_scale_m, "disp_scale_m": m.disp_scale_m}

    def to_dict(self) -> dict[str, Any]:
        """The JSON document written to ``meta.json``, with the ``checksum`` of everything else in it."""
        return stamped_meta(self._body())

    def _body(self) -> dict[str, Any]:
        return {
            "format": CHECKPOINT_FORMAT,
            "format_version": FORMAT_VERSION,
            "model_kind": MODEL_KIND,
            "config": config_to_dict(self.config),
            "normalisation": self.normalisation,
            "dataset_kind": self.dataset_kind,
            "manifest_hash": self.manifest_hash,
            "logpipe_version": self.logpipe_version,
            "step": self.step,
            "metrics": self.metrics,
            "weights_sha256": self.weights_sha256,
            "created_unix": self.created_unix,
            **({"training_data": self.training_data.to_dict()} if self.training_data is not None else {}),
            **({"inference": dataclasses.asdict(self.inference)} if self.inference is not None else {}),
        }


def read_meta(folder: Path) -> CheckpointMeta:
    """Parse and check ``meta.json`` of a checkpoint folder."""
    path = folder / "meta.json"
    try:
        data = read_json(path)
    except (OSError, ValueError) as exc:
        raise CheckpointError(f"{path}: not a readable checkpoint: {exc}") from exc
    if not isinstance(data, dict):
        raise CheckpointError(f"{path}: not a readable checkpoint: not a JSON object")
    meta = _parse_meta(data, path)
    problem = meta_checksum_problem(data)
    if problem:
        raise CheckpointError(f"{path}: {problem}")
    return meta


def _parse_meta(data: dict[str, Any], path: Path) -> CheckpointMeta:
    if data.get("format") != CHECKPOINT_FORMAT or data.get("model_kind") != MODEL_KIND:
        raise CheckpointError(f"{path}: not a {MODEL_KIND} {CHECKPOINT_FORMAT}")
    if data.get("format_version") != FORMAT_VERSION:
        raise CheckpointError(
            f"{path}: checkpoint format version {data.get('format_version')} is not {FORMAT_VERSION}"
        )
    try:
        config = train_config_from_dict(data["config"])
        return CheckpointMeta(
            config=config,
            dataset_kind=str(data["dataset_kind"]),
            manifest_hash=str(data["manifest_hash"]),
            logpipe_version=str(data["logpipe_version"]),
            step=int(data["step"]),
            metrics={str(k): float(v) for k, v in data["metrics"].items()},
            weights_sha256=str(data["weights_sha256"]),
            created_unix=float(data["created_unix"]),
            training_data=TrainingData.from_dict(data["training_data"], path) if "training_data" in data else None,
            inference=InferenceSettings.from_dict(data["inference"], path) if data.get("inference") else None,
        )
    except (KeyError, TypeError, ValueError, ConfigError) as exc:
        raise CheckpointError(f"{path}: malformed checkpoint metadata: {exc}") from exc


AMENDABLE = frozenset({"inference", "training_data"})
"""``meta.json`` entries that may change after training: neither touches the weights or what they mean."""


def amend_meta(folder: Path, **changes: InferenceSettings | TrainingData | None) -> CheckpointMeta:
    """Record (or with None, clear) the inference settings chosen on validation (``inference=``) or the data a
    checkpoint was trained on (``training_data=``, for checkpoints older than that record) in ``meta.json``.

    Only ``meta.json`` changes (the weights and their sha256 stay); it is replaced whole, under the folder's lock.

    Raises:
        CheckpointError: not a checkpoint folder, or another entry named; ArtifactBusyError: another writer.
    """
    unknown = sorted(set(changes) - AMENDABLE)
    if unknown:
        raise CheckpointError(f"{folder}: only {sorted(AMENDABLE)} may be amended, not {unknown}")
    lock = FolderLock(folder)
    lock.acquire()
    try:
        meta = dataclasses.replace(read_meta(folder), **changes)  # type: ignore[arg-type]
        with atomic_path(folder / "meta.json", durable=True) as tmp:
            tmp.write_text(json.dumps(meta.to_dict(), indent=2, sort_keys=True) + "\n", encoding="utf-8")
    finally:
        lock.release()
    return meta


def check_meta(
    meta: CheckpointMeta,
    where: Path,
    *,
    expect_kind: str | None = None,
    expect_config: ModelConfig | TrainConfig | None = None,
    expect_manifest_hash: str | None = None,
) -> None:
    """Raise ``CheckpointMismatchError`` naming every difference from what the caller expects (a checkpoint
    trained on several formats fits each of them: ``kind_accepts``)."""
    problems = []
    if expect_kind is not None and not kind_accepts(meta.dataset_kind, expect_kind):
        problems.append(f"dataset kind: expected {expect_kind!r}, checkpoint has {meta.dataset_kind!r}")
    if expect_manifest_hash is not None and meta.manifest_hash != expect_manifest_hash:
        problems.append(
            f"dataset manifest hash: expected {expect_manifest_hash!r}, checkpoint has {meta.manifest_hash!r}"
        )
    if isinstance(expect_config, TrainConfig):
        problems += config_differences(config_to_dict(expect_config), config_to_dict(meta.config), "train.")
    elif isinstance(expect_config, ModelConfig):
        problems += config_differences(config_to_dict(expect_config), config_to_dict(meta.config.model), "model.")
    if problems:
        raise CheckpointMismatchError(f"{where}: checkpoint does not match: " + "; ".join(problems))
