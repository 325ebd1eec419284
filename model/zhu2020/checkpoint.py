"""Checkpoints: a folder with weights (safetensors) and JSON metadata; never a pickle.

Layout of a checkpoint folder::

    weights.safetensors   model parameters and buffers
    meta.json             format, full TrainConfig, normalisation, dataset kind, dataset manifest hash,
                          logpipe version, step, metrics, sha256 of weights.safetensors; optionally the data it
                          was trained and validated on (``training_data``) and the inference settings chosen on
                          validation (``inference``, ``logpipe predict``'s defaults for it)
    optimizer.safetensors (resumable "last" checkpoints only) Adam moments + torch RNG state
    averaged.safetensors  (resumable checkpoints of a run with ``ema_decay``) the weight average
    train_state.json      (resumable only) optimiser param groups, loop counters, numpy RNG state

``meta.json`` is written last and names the weights' sha256, so a folder interrupted mid-write is
detected on load instead of silently mixing old and new files.

This module writes and loads the folder (``save_checkpoint``, ``load_checkpoint``, the resumable state) and
warm-starts a wider network from one (``warm_start``); ``meta`` owns what ``meta.json`` holds.
"""

from __future__ import annotations

import dataclasses
import json
import os
import shutil
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, NotRequired, TypedDict

import torch
from safetensors.torch import load_file, save_file

from logpipe.storage.folder_swap import recover_folder, replace_folder, staging_folder_for
from logpipe.storage.io import sha256_file

from ..checkpoint.format import CheckpointError, TrainingData, config_differences, logpipe_version
from .config import ModelConfig, TrainConfig, config_to_dict
from .meta import CheckpointMeta, check_meta, read_meta
from .network import TrajectoryNet


class TrainState(TypedDict):
    """``train_state.json`` of a resumable checkpoint beside the optimiser's param groups: where the run is."""

    step: int
    epoch: int
    pos_in_epoch: int  # scenes of the epoch already drawn
    best_ade: float  # metres (inf before the first validation)
    best_fde: float  # metres
    best_step: int
    bad_evals: int  # validations since the best one
    elapsed_s: NotRequired[float]  # wall seconds of the run so far; absent in older checkpoints


@dataclass
class LoadedCheckpoint:
    """A loaded checkpoint: the network (eval mode) and its metadata."""

    net: TrajectoryNet
    meta: CheckpointMeta
    path: Path



def _atomic_json(path: Path, data: dict[str, Any]) -> None:
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(data, indent=2, sort_keys=True) + "\n", encoding="utf-8")
    os.replace(tmp, path)


AVERAGED_FILE = "averaged.safetensors"


def _atomic_tensors(path: Path, tensors: dict[str, torch.Tensor]) -> None:
    tmp = path.with_name(path.name + ".tmp")
    save_file({k: v.detach().cpu().contiguous().clone() for k, v in tensors.items()}, str(tmp))
    os.replace(tmp, path)


def save_checkpoint(  # noqa: PLR0913  keyword-only optional parts, each stored as given
    folder: Path,
    net: TrajectoryNet,
    config: TrainConfig,
    *,
    dataset_kind: str,
    manifest_hash: str,
    step: int,
    metrics: dict[str, float] | None = None,
    optimizer: torch.optim.Optimizer | None = None,
    train_state: TrainState | None = None,
    averaged: dict[str, torch.Tensor] | None = None,
    training_data: TrainingData | None = None,
) -> Path:
    """Write a checkpoint folder (replacing one that is there); with ``optimizer`` it is resumable, and
    ``averaged`` (the state dict of the run's weight average, ``TrainConfig.ema_decay``) goes to
    ``averaged.safetensors``.

    The files are only valid together (``meta.json`` names the weights' sha256), so the whole folder is built
    beside the old one and swapped in at once: a crash leaves the previous checkpoint or the new one.
    """
    recover_folder(folder)
    staging = staging_folder_for(folder)
    try:
        _write_checkpoint_files(staging, net, CheckpointMeta(
            config=config, dataset_kind=dataset_kind, manifest_hash=manifest_hash, logpipe_version=logpipe_version(),
            step=step, metrics=dict(metrics or {}), weights_sha256="", created_unix=time.time(),
            training_data=training_data),
            optimizer, train_state, averaged)
        replace_folder(staging, folder)
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    return folder


