"""Where the scripts find their inputs: the repository, the checkpoints shipped in the package (with
``--checkpoint METHOD=PATH`` overrides), the extra training seeds' checkpoints outside it, and the ingested
datasets they work on."""

from __future__ import annotations

import argparse
from collections.abc import Sequence
from pathlib import Path

from logpipe.dataset.reader import Dataset
from logpipe.stages.ingest import IngestOptions, ingest

REPO = Path(__file__).resolve().parents[1]
CHECKPOINTS = REPO / "model" / "checkpoints"
"""The checkpoints shipped in the package: ``logpipe predict``'s defaults and the results tables' baselines."""
SEEDS_DIR = REPO / "out" / "checkpoints"
"""Where ``make train-* SEED=N`` puts the extra training seeds' checkpoints (``seedN/<kind>/...``, gitignored): the
reproduce scripts' across-seeds tables read them (``--seeds-dir``)."""
SHIPPED_PREFIX = "model/checkpoints/"
"""How a default checkpoint template starts: the part ``seed_template`` swaps for a seed's folder."""


def checkpoint_paths(ap: argparse.ArgumentParser, items: Sequence[str], defaults: dict[str, str]) -> dict[str, str]:
    """``defaults`` (method -> checkpoint folder or template) updated by ``--checkpoint METHOD=PATH`` items; an
    unknown method or an empty path is an argument error."""
    paths = dict(defaults)
    for item in items:
        method, _, path = item.partition("=")
        if method not in defaults or not path:
            ap.error(f"--checkpoint {item!r}: expected METHOD=PATH with METHOD in {sorted(defaults)}")
        paths[method] = path
    return paths


def ensure_dataset(data: Path, out: Path, fmt: str | None = None) -> Dataset:
    """``logpipe ingest data --out out --no-mcap`` (a no-op when already ingested: inputs are content-hashed)."""
    ingest([data], IngestOptions(out=out, format=fmt, write_mcap=False))
    return Dataset.open(out)


def find_checkpoint(template: str, scene: str) -> Path | None:
    """The checkpoint folder (``meta.json`` inside, or in its ``best/``) for ``scene``, or None."""
    base = (REPO / template.format(scene=scene)).resolve()
    for cand in (base, base / "best"):
        if (cand / "meta.json").is_file():
            return cand
    return None
