"""``logpipe verify``: check artifact folders against their manifests, and optionally remove leftovers.

Which files a folder owns (and so which unnamed files are leftovers) depends on its kind, read from the
manifest: a dataset owns its table and MCAP folders, any other artifact everything but nested artifacts.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from logpipe.artifact import MANIFEST, ArtifactWriter, Owned, verify_folder
from logpipe.dataset import dataset_owned
from logpipe.errors import DatasetError


def _owned(manifest_path: Path) -> Owned:
    from logpipe.artifact import read_manifest

    manifest = read_manifest(manifest_path.parent, required=False) or {}
    if "format" in manifest and "shards" in manifest and "tables" in manifest:
        return dataset_owned
    return lambda rel: True


def artifact_folders(root: Path) -> list[Path]:
    """``root`` and every artifact folder nested in it (a dataset's raster runs), outer first."""
    root = Path(root)
    if not (root / MANIFEST).is_file():
        raise DatasetError(f"{root}: no {MANIFEST}; not a logpipe output folder")
    nested = sorted(p.parent for p in root.glob(f"*/*/{MANIFEST}") if p.parent.parent.name == "rasters")
    return [root, *nested]


def verify_tree(roots: list[Path], *, repair: bool = False, deep: bool = True) -> dict[str, Any]:
    """Verify each folder (and its nested artifacts); with ``repair``, remove leftovers under each writer lock.

    Returns:
        ``{"folders", "files_checked", "problems": [line...], "leftovers": [path...]}``.
    """
    from logpipe.artifact import read_manifest

    folders = [f for root in roots for f in artifact_folders(root)]
    problems: list[str] = []
    leftovers: list[str] = []
    checked = 0
    for folder in folders:
        owned = _owned(folder / MANIFEST)
        found, left = verify_folder(folder, owned, deep=deep)
        checked += len((read_manifest(folder, required=False) or {}).get("files", {}))
        problems += [p.line() for p in found]
        leftovers += [str(folder / rel) for rel in left]
        if repair and left:
            with ArtifactWriter(folder, owned):
                pass  # entering the writer removes what no commit names
    return {"folders": [str(f) for f in folders], "files_checked": checked, "problems": problems,
            "leftovers": leftovers}
