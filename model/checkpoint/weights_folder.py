"""A checkpoint folder of a family whose whole state is one set of weights and a plain config (the social
baselines, ``model.social_lstm`` and ``model.social_gan``): ``weights.safetensors`` and ``meta.json``, never a
pickle, the folder replaced whole (``logpipe.storage.folder_swap``) so a crash leaves the old folder or the new one.

``meta.json`` carries ``format``, ``format_version``, ``model_kind``, the family's ``config`` table, the dataset
kind, manifest hash, window lengths, what it was trained on (``TrainingData``), validation metrics, the weights'
sha256 and the ``checksum`` of all the rest (``stamped_meta``). Weights load only when their sha256 is that one, as
safetensors (no code runs), and only finite ones.
"""

from __future__ import annotations

import json
import os
import shutil
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol

from logpipe.storage.folder_swap import recover_folder, replace_folder, staging_folder_for
from logpipe.storage.io import sha256_file

from .format import (
    CHECKPOINT_FORMAT,
    CheckpointError,
    TrainingData,
    logpipe_version,
    meta_checksum_problem,
    stamped_meta,
)

if TYPE_CHECKING:  # meta.json is read without torch (predict of a baseline never loads it); weights load with it
    import torch

WEIGHTS = "weights.safetensors"
META = "meta.json"
FORMAT_VERSION = 1


@dataclass
class WeightsMeta:
    """``meta.json`` of a weights-and-config checkpoint (see the module docstring)."""

    model_kind: str
    config: dict[str, Any]
    dataset_kind: str
    manifest_hash: str
    obs_len: int
    pred_len: int
    step: int
    metrics: dict[str, float] = field(default_factory=dict)
    training_data: TrainingData | None = None
    weights_sha256: str = ""
    logpipe_version: str = ""
    created_unix: float = 0.0

    def to_dict(self) -> dict[str, Any]:
        """The JSON document with its checksum."""
        body = {"format": CHECKPOINT_FORMAT, "format_version": FORMAT_VERSION, "model_kind": self.model_kind,
                "config": self.config, "dataset_kind": self.dataset_kind, "manifest_hash": self.manifest_hash,
                "obs_len": self.obs_len, "pred_len": self.pred_len, "step": self.step, "metrics": self.metrics,
                "weights_sha256": self.weights_sha256, "logpipe_version": self.logpipe_version,
                "created_unix": self.created_unix}
        if self.training_data is not None:
            body["training_data"] = self.training_data.to_dict()
        return stamped_meta(body)


class FolderMeta(Protocol):
    """What ``save_weights_folder`` stamps and writes of a family's ``meta.json`` (``WeightsMeta``,
    ``residual.meta.ResidualMeta``)."""

    weights_sha256: str
    logpipe_version: str
    created_unix: float

    def to_dict(self) -> dict[str, Any]:
        """The JSON document."""
        ...


def save_weights_folder(folder: Path, state: dict[str, torch.Tensor], meta: FolderMeta) -> Path:
    """Write ``state`` and ``meta`` into ``folder`` (replacing one that is there), ``meta.json`` last, naming the
    weights' sha256; the folder is swapped in whole, so a crash leaves the old folder or the new one."""
    from safetensors.torch import save_file

    recover_folder(folder)
    staging = staging_folder_for(folder)
    try:
        staging.mkdir(parents=True, exist_ok=True)
        weights = staging / WEIGHTS
        save_file({k: v.detach().cpu().contiguous().clone() for k, v in state.items()}, str(weights))
        meta.weights_sha256 = sha256_file(weights)
        meta.logpipe_version, meta.created_unix = logpipe_version(), time.time()
        tmp = staging / (META + ".tmp")
        tmp.write_text(json.dumps(meta.to_dict(), indent=2, sort_keys=True) + "\n", encoding="utf-8")
        os.replace(tmp, staging / META)
        replace_folder(staging, folder)
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    return folder


def read_weights_meta(folder: Path, model_kinds: tuple[str, ...]) -> WeightsMeta:
    """Parse ``folder/meta.json``, which must be of one of ``model_kinds``.

    Raises:
        CheckpointError: unreadable, another format, kind or version, a malformed field, or edited (checksum).
    """
    path = folder / META
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError) as exc:
        raise CheckpointError(f"{path}: not a readable checkpoint: {exc}") from None
    kind = data.get("model_kind") if isinstance(data, dict) else None
    if not isinstance(data, dict) or data.get("format") != CHECKPOINT_FORMAT or kind not in model_kinds:
        raise CheckpointError(f"{path}: not a {' or '.join(model_kinds)} {CHECKPOINT_FORMAT}")
    if data.get("format_version") != FORMAT_VERSION:
        raise CheckpointError(f"{path}: checkpoint version {data.get('format_version')} is not {FORMAT_VERSION}")
    problem = meta_checksum_problem(data)
    if problem:
        raise CheckpointError(f"{path}: {problem}")
    try:
        training = data.get("training_data")
        return WeightsMeta(
            model_kind=str(data["model_kind"]), config=dict(data["config"]), dataset_kind=str(data["dataset_kind"]),
            manifest_hash=str(data["manifest_hash"]), obs_len=int(data["obs_len"]), pred_len=int(data["pred_len"]),
            step=int(data["step"]), metrics={str(k): float(v) for k, v in dict(data.get("metrics", {})).items()},
            training_data=None if training is None else TrainingData.from_dict(training, path),
            weights_sha256=str(data["weights_sha256"]), logpipe_version=str(data.get("logpipe_version", "")),
            created_unix=float(data.get("created_unix", 0.0)))
    except (KeyError, TypeError, ValueError) as exc:
        raise CheckpointError(f"{path}: malformed checkpoint metadata: {exc}") from None


def load_weights(folder: Path, weights_sha256: str) -> dict[str, torch.Tensor]:
    """The weights of ``folder``, checked against the sha256 its ``meta.json`` names and for finite values (every
    family's loader: safetensors only, never a pickle).

    Raises:
        CheckpointError: missing, another sha256, unreadable or not finite.
    """
    import torch
    from safetensors import SafetensorError
    from safetensors.torch import load_file

    weights = folder / WEIGHTS
    if not weights.is_file() or sha256_file(weights) != weights_sha256:
        raise CheckpointError(f"{weights}: missing or does not match the sha256 in meta.json")
    try:
        state = load_file(str(weights))
    except (SafetensorError, OSError) as exc:
        raise CheckpointError(f"{weights}: unreadable weights: {exc}") from None
    bad = sorted(k for k, v in state.items() if v.is_floating_point() and not bool(torch.isfinite(v).all()))
    if bad:
        raise CheckpointError(f"{weights}: non-finite values in {bad[:3]}")
    return state


def load_into(module: torch.nn.Module, state: dict[str, torch.Tensor], where: Path) -> None:
    """``module.load_state_dict(state)`` (strict), a mismatch reported as a ``CheckpointError`` naming ``where``."""
    try:
        module.load_state_dict(state)
    except RuntimeError as exc:
        raise CheckpointError(f"{where / WEIGHTS}: weights do not fit the config in meta.json: "
                              f"{str(exc).splitlines()[0]}") from None
