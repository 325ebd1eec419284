"""Sample-index rows → model inputs for prediction: ``SampleCutter`` cuts each sample's window out of its log
(``logpipe.dataset.windows``), keeps the targets of the object types asked for, attaches the sample's raster, and plans
the batches a shard's samples form (the same on every process that cuts them: the predict stage, Ray actors).

Positions are metres in the log's world frame; times are ns on the log's clock.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc

from logpipe.dataset.sample_filter import SelectedSamples
from logpipe.dataset.shards import log_slices
from logpipe.dataset.windows import LogWindows
from logpipe.errors import LogpipeError
from logpipe.raster.runs import RasterShards
from logpipe.storage.io import read_table
from logpipe.types import OBJECT_TYPES, SceneSample

BatchPlan = list[list[tuple[str, dict[str, Any]]]]
"""Consecutive batches of (log id, sample-index row)."""
WorkItem = tuple[str, BatchPlan]
"""A shard path and consecutive batches of it (a Ray actor's unit of work)."""


@dataclass(frozen=True)
class SampleCutter:
    """How a run cuts its samples.

    Attributes:
        obs_len: the protocol's observed steps.
        object_types: only targets of these classes (``SampleFilter.object_types``; empty: all).
        rasters: the raster run whose rasters are attached (None: none); ``raster_ids`` its sample ids.
    """

    obs_len: int
    object_types: tuple[str, ...] = ()
    rasters: RasterShards | None = None
    raster_ids: frozenset[str] = field(default_factory=frozenset)

    def cut(self, windows: LogWindows, row: dict[str, Any], raster: bool = True) -> SceneSample | None:
        """The sample of ``row`` with the object-type filter applied to its targets and (``raster``) its raster
        attached; None when no target is left."""
        sample = windows.sample(row, self.obs_len)
        if self.object_types:
            keep = np.isin(np.asarray(OBJECT_TYPES)[sample.object_types], self.object_types)
            sample.target_mask = sample.target_mask & keep
        if not sample.target_mask.any():
            return None
        if raster and self.rasters is not None and sample.sample_id in self.raster_ids:
            sample.raster, sample.world_to_raster = self.rasters.get(sample.sample_id)
        return sample

    def for_samples(self, sample_ids: pa.Array) -> SampleCutter:
        """This cutter with only ``sample_ids``' rasters (what a worker's job carries: the whole raster index of a
        50k-log corpus is ~20 MB to pickle), in a fresh ``RasterShards``, which has no memory maps to pickle."""
        if self.rasters is None:
            return self
        index = self.rasters.index
        index = index.filter(pc.is_in(index.column("sample_id"), value_set=sample_ids))
        shards = set(pc.unique(index.column("shard")).to_pylist())
        files = {rel: entry for rel, entry in self.rasters.files.items() if rel in shards}
        return replace(self, rasters=RasterShards(self.rasters.run_dir, self.rasters.spec, index, files),
                       raster_ids=self.raster_ids & frozenset(sample_ids.to_pylist()))

    def plan_batches(self, tracks: pa.Table, log_ids: Sequence[str], samples: SelectedSamples,
                     batch_size: int) -> BatchPlan:
        """The batches of one shard's ``tracks``: the samples of ``log_ids`` (in that order) left with targets,
        ``batch_size`` at a time."""
        windows = dict(log_windows(tracks, log_ids))
        rows = samples.rows_by_log(list(windows))
        kept = [(log_id, row) for log_id, log in windows.items()
                for row in rows[log_id] if self.cut(log, row, raster=False) is not None]
        return [kept[i : i + batch_size] for i in range(0, len(kept), batch_size)]

    def cut_planned(self, shard: ShardWindows, path: str, batches: BatchPlan) -> Iterator[list[SceneSample]]:
        """The samples of each planned batch of the shard file at ``path``.

        Raises:
            LogpipeError: a planned sample has no targets (the plan was made with another cutter).
        """
        for batch in batches:
            samples = []
            for log_id, row in batch:
                sample = self.cut(shard.get(path, log_id), row)
                if sample is None:
                    raise LogpipeError(f"{path}: sample {row['sample_id']} has no targets on a Ray actor")
                samples.append(sample)
            yield samples


def work_items(planned: Sequence[tuple[Path, BatchPlan]], parts: int) -> list[WorkItem]:
    """The planned batches of each shard split into runs of consecutive batches, about ``parts`` in all."""
    per_item = max(1, -(-sum(len(b) for _, b in planned) // parts))
    return [(str(path), batches[i : i + per_item]) for path, batches in planned
            for i in range(0, len(batches), per_item)]


def raster_problems(dataset_dir: Path, rasters: RasterShards | None, samples: SelectedSamples,
                    allow_blank: bool = False) -> list[str]:
    """Why the raster run ``rasters`` cannot feed a network that needs a raster for each of the selected
    ``samples``; empty when it can. Blank rasters (no map, or the centre off it) are a problem unless
    ``allow_blank``: the environment net would take an empty picture for a road with no lanes."""
    if rasters is None:
        return [f"the checkpoint uses the environment net but {dataset_dir} has no raster run with the channels "
                "it expects; run `logpipe rasterise`"]
    ids = samples.sample_ids()
    lacking = pc.invert(pc.is_in(ids, value_set=rasters.index.column("sample_id").combine_chunks()))
    missing = ids.filter(lacking).to_pylist()
    if missing:
        return [f"raster run {rasters.run_dir.name} lacks {len(missing)} selected samples (e.g. {missing[0]}); "
                "re-run `logpipe rasterise`"]
    blank = pc.sum(pc.is_in(ids, value_set=rasters.index.filter(rasters.index.column("empty")).column("sample_id")
                            .combine_chunks())).as_py() or 0
    if blank and not allow_blank:
        return [f"{blank} of the {len(ids)} selected samples have a blank raster in run {rasters.run_dir.name} "
                "(their log has no map, or the centre is off it: see `logpipe rasterise`'s summary); give the "
                "maps to `logpipe rasterise`, or --allow-blank-rasters to predict on them anyway"]
    return []


def log_windows(tracks: pa.Table, log_ids: Sequence[str]) -> Iterator[tuple[str, LogWindows]]:
    """The windows of each of ``log_ids`` that ``tracks`` (a shard) holds, in the order of ``log_ids``."""
    slices = log_slices(tracks)
    chosen = [i for i in log_ids if i in slices]
    if 0 < len(chosen) < len(slices):  # convert only the chosen logs' rows (a filter may pick a few per shard)
        tracks = pa.concat_tables([tracks.slice(slices[i][0], slices[i][1] - slices[i][0]) for i in chosen])
    windows = LogWindows.of_logs(tracks) if chosen else {}
    for log_id in chosen:
        yield log_id, windows[log_id]


class ShardWindows:
    """The windows of the logs of the last shard file read (a Ray actor's work items name shards by path)."""

    def __init__(self) -> None:
        self._path: str | None = None
        self._windows: dict[str, LogWindows] = {}

    def get(self, path: str, log_id: str) -> LogWindows:
        """The windows of ``log_id`` in the shard at ``path``."""
        if self._path != path:
            self._path, self._windows = path, LogWindows.of_logs(read_table(Path(path)))
        return self._windows[log_id]
