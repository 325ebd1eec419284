"""A checkpoint folder of a family whose whole state is one set of weights and a plain config (the social
baselines, ``model.social_lstm`` and ``model.social_gan``): ``weights.safetensors`` and ``meta.json``, never a
pickle, the folder replaced whole (``logpipe.storage.folder_swap``) so a crash leaves the old folder or the new one.

``meta.json`` carries ``format``, ``format_version``, ``model_kind``, the family's ``config`` table, the dataset
kind, manifest hash, window lengths, what it was trained on (``TrainingData``), validation metrics, the weights'
sha256 and the ``checksum`` of all the rest (``stamped_meta``). Weights load only when their sha256 is that one, as
safetensors (no code runs), and only finite ones.

A resumable ``last/`` also holds ``train_state.pt`` (optimiser states, counters, random states: ``model.training.
window_loop``), named by its sha256 in ``meta.json`` and read by ``torch.load(weights_only=True)`` (tensors and
plain containers only, never arbitrary objects), only when that sha256 matches.
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
TRAIN_STATE = "train_state.pt"
RESUMABLE_KEYS = ("steps", "time_budget_s", "patience")
"""Config keys a resumed run may change (how long it goes on); any other change would not continue the run."""
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
    train_state_sha256: str = ""

    def to_dict(self) -> dict[str, Any]:
        """The JSON document with its checksum."""
        body = {"format": CHECKPOINT_FORMAT, "format_version": FORMAT_VERSION, "model_kind": self.model_kind,
                "config": self.config, "dataset_kind": self.dataset_kind, "manifest_hash": self.manifest_hash,
                "obs_len": self.obs_len, "pred_len": self.pred_len, "step": self.step, "metrics": self.metrics,
                "weights_sha256": self.weights_sha256, "logpipe_version": self.logpipe_version,
                "created_unix": self.created_unix}
        if self.training_data is not None:
            body["training_data"] = self.training_data.to_dict()
        if self.train_state_sha256:
            body["train_state_sha256"] = self.train_state_sha256
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


def save_weights_folder(folder: Path, state: dict[str, torch.Tensor], meta: FolderMeta,
                        train_state: bytes | None = None) -> Path:
    """Write ``state`` and ``meta`` into ``folder`` (replacing one that is there), ``meta.json`` last, naming the
    weights' sha256; the folder is swapped in whole, so a crash leaves the old folder or the new one. With
    ``train_state`` (a ``WeightsMeta`` only) the folder is resumable: ``train_state.pt`` beside, its sha256 named."""
    from safetensors.torch import save_file

    recover_folder(folder)
    staging = staging_folder_for(folder)
    try:
        staging.mkdir(parents=True, exist_ok=True)
        if train_state is not None and isinstance(meta, WeightsMeta):
            (staging / TRAIN_STATE).write_bytes(train_state)
            meta.train_state_sha256 = sha256_file(staging / TRAIN_STATE)
        elif isinstance(meta, WeightsMeta):
            meta.train_state_sha256 = ""
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
            created_unix=float(data.get("created_unix", 0.0)),
            train_state_sha256=str(data.get("train_state_sha256", "")))
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


def load_resumable(folder: Path, expected: WeightsMeta) -> tuple[dict[str, torch.Tensor], dict[str, Any]]:
    """The weights and training state of a resumable ``folder`` (a run's ``last/``) that continues the run
    ``expected`` describes: the same kind, dataset and config but for ``RESUMABLE_KEYS``.

    Raises:
        CheckpointError: not a checkpoint of that kind, another dataset or config, no (or a damaged) training
            state, or unreadable weights.
    """
    import io
    import pickle

    import torch

    meta = read_weights_meta(folder, (expected.model_kind,))
    if meta.manifest_hash != expected.manifest_hash:
        raise CheckpointError(f"{folder / META}: cannot resume: trained on another dataset (manifest hash)")
    changed = sorted(k for k in {*meta.config, *expected.config} - set(RESUMABLE_KEYS)
                     if meta.config.get(k) != expected.config.get(k))
    if changed:
        key = changed[0]
        raise CheckpointError(f"{folder / META}: cannot resume: config {key} is {meta.config.get(key)!r}, this run "
                              f"gives {expected.config.get(key)!r} (only {', '.join(RESUMABLE_KEYS)} may change)")
    path = folder / TRAIN_STATE
    if not meta.train_state_sha256 or not path.is_file() or sha256_file(path) != meta.train_state_sha256:
        raise CheckpointError(f"{path}: cannot resume: missing or does not match the sha256 in meta.json")
    try:
        state = torch.load(io.BytesIO(path.read_bytes()), weights_only=True)
    except (pickle.UnpicklingError, RuntimeError, ValueError, EOFError) as exc:  # weights_only: no other objects
        raise CheckpointError(f"{path}: unreadable training state: {str(exc).splitlines()[0]}") from None
    if not isinstance(state, dict):
        raise CheckpointError(f"{path}: unreadable training state: not a table")
    return load_weights(folder, meta.weights_sha256), state
