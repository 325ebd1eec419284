"""Streaming training data: a torch ``DataLoader`` over a dataset's Parquet shards.

``ShardScenes`` yields the ``SceneSample``s of a set of logs shard by shard; each ``DataLoader`` worker takes
every ``num_workers``-th shard, so cutting windows (Python, per sample) runs on all cores while the training
process only steps the model, and memory holds one shard per worker instead of the whole split.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

import pyarrow as pa
import pyarrow.compute as pc
from torch.utils.data import DataLoader, IterableDataset, get_worker_info

from logpipe.dataset.reader import Dataset, scene_sample
from logpipe.types import SceneSample


class ShardScenes(IterableDataset[SceneSample]):
    """The samples of ``log_ids`` in a dataset, read one shard at a time.

    Attributes:
        root: the dataset folder.
        log_ids: logs whose samples are yielded.
        raster_run: folder under ``rasters/`` whose images are attached (None: no rasters).
    """

    def __init__(self, root: Path, log_ids: Sequence[str], raster_run: str | None = None) -> None:
        super().__init__()
        self.root = Path(root)
        self.log_ids = sorted(set(log_ids))
        self.raster_run = raster_run

    def __iter__(self) -> Iterator[SceneSample]:
        dataset = Dataset.open(self.root)
        info = get_worker_info()
        shards = dataset.shard_paths
        if info is not None:
            shards = shards[info.id :: info.num_workers]
        rasters = None
        if self.raster_run is not None:
            from logpipe.raster.runs import find_raster_run

            rasters = find_raster_run(self.root, self.raster_run, None)
        samples = dataset.samples()
        samples = samples.filter(pc.is_in(samples.column("log_id"), value_set=pa.array(self.log_ids)))
        by_log: dict[str, list[dict[str, Any]]] = {}
        for row in samples.to_pylist():
            by_log.setdefault(row["log_id"], []).append(row)
        protocol = dataset.protocol
        for log_id, tracks in dataset.iter_logs(shards=shards, log_ids=self.log_ids):
            for row in by_log.get(log_id, []):
                sample = scene_sample(tracks, row, protocol)
                if rasters is not None:
                    sample.raster, sample.world_to_raster = rasters.get(sample.sample_id)
                yield sample


def _as_is(item: Any) -> Any:
    # batch_size=None would otherwise turn the numpy arrays into tensors; the model collates itself.
    return item


def scene_loader(
    root: Path, log_ids: Sequence[str], *, workers: int = 2, raster_run: str | None = None
) -> DataLoader[SceneSample]:
    """A re-iterable ``DataLoader`` of ``SceneSample``s (one per item) for ``fit``'s streaming input."""
    return DataLoader(
        ShardScenes(root, log_ids, raster_run),
        batch_size=None,
        num_workers=workers,
        collate_fn=_as_is,
        persistent_workers=False,
    )
