"""Where a log's original recording is, for copying it into a prediction MCAP: the bag or MCAP file it was
ingested from (ROS/MCAP logs, found under the input roots and checked by sha256), else the MCAP ingest wrote;
and the world frame its positions are in.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from logpipe.dataset.reader import Dataset
from logpipe.errors import DatasetError
from logpipe.mcap.merge import Source
from logpipe.mcap.tracks import WORLD_FRAME
from logpipe.storage.io import sha256_tree

ORIGINAL_FORMATS = ("rosbag", "mcap")
"""Formats whose original file is copied into the output MCAP; other logs use the MCAP ingest wrote."""


def find_original(row: dict[str, Any], inputs: Sequence[Path], dataset: Dataset) -> Source:
    """The recording a log (its logs-table ``row``) came from: the bag/MCAP under one of ``inputs`` (checked by
    sha256) for ROS/MCAP logs, else the MCAP ingest wrote.

    Raises:
        DatasetError: not found (naming where it looked), or the file there has other contents.
    """
    log_id, rel = str(row["log_id"]), str(row["source_file"])
    if row["source_format"] not in ORIGINAL_FORMATS:
        path = dataset.mcap_path(log_id)
        if not path.is_file():
            raise DatasetError(f"{path}: ingest wrote no MCAP for log {log_id!r} (ingested with --no-mcap?); "
                               "re-ingest with MCAP or predict with --no-mcap")
        return Source((path,), "mcap", str(path))
    if not inputs:
        raise DatasetError(f"log {log_id!r} comes from {rel} ({row['source_format']}): give --inputs ROOT (the "
                           "file or folder it was ingested from) so its original channels can be copied")
    for root in inputs:
        candidate = root if root.name == rel and root.exists() else root / rel
        if candidate.exists():
            if sha256_tree(candidate) != row["source_sha256"]:
                raise DatasetError(f"{candidate}: contents differ from the ingested {rel} (sha256 mismatch)")
            return _source_of(candidate, rel)
    raise DatasetError(f"original of log {log_id!r} ({rel}) not found under --inputs {[str(p) for p in inputs]}")


def _source_of(path: Path, name: str) -> Source:
    """MCAP files (and ROS2 bags stored as MCAP) are copied record by record; other bags go through rosbags."""
    if path.is_file():
        return Source((path,), "mcap" if path.suffix == ".mcap" else "rosbag", name)
    from logpipe.formats.rosbag import storage_paths

    parts = storage_paths(path)
    if parts and all(p.suffix == ".mcap" for p in parts):
        return Source(tuple(parts), "mcap", name)
    return Source((path,) if (path / "metadata.yaml").exists() else tuple(parts), "rosbag", name)


def world_frame(row: dict[str, Any]) -> str:
    """The frame a log's x/y are in (its logs-table ``row``): a ROS log's world frame (``map``, ``odom``) so
    predictions sit in its tf tree; ``world`` (the frame ingest's MCAP uses) otherwise."""
    if row["source_format"] in ORIGINAL_FORMATS:
        attrs = json.loads(row["attributes"] or "{}")
        frame = attrs.get("world_frame")
        if isinstance(frame, str) and frame:
            return frame
    return WORLD_FRAME
