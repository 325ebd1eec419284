"""What every checkpoint's ``meta.json`` shares, whatever the family: the format name, the errors, the dataset kinds
a checkpoint fits (``combined_kind``, ``kind_accepts``), what it was trained on (``TrainingData``), the inference
settings chosen on validation (``InferenceSettings``, ``logpipe predict``'s defaults), the checksum that catches an
edited ``meta.json`` (``stamped_meta``, ``meta_checksum_problem``) and a readable diff of two configs.
"""

from __future__ import annotations

import hashlib
from collections.abc import Sequence
from dataclasses import dataclass
from importlib import metadata
from pathlib import Path
from typing import Any

from logpipe.dataset.reader import Dataset
from logpipe.errors import LogpipeError
from logpipe.storage.artifact import manifest_checksum

CHECKPOINT_FORMAT = "logpipe-model-checkpoint"


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


def config_differences(expected: dict[str, Any], found: dict[str, Any], prefix: str = "") -> list[str]:
    out = []
    for key in sorted(set(expected) | set(found)):
        a, b = expected.get(key), found.get(key)
        if isinstance(a, dict) and isinstance(b, dict):
            out += config_differences(a, b, f"{prefix}{key}.")
        elif a != b:
            out.append(f"{prefix}{key}: expected {a!r}, checkpoint has {b!r}")
    return out
