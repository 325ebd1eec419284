"""A training run's state around ``training.fit``: the device it trains on, its run folder held by one training
at a time, and several sample streams read as one.

``logpipe train`` (``stages/train.py``) resolves the datasets, splits and config; this module owns what a run
needs from the process and the folder: under torchrun (``WORLD_SIZE`` > 1, ``data_parallel``) training is CPU
only and only process 0 (``RANK`` 0) writes, so only it holds the folder's lock.
"""

from __future__ import annotations

import os
from collections.abc import Iterable, Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path

import torch

from logpipe.storage.folder_lock import FolderLock
from logpipe.types import SceneSample

from .device import resolve_device


def train_device(device: str) -> torch.device:
    """The torch device for ``--device`` (``auto``, ``cpu``, ``cuda``), resolved before any data is read so a
    bad value fails first. torchrun's data-parallel training is CPU only (gloo, see ``fit``): there ``auto`` is
    the CPU."""
    return resolve_device("cpu" if device == "auto" and int(os.environ.get("WORLD_SIZE", "1")) > 1 else device)


@contextmanager
def run_folder(out_dir: Path) -> Iterator[None]:
    """Hold ``out_dir``'s lock while a training writes it (one training per run folder; under torchrun only
    process 0 writes, so only it locks). A run that could not start leaves no folder it created."""
    lock = FolderLock(out_dir) if os.environ.get("RANK", "0") == "0" else None
    created = not out_dir.exists()
    if lock is not None:
        out_dir.mkdir(parents=True, exist_ok=True)
        lock.acquire()
    try:
        yield
    finally:
        if lock is not None:
            # Still under the lock, so another training that takes the folder next never loses it; removed
            # only when empty: a run that could not start leaves no folder.
            lock.release(remove_folder=created)


class ChainedScenes:
    """Re-iterable sample streams read one after the other (``fit`` re-iterates its input every epoch)."""

    def __init__(self, parts: Sequence[Iterable[SceneSample]]) -> None:
        self.parts = list(parts)

    def __iter__(self) -> Iterator[SceneSample]:
        for part in self.parts:
            yield from part
