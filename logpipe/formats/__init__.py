"""Input formats: one adapter module per format behind ``FormatAdapter`` (see ``base.py``).

``FORMATS`` lists the CLI names; ``adapter_class`` imports a format's module on first use (the bag, MCAP
and AV2 adapters pull in rosbags, mcap and YAML, ~0.2 s that a pool worker parsing CSVs need not pay);
``detect`` picks the adapter for a path by sniffing.
"""

from __future__ import annotations

import heapq
import importlib
import inspect
import logging
import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from logpipe.errors import LogpipeError
from logpipe.formats.base import FormatAdapter, ParsedLogs

_CLASSES: dict[str, tuple[str, str]] = {  # CLI name -> (module, class)
    "argoverse1": ("logpipe.formats.argoverse1", "Argoverse1Adapter"),
    "ethucy": ("logpipe.formats.ethucy", "EthUcyAdapter"),
    "apolloscape": ("logpipe.formats.apolloscape", "ApolloScapeAdapter"),
    "argoverse2": ("logpipe.formats.av2", "Av2Adapter"),
    "rosbag": ("logpipe.formats.rosbag", "RosbagAdapter"),
    "mcap": ("logpipe.formats.mcapfile", "McapAdapter"),
    "commonroad": ("logpipe.formats.commonroad", "CommonRoadAdapter"),
}
FORMATS: tuple[str, ...] = tuple(_CLASSES)
TEXT_FORMATS = ("argoverse1", "ethucy", "apolloscape")
"""Formats of delimited text (``.csv``/``.txt`` with a header or numeric first line). The other sniffs claim
only other names or magic bytes (``scenario_*.parquet``, ``*.feather``, ``.bag``/``.db3`` magic, files of a
rosbag2 folder, the MCAP magic or ``.mcap``, an ``.xml`` opening ``<commonRoad``), so a file a text format claims is
never theirs."""


def adapter_class(name: str) -> type[FormatAdapter]:
    """The adapter class of CLI name ``name``."""
    if name not in _CLASSES:
        raise LogpipeError(f"unknown format {name!r}; known: {', '.join(sorted(FORMATS))}")
    module, cls = _CLASSES[name]
    found: type[FormatAdapter] = getattr(importlib.import_module(module), cls)
    return found


def get_adapter(name: str, **options: Any) -> FormatAdapter:
    """An adapter instance by CLI name, with its options (e.g. ``hz``, ``mapping`` for bags)."""
    cls = adapter_class(name)
    accepted = set(inspect.signature(cls).parameters)
    unknown = sorted(set(options) - accepted)
    if unknown:
        raise LogpipeError(f"format {name!r} takes no option(s) {', '.join(unknown)}"
                           f" (it takes: {', '.join(sorted(accepted)) or 'none'})")
    return cls(**options)


def detect(path: Path) -> str:
    """Name of the adapter that reads ``path`` (a file, or a folder: judged by its first readable input).

    Raises:
        LogpipeError: no adapter, or more than one, recognises it (then ``--format`` decides).
    """
    if not path.exists():
        raise LogpipeError(f"{path}: no such file or folder")
    candidates = [path] if path.is_file() else _first_files(path, 200)
    for candidate in candidates:
        # Text formats first: when one claims the file the others cannot (see TEXT_FORMATS), and their
        # modules (rosbags, mcap, YAML: ~0.2 s) need not be imported.
        names = [name for name in TEXT_FORMATS if adapter_class(name)().sniff(candidate)]
        if not names:
            names = [name for name in FORMATS if name not in TEXT_FORMATS and adapter_class(name)().sniff(candidate)]
        if len(names) == 1:
            return names[0]
        if len(names) > 1:
            raise LogpipeError(f"{candidate}: looks like several formats ({', '.join(names)}); pass --format")
    raise LogpipeError(f"{path}: no known format recognised; pass --format ({', '.join(sorted(FORMATS))})")


logger = logging.getLogger(__name__)
ROS_FORMATS = ("rosbag", "mcap")
"""Formats read by the same extraction, options and protocol: one dataset can hold both (``choose_format``)."""


def choose_format(roots: Sequence[Path], given: str | None) -> tuple[str, dict[str, Any]]:
    """The format ``ingest`` reads ``roots`` with, and the adapter options that adds: ``given`` as it is, else
    ``detect``'s, except that ROS bags and standalone MCAP files found together (in one folder or across the
    roots) are one ``rosbag`` dataset whose adapter reads the MCAP files too (``with_mcap``)."""
    fmt = given or detect(roots[0])
    if given is None and fmt in ROS_FORMATS:
        bags = any(adapter_class("rosbag")().discover(r) for r in roots)
        mcaps = any(adapter_class("mcap")().discover(r) for r in roots)
        if bags and mcaps:
            return "rosbag", {"with_mcap": True}
    return fmt, {}


def other_format_inputs(roots: Sequence[Path], found: Sequence[Path], fmt: str) -> list[dict[str, str]]:
    """Files under the folders of ``roots`` that no input of ``found`` covers but another format recognises:
    ``{"path", "format", "why"}`` each (and a logged warning), so an ingest names what it leaves out.
    Text formats judge only ``.csv``/``.txt`` files (a map or a README is no log)."""
    covered = {str(p) for p in found}
    folders = tuple(str(p) + os.sep for p in found if p.is_dir())
    skipped = []
    for root in (r for r in roots if r.is_dir()):
        for folder, _, files in sorted(os.walk(root)):
            for name in sorted(files):
                path = os.path.join(folder, name)
                if path in covered or path.startswith(folders):
                    continue
                other = _recognised(Path(path), fmt)
                if other is not None:
                    skipped.append({"path": os.path.relpath(path, root), "format": other,
                                    "why": f"a {other} input; this dataset is {fmt} (ingest it with its own --out)"})
                    logger.warning("%s: skipped: %s", path, skipped[-1]["why"])  # named, not dropped in silence
    return skipped


def _recognised(path: Path, fmt: str) -> str | None:
    """The format other than ``fmt`` that claims ``path``, if exactly one does."""
    names = [n for n in FORMATS if n != fmt and (n not in TEXT_FORMATS or path.suffix in (".csv", ".txt"))]
    claims = [n for n in names if adapter_class(n)().sniff(path)]
    return claims[0] if len(claims) == 1 else None


def _first_files(root: Path, limit: int) -> list[Path]:
    """The first ``limit`` files under ``root`` in path order, from one ``os.walk``: no ``Path`` and no stat per
    file of the whole tree (a sorted ``rglob`` cost ~0.4 s per 10,000 files)."""
    names = (os.path.join(folder, name) for folder, _, files in os.walk(root) for name in files)
    first = heapq.nsmallest(limit, names, key=lambda name: name.split(os.sep))
    return [Path(name) for name in first if os.path.isfile(name)]


__all__ = ["FORMATS", "ROS_FORMATS", "TEXT_FORMATS", "FormatAdapter", "ParsedLogs", "adapter_class", "choose_format",
           "detect", "get_adapter", "other_format_inputs"]
