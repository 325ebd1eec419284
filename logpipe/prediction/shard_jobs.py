"""A dataset shard's predict work as one picklable job, shared by both predict paths (the columnar one,
``logpipe.prediction.columnar``, and the per-sample one, ``logpipe.prediction.sample_shards``): each job carries only
its own logs' sample rows, steps and MCAP writer, and writes its own uncommitted files wherever it runs (this
process, a worker process, a Ray task or actor); the stage commits the results in shard order."""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Generic, TypeVar

import pyarrow as pa
import pyarrow.compute as pc

from logpipe.dataset.sample_filter import SelectedLogs, SelectedSamples
from logpipe.prediction.mcap_logs import PredictionMcaps
from logpipe.prediction.options import PredictSummary
from logpipe.prediction.runs import RunShardEntry
from logpipe.storage.artifact import FileEntry
from logpipe.storage.io import read_table

RunT = TypeVar("RunT")


@dataclass(frozen=True)
class ShardJob(Generic[RunT]):
    """One dataset shard's work (picklable).

    Attributes:
        run: what the run's jobs share (the path's own record); ``path``: the shard file; ``key``: its name in the
            run manifest; ``index``: its number (``part-NNNNN``).
        log_ids: the selected logs it holds, in logs-table order; ``samples``: their selected sample-index rows, log
            after log in that order; ``dt_ns``: each of its logs' median step (ns).
        summary: a zeroed run summary, filled with this shard's counts.
        mcaps: how to write its logs' MCAPs (None: Parquet only).
    """

    run: RunT
    path: Path
    key: str
    index: int
    log_ids: tuple[str, ...]
    samples: pa.Table
    dt_ns: dict[str, int]
    summary: PredictSummary
    mcaps: PredictionMcaps | None = None

    def start(self, columns: Sequence[str] | None = None) -> tuple[RunShardEntry, pa.Table | None]:
        """The shard's manifest entry to fill and its tracks (only ``columns``, if given; None when it holds no
        selected log: nothing to read or write); the read counts as IO in ``summary``."""
        entry: RunShardEntry = {"shard": self.key, "logs": len(self.log_ids), "samples": 0, "rows": 0, "file": None}
        if not self.log_ids:
            return entry, None
        t0 = time.perf_counter()
        # a damaged shard is a one-line DatasetError
        tracks = read_table(self.path, columns=None if columns is None else list(columns))
        # Only the selected logs' rows: a filtered run over a large shard then indexes and cuts its own logs, not
        # the shard's (a log's rows keep their order, so forecasts and outputs are the same).
        mine = pc.is_in(tracks.column("log_id"), value_set=pa.array(self.log_ids, pa.string()))
        if not pc.all(mine).as_py():
            tracks = tracks.filter(mine)
        self.summary.io_seconds += time.perf_counter() - t0
        return entry, tracks


@dataclass(frozen=True)
class ShardDone:
    """A predicted shard: its manifest entry, the files to commit with it and its counts."""

    entry: RunShardEntry
    files: dict[str, FileEntry]
    summary: PredictSummary


def shard_jobs(run: RunT, root: Path, pending: Sequence[tuple[int, Path]], logs: SelectedLogs,
               samples: SelectedSamples, summary: PredictSummary,
               mcaps: PredictionMcaps | None = None) -> list[ShardJob[RunT]]:
    """The jobs of the ``pending`` (index, path) shards of the dataset at ``root``, from the selected ``logs`` and
    ``samples``; ``mcaps``: the run's MCAP writer, if it writes them."""
    by_shard = logs_by_shard(logs)
    log_dt_ns = logs.column("median_dt_ns")
    jobs = []
    for index, path in pending:
        mine = by_shard.get(path.name, [])
        # combine_chunks, and the MCAP writer cut to the shard's logs: a job pickles its own part, not the run's.
        jobs.append(ShardJob(run, path, path.relative_to(root).as_posix(), index, tuple(mine),
                             samples.table(mine).combine_chunks(), {i: int(log_dt_ns[i]) for i in mine},
                             summary.zeroed(), mcaps.of_logs(mine) if mcaps is not None else None))
    return jobs


def logs_by_shard(logs: SelectedLogs) -> dict[str, list[str]]:
    """The ids of ``logs`` by the file name of their shard, in the logs' order."""
    by_shard: dict[str, list[str]] = {}
    for log_id, shard in logs.column("shard").items():
        by_shard.setdefault(str(shard).rsplit("/", 1)[-1], []).append(log_id)  # a POSIX path; no Path per log
    return by_shard
