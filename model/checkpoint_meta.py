"""A checkpoint's ``meta.json``: what the weights are (format, the full TrainConfig, normalisation), what they were
trained on (dataset kind, manifest hash, ``TrainingData``) and the inference settings chosen on validation
(``InferenceSettings``, ``logpipe predict``'s defaults); parsing it (``read_meta``), comparing it with what a
caller expects (``check_meta``) and amending the entries that may change after training (``amend_meta``).
``checkpoints`` writes and loads the folder around it.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
from collections.abc import Sequence
from dataclasses import dataclass
from importlib import metadata
from pathlib import Path
from typing import Any

from logpipe.dataset.reader import Dataset
from logpipe.errors import LogpipeError
from logpipe.storage.artifact import manifest_checksum
from logpipe.storage.folder_lock import FolderLock
from logpipe.storage.io import atomic_path, read_json

from .config import (
    ConfigError,
    ModelConfig,
    TrainConfig,
    config_to_dict,
    train_config_from_dict,
)

CHECKPOINT_FORMAT = "logpipe-model-checkpoint"
FORMAT_VERSION = 1
MODEL_KIND = "zhu2020"


class CheckpointError(LogpipeError):
    """A checkpoint folder is missing, corrupt or of another format."""


class CheckpointMismatchError(CheckpointError):
    """A checkpoint does not match what the caller expects (config, dataset kind, manifest)."""


KIND_SEPARATOR = "+"
"""Joins the formats of a checkpoint trained on datasets of several formats (``argoverse1+argoverse2``)."""


def combined_kind(kinds: Sequence[str]) -> str:
    """``dataset_kind`` of a checkpoint trained on datasets of these formats: the format itself when they share
    one (so a single dataset's checkpoint is as before), else the distinct formats sorted and joined by ``+``."""
    return KIND_SEPARATOR.join(sorted(set(kinds)))


def kind_accepts(checkpoint_kind: str, dataset_kind: str) -> bool:
    """Whether a checkpoint of ``checkpoint_kind`` fits data of ``dataset_kind``: the same kind, or one of the
    formats a several-format checkpoint was trained on (and nothing else)."""
    return dataset_kind == checkpoint_kind or dataset_kind in checkpoint_kind.split(KIND_SEPARATOR)


def combined_manifest_hash(hashes: Sequence[str]) -> str:
    """``manifest_hash`` of a run over datasets whose manifests have these sha256 digests, in the order given:
    the digest itself for one dataset, else the sha256 of the digests one per line."""
    if len(hashes) == 1:
        return hashes[0]
    return hashlib.sha256("\n".join(hashes).encode("ascii")).hexdigest()


def logpipe_version() -> str:
    """``logpipe.__version__`` if present, else the installed distribution's version, else "unknown"."""
    import logpipe

    version = getattr(logpipe, "__version__", None)
    if isinstance(version, str):
        return version
    try:
        return metadata.version("logpipe")
    except metadata.PackageNotFoundError:
        return "unknown"


@dataclass(frozen=True)
class InferenceSettings:
    """Inference settings chosen on validation data for a checkpoint: ``logpipe predict``'s defaults for it.

    Attributes:
        num_modes: K the settings were chosen at (predict's default ``--modes``).
        noise_scale: standard deviation of the noise z (1 = as trained, eq. 21).
        constant_velocity_modes: modes held to constant velocity (None = the training config's).
        context_max_neighbours: at most this many neighbours in each target's context (None = all within
            ``ModelConfig.context_radius_m``).
        chosen_on: how they were chosen (split, criterion, grid, seed), shown in predict's summary.
    """

    num_modes: int
    noise_scale: float = 1.0
    constant_velocity_modes: int | None = None
    context_max_neighbours: int | None = None
    chosen_on: str = ""

    @classmethod
    def from_dict(cls, data: Any, where: Path) -> InferenceSettings:
        """Parse the ``inference`` block of ``meta.json``.

        Raises:
            CheckpointError: not an object, or a value of the wrong type or range.
        """
        if not isinstance(data, dict):
            raise CheckpointError(f"{where}: 'inference' is not a JSON object")
        try:
            settings = cls(num_modes=int(data["num_modes"]), noise_scale=float(data.get("noise_scale", 1.0)),
                           constant_velocity_modes=_optional_int(data.get("constant_velocity_modes")),
                           context_max_neighbours=_optional_int(data.get("context_max_neighbours")),
                           chosen_on=str(data.get("chosen_on", "")))
        except (KeyError, TypeError, ValueError) as exc:
            raise CheckpointError(f"{where}: malformed 'inference' block: {exc}") from None
        cv, cap = settings.constant_velocity_modes, settings.context_max_neighbours
        bad_cv = cv is not None and not 0 <= cv <= settings.num_modes
        if settings.num_modes < 1 or not settings.noise_scale > 0 or bad_cv or (cap is not None and cap < 0):
            raise CheckpointError(f"{where}: 'inference' values out of range: {data}")
        return settings


@dataclass(frozen=True)
class TrainingData:
    """What a checkpoint was trained and validated on, so predicting over it can be flagged.

    Attributes:
        train_split: the dataset split trained on (``zara1/train``, ``hash/train``...).
        val_split: the split validated (and early-stopped) on, if any.
        train_sources: sha256 of each recording file the training logs came from (content, not names, so a
            re-ingested or renamed copy is still recognised).
        val_sources: the same for the validation logs.
    """

    train_split: str
    val_split: str | None
    train_sources: tuple[str, ...]
    val_sources: tuple[str, ...]

    @classmethod
    def of(cls, dataset: Dataset, train_split: str, val_split: str | None) -> TrainingData:
        """The recordings behind the logs of ``train_split`` and ``val_split`` of ``dataset``."""
        train_logs = dataset.logs_in_split(train_split)
        val_logs = dataset.logs_in_split(val_split) if val_split else []
        return cls.of_logs([(dataset, train_logs, val_logs)], train_split, val_split)

    @classmethod
    def of_logs(cls, parts: Sequence[tuple[Dataset, Sequence[str], Sequence[str]]], train_split: str,
                val_split: str | None) -> TrainingData:
        """The recordings behind ``(dataset, training log ids, validation log ids)`` of each dataset trained on
        (their union), with the splits as given."""
        train: set[str] = set()
        val: set[str] = set()
        for dataset, train_logs, val_logs in parts:
            logs = dataset.logs()
            source = dict(zip(logs.column("log_id").to_pylist(), logs.column("source_sha256").to_pylist(),
                              strict=True))
            train |= {str(source[log]) for log in train_logs}
            val |= {str(source[log]) for log in val_logs}
        return cls(train_split, val_split, tuple(sorted(train)), tuple(sorted(val)))

    def to_dict(self) -> dict[str, Any]:
        """The ``training_data`` block of ``meta.json``."""
        return {"train_split": self.train_split, "val_split": self.val_split,
                "train_sources": list(self.train_sources), "val_sources": list(self.val_sources)}

    @classmethod
    def from_dict(cls, data: Any, where: Path) -> TrainingData:
        """Parse the ``training_data`` block of ``meta.json``.

        Raises:
            CheckpointError: not an object, or a field of the wrong type.
        """
        try:
            val = data["val_split"]
            out = cls(str(data["train_split"]), None if val is None else str(val),
                      tuple(str(s) for s in data["train_sources"]), tuple(str(s) for s in data["val_sources"]))
        except (KeyError, TypeError) as exc:
            raise CheckpointError(f"{where}: malformed 'training_data' block: {exc}") from None
        return out


def _optional_int(value: Any) -> int | None:
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, int):
        raise TypeError(f"expected an integer or null, got {value!r}")
    return value


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


def stamped_meta(body: dict[str, Any]) -> dict[str, Any]:
    """``body`` with its ``checksum``: the weights' sha256 alone left the rest of ``meta.json`` (the config
    that rebuilds the network, the inference settings predict uses) open to an unnoticed edit."""
    body = {k: v for k, v in body.items() if k != "checksum"}
    return {**body, "checksum": manifest_checksum(body)}


def meta_checksum_problem(data: dict[str, Any]) -> str | None:
    """Why a parsed ``meta.json`` fails its ``checksum``, or None (also for one written before checksums)."""
    if "checksum" in data and data["checksum"] != manifest_checksum(data):
        return "content differs from its checksum (edited or damaged); re-create it with `logpipe train`"
    return None


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


def config_differences(expected: dict[str, Any], found: dict[str, Any], prefix: str = "") -> list[str]:
    out = []
    for key in sorted(set(expected) | set(found)):
        a, b = expected.get(key), found.get(key)
        if isinstance(a, dict) and isinstance(b, dict):
            out += config_differences(a, b, f"{prefix}{key}.")
        elif a != b:
            out.append(f"{prefix}{key}: expected {a!r}, checkpoint has {b!r}")
    return out


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