def _write_checkpoint_files(folder: Path, net: TrajectoryNet, meta: CheckpointMeta,
                            optimizer: torch.optim.Optimizer | None, train_state: TrainState | None,
                            averaged: dict[str, torch.Tensor] | None) -> None:
    """The files of a checkpoint into ``folder``; ``meta`` gets the weights' sha256 once they are written."""
    weights = folder / "weights.safetensors"
    _atomic_tensors(weights, dict(net.state_dict()))
    if averaged is not None:
        _atomic_tensors(folder / AVERAGED_FILE, averaged)
    if optimizer is not None:
        state = optimizer.state_dict()
        tensors = {"rng.torch": torch.get_rng_state()}
        for idx, per_param in state["state"].items():
            for key, value in per_param.items():
                tensors[f"state.{idx}.{key}"] = torch.as_tensor(value)
        _atomic_tensors(folder / "optimizer.safetensors", tensors)
        _atomic_json(folder / "train_state.json", {"param_groups": state["param_groups"], **(train_state or {})})
    meta = dataclasses.replace(meta, weights_sha256=sha256_file(weights))
    _atomic_json(folder / "meta.json", meta.to_dict())


def _verified_weights(folder: Path, meta: CheckpointMeta) -> dict[str, torch.Tensor]:
    """The tensors of ``folder/weights.safetensors`` once its sha256 matches the one ``meta.json`` names."""
    weights = folder / "weights.safetensors"
    if not weights.is_file() or sha256_file(weights) != meta.weights_sha256:
        raise CheckpointError(f"{weights}: missing or does not match the sha256 in meta.json")
    try:
        tensors = load_file(str(weights))
    except Exception as exc:  # safetensors raises its own header/format errors: one line naming the file
        first = str(exc).strip().splitlines()[0][:200] if str(exc).strip() else type(exc).__name__
        raise CheckpointError(f"{weights}: not a readable safetensors file: {first}") from None
    # One NaN weight makes every forecast NaN, and predict then drops every row (rows: 0, exit 0).
    for name, tensor in tensors.items():
        if tensor.is_floating_point() and not bool(torch.isfinite(tensor).all()):
            raise CheckpointError(f"{weights}: tensor {name!r} holds NaN or infinite values; the checkpoint is "
                                  "damaged (retrain or restore it)")
    return tensors


def load_checkpoint(
    path: Path,
    *,
    expect_kind: str | None = None,
    expect_config: ModelConfig | TrainConfig | None = None,
    expect_manifest_hash: str | None = None,
) -> LoadedCheckpoint:
    """Load a checkpoint folder (or its ``meta.json``) into a ``TrajectoryNet`` in eval mode.

    Raises:
        CheckpointError: missing/corrupt files, weights that do not fit the stored config.
        CheckpointMismatchError: dataset kind, manifest hash or config differ from the expected ones.
    """
    folder = path.parent if path.name == "meta.json" else path
    recover_folder(folder)
    meta = read_meta(folder)
    check_meta(
        meta, folder, expect_kind=expect_kind, expect_config=expect_config, expect_manifest_hash=expect_manifest_hash
    )
    tensors = _verified_weights(folder, meta)
    net = TrajectoryNet(meta.config.model, load_backbone=False)
    try:
        net.load_state_dict(tensors, strict=True)
    except RuntimeError as exc:
        raise CheckpointError(f"{folder / 'weights.safetensors'}: weights do not fit the stored config: {exc}") from exc
    return LoadedCheckpoint(net.eval(), meta, folder)


def load_averaged(folder: Path) -> dict[str, torch.Tensor]:
    """The weight average a resumable checkpoint of an ``ema_decay`` run keeps beside its raw weights."""
    path = folder / AVERAGED_FILE
    try:
        return load_file(str(path))
    except (OSError, ValueError, RuntimeError) as exc:
        raise CheckpointError(f"{path}: cannot read the run's weight average: {exc}") from exc


