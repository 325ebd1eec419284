"""The score report folder ``logpipe score`` writes: ``report.json``, ``report.md`` and PNG plots, committed
as one artifact (``logpipe.artifact``), and its reader."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from logpipe import __version__
from logpipe.artifact import ArtifactWriter, FileEntry, Ownership, output_errors, read_manifest
from logpipe.errors import DatasetError
from logpipe.io import atomic_path, sha256_bytes

REPORT_VERSION = 1
REPORT_ARTIFACT = "score_report"
"""``manifest.json`` ``artifact`` value of a score report folder."""
REPORT_JSON = "report.json"
REPORT_MD = "report.md"


REPORT_OWNED = Ownership([REPORT_JSON, REPORT_MD, "horizon.png", "scenes_*.png"])
"""A report folder's own files: the reports and the plots at its top (never a report nested in it)."""


def write_report_folder(out_dir: Path, outputs: dict[str, bytes], inputs: list[str], truth: str) -> None:
    """Commit ``outputs`` (file name -> bytes) as the report folder's state (``logpipe.artifact``).

    Files whose bytes are already committed are left alone (a rerun over the same inputs writes nothing). A
    committed file about to get other bytes is first dropped from the manifest by a commit of its own, so the
    manifest never names a file whose bytes differ from what it records, whenever a crash comes.

    Raises:
        DatasetError: ``out_dir`` holds another artifact (a dataset, a prediction run).
        OutputError: the disk is full, read-only or not writable; the folder keeps its committed state.
    """
    _refuse_other_artifact(out_dir)
    new: dict[str, FileEntry] = {name: {"bytes": len(data), "sha256": sha256_bytes(data)}
                                 for name, data in outputs.items()}

    def manifest(files: dict[str, FileEntry]) -> dict[str, Any]:
        return {"artifact": REPORT_ARTIFACT, "report_version": REPORT_VERSION, "logpipe_version": __version__,
                "inputs": inputs, "truth": truth, "files": files}

    with output_errors(), ArtifactWriter(out_dir, REPORT_OWNED, REPORT_ARTIFACT) as writer:
        _refuse_other_artifact(out_dir)
        old: dict[str, FileEntry] = dict((writer.manifest or {}).get("files", {}))
        changed = [name for name in outputs if old.get(name) != new[name]]
        if writer.manifest is not None and any(name in old for name in changed):
            writer.commit(manifest({k: v for k, v in old.items() if k not in changed}))
        for name in changed:
            with atomic_path(out_dir / name) as tmp:
                tmp.write_bytes(outputs[name])
        if not writer.is_committed(manifest(new)):
            writer.commit(manifest(new))


def _refuse_other_artifact(out_dir: Path) -> None:
    existing = read_manifest(out_dir, required=False) if out_dir.is_dir() else None
    if existing is not None and existing.get("artifact") != REPORT_ARTIFACT:
        raise DatasetError(f"{out_dir}: holds another logpipe artifact (a {existing.get('artifact') or 'dataset'}), "
                         "not a score report; choose another --out")




def read_report(out_dir: Path) -> dict[str, Any]:
    """``report.json`` of a committed report folder (checked against its manifest's size).

    Raises:
        DatasetError: not a committed score report, or its ``report.json`` was changed.
    """
    manifest = read_manifest(Path(out_dir))
    assert manifest is not None
    if manifest.get("artifact") != REPORT_ARTIFACT:
        raise DatasetError(f"{out_dir}: not a score report (a {manifest.get('artifact') or 'dataset'})")
    entry = manifest["files"].get(REPORT_JSON)
    data = (Path(out_dir) / REPORT_JSON).read_bytes()
    if entry is None or sha256_bytes(data) != entry["sha256"]:
        raise DatasetError(f"{Path(out_dir) / REPORT_JSON}: differs from its manifest; `logpipe verify` says more")
    report: dict[str, Any] = json.loads(data)
    return report
