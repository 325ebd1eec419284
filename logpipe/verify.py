"""``logpipe verify``: check artifact folders against their manifests, and optionally remove leftovers.

Which files a folder owns (and so which unnamed files are leftovers) is recorded in its manifest (``owns``);
datasets from before that are recognised by their keys.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from logpipe.dataset.reader import DATASET_ARTIFACT, DATASET_LEGACY_KEYS, DATASET_OWNED
from logpipe.errors import DatasetError
from logpipe.prediction.runs import RUN_ARTIFACT, RUN_OWNED
from logpipe.raster.runs import RASTER_ARTIFACT
from logpipe.scoring.reports import REPORT_ARTIFACT, REPORT_OWNED
from logpipe.storage.artifact import (
    EVERYTHING,
    MANIFEST,
    ArtifactWriter,
    Ownership,
    foreign_manifest,
    manifest_checksum,
    read_manifest,
    verify_folder,
)

WRITERS_OWN = {DATASET_ARTIFACT: DATASET_OWNED, RASTER_ARTIFACT: EVERYTHING, RUN_ARTIFACT: RUN_OWNED,
               REPORT_ARTIFACT: REPORT_OWNED}
"""What each kind's writer owns, from the writers' code: ``--repair`` removes only such files, whatever a
manifest's own ``owns`` claims (a foreign or edited manifest must never widen what logpipe deletes)."""


def _kind_and_owned(folder: Path) -> tuple[str, Ownership | None, int]:
    """The artifact kind, the ownership of its writer (None: no logpipe writer's manifest, never repaired) and
    number of files a folder's manifest records (older datasets: recognised by their keys; a damaged manifest
    counts no file, ``verify_folder`` reports it)."""
    try:
        manifest = read_manifest(folder, required=False)
    except DatasetError:  # damaged: ``verify_folder`` reports it and finds no leftovers, so nothing is removed
        return "unknown", EVERYTHING, 0
    if manifest is None or foreign_manifest(manifest, DATASET_LEGACY_KEYS):
        return "unknown", None, 0
    kind = str(manifest.get("artifact", DATASET_ARTIFACT))
    files = manifest.get("files")
    return kind, WRITERS_OWN.get(kind), len(files) if isinstance(files, dict) else 0


CHECKPOINT_META = "meta.json"
"""A checkpoint folder's metadata (``logpipe.model.zhu2020.checkpoint``): it names the weights' sha256."""


def _verify_checkpoint(folder: Path) -> list[str]:
    """Problems of a checkpoint folder: unreadable metadata, or weights whose sha256 is not the recorded one."""
    from logpipe.storage.io import sha256_file
    from logpipe.storage.regular_files import read_json_file

    try:
        meta = read_json_file(folder / CHECKPOINT_META)
        expected = str(meta["weights_sha256"])
    except (OSError, ValueError, KeyError, TypeError) as exc:
        return [f"{folder / CHECKPOINT_META}: unreadable checkpoint metadata ({type(exc).__name__})"]
    if "checksum" in meta and meta["checksum"] != manifest_checksum(meta):  # the config, inference settings...
        return [f"{folder / CHECKPOINT_META}: content differs from its checksum (edited or damaged)"]
    weights = folder / "weights.safetensors"
    if not weights.is_file():
        return [f"{weights}: missing"]
    if sha256_file(weights) != expected:
        return [f"{weights}: sha256 differs from {CHECKPOINT_META} (content changed)"]
    return []


def artifact_folders(root: Path) -> list[Path]:
    """``root`` and every artifact folder nested in it (a dataset's raster runs), outer first."""
    root = Path(root)
    if not (root / MANIFEST).is_file():
        if (root / CHECKPOINT_META).is_file():
            return [root]
        raise DatasetError(f"{root}: no {MANIFEST}; not a logpipe output folder")
    nested = sorted(p.parent for p in root.glob(f"*/*/{MANIFEST}") if p.parent.parent.name == "rasters")
    return [root, *nested]


def verify_tree(roots: list[Path], *, repair: bool = False, deep: bool = True) -> dict[str, Any]:
    """Verify each folder (and its nested artifacts); with ``repair``, remove leftovers under each writer lock.

    Returns:
        ``{"folders", "files_checked", "problems": [line...], "leftovers": [path...]}``.
    """
    folders = [f for root in roots for f in artifact_folders(root)]
    problems: list[str] = []
    leftovers: list[str] = []
    checked = 0
    for folder in folders:
        if not (folder / MANIFEST).is_file():  # a checkpoint
            problems += _verify_checkpoint(folder)
            checked += 1
            continue
        kind, owned, files = _kind_and_owned(folder)
        if owned is None:  # not written by logpipe: nothing in it is logpipe's to judge or to remove
            problems.append(f"{folder / MANIFEST}: not written by logpipe (no known artifact kind); "
                            "verify and --repair leave the folder alone")
            continue
        found, left = verify_folder(folder, owned, deep=deep)
        checked += files
        problems += [p.line() for p in found]
        leftovers += [str(folder / rel) for rel in left]
        if repair and left:
            with ArtifactWriter(folder, owned, kind, DATASET_LEGACY_KEYS if kind == DATASET_ARTIFACT else ()):
                pass  # entering the writer removes what no commit names
    return {"folders": [str(f) for f in folders], "files_checked": checked, "problems": problems,
            "leftovers": leftovers}