def load_training_state(folder: Path, optimizer: torch.optim.Optimizer) -> TrainState:
    """Restore Adam moments and the torch RNG from a resumable checkpoint; returns ``train_state.json``."""
    try:
        tensors = load_file(str(folder / "optimizer.safetensors"))
        extra = json.loads((folder / "train_state.json").read_text(encoding="utf-8"))
    except (OSError, ValueError) as exc:
        raise CheckpointError(f"{folder}: not a resumable checkpoint: {exc}") from exc
    state: dict[int, dict[str, torch.Tensor]] = {}
    for name, value in tensors.items():
        if name.startswith("state."):
            _, idx, key = name.split(".", 2)
            state.setdefault(int(idx), {})[key] = value
    optimizer.load_state_dict({"state": state, "param_groups": extra.pop("param_groups")})
    torch.set_rng_state(tensors["rng.torch"])
    loop: TrainState = extra  # the rest of train_state.json, as the training loop wrote it
    return loop


# LSTM input weights whose input is a concatenation led by the displacement embedding (eqs. 16 and 18):
# a checkpoint without the features (Noise-LSTM) fills the leading columns.
_WIDENABLE = ("encoder.weight_ih", "decoder.weight_ih")


@dataclass(frozen=True)
class WarmStart:
    """What ``warm_start`` did.

    Attributes:
        source: the checkpoint folder read.
        weights_sha256: sha256 of its weights file.
        copied: parameters copied whole.
        widened: LSTM input weights whose leading columns were copied and the columns of the extra inputs
            (interaction and environment features) zeroed.
        kept: parameters the checkpoint does not have (they keep their fresh initialisation).
        differences: the model config keys on which the checkpoint differs from ``net`` (``features`` aside):
            copied weights may mean something else there (another output form, speed unit, ...).
    """

    source: Path
    weights_sha256: str
    copied: tuple[str, ...]
    widened: tuple[str, ...]
    kept: tuple[str, ...]
    differences: tuple[str, ...]

    def to_dict(self) -> dict[str, Any]:
        return {"source": str(self.source), "weights_sha256": self.weights_sha256, "copied": len(self.copied),
                "widened": list(self.widened), "kept": list(self.kept), "differences": list(self.differences)}


def warm_start(net: TrajectoryNet, folder: Path) -> WarmStart:
    """Initialise ``net`` from a checkpoint of a network with fewer features (e.g. Noise-LSTM into the full model).

    Every parameter the checkpoint has is copied; the encoder and decoder input weights get the checkpoint's
    columns first and zeros for the extra feature inputs, so the warm-started net computes exactly what the
    checkpoint did until training moves those zeros. Parameters it lacks (AIN, environment net, attention)
    keep their initialisation.

    Raises:
        CheckpointError: missing or corrupt files, a parameter of ``net`` that the checkpoint has with a shape
            that cannot be fitted, or a checkpoint parameter ``net`` lacks.
    """
    meta = read_meta(folder)
    source = _verified_weights(folder, meta)
    target = net.state_dict()
    unknown = sorted(set(source) - set(target))
    if unknown:
        raise CheckpointError(f"{folder}: parameters the network does not have: {unknown}")
    copied: list[str] = []
    widened: list[str] = []
    with torch.no_grad():
        for name, value in source.items():
            slot = target[name]
            if value.shape == slot.shape:
                slot.copy_(value)
                copied.append(name)
            elif (name in _WIDENABLE and value.dim() == 2 and value.shape[0] == slot.shape[0]
                  and value.shape[1] < slot.shape[1]):
                slot.zero_()
                slot[:, : value.shape[1]] = value
                widened.append(name)
            else:
                raise CheckpointError(f"{folder}: parameter {name} has shape {tuple(value.shape)}, the network "
                                      f"{tuple(slot.shape)}")
    kept = tuple(sorted(set(target) - set(source)))
    mine, theirs = config_to_dict(net.config), config_to_dict(meta.config.model)
    mine.pop("features")
    theirs.pop("features")
    differences = tuple(config_differences(mine, theirs, "model."))
    return WarmStart(folder, meta.weights_sha256, tuple(copied), tuple(widened), kept, differences)
