"""Writing one dataset shard's prediction outputs while the model runs: ``ShardWriter`` (a background writer
thread, and the GIL tuning that keeps it from stalling the model thread), the Parquet rows of a batch
(``logpipe.prediction.runs`` decides their layout) and what it is handed per sample (``SamplePrediction``).

Positions are metres in the log's world frame; times are ns on the log's clock.
"""

from __future__ import annotations

import queue
import sys
import threading
import time
from collections.abc import Callable, Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from logpipe.errors import DatasetError
from logpipe.prediction.runs import MCAP_DIR, PREDICTIONS_DIR, PredictionMeta, RunShardEntry
from logpipe.prediction.table import OodRows, RowGroupWriter, SampleForecast, build_table
from logpipe.storage.artifact import FileEntry, file_entry
from logpipe.storage.io import atomic_path, parquet_options
from logpipe.types import OBJECT_TYPES, NDArrayFloat, NDArrayInt, SampleProtocol, SceneSample

if TYPE_CHECKING:
    from logpipe.prediction.options import PredictSummary

ROW_GROUP_ROWS = 256 * 1024
"""Rows per Parquet row group of a predictions file (the last one shorter), whatever the batching."""
SWITCH_INTERVAL_S = 1e-4
"""GIL switch interval while predicting (see ``fast_gil_switching``)."""
QUEUED_BATCHES = 2
"""Batches' worth of predicted samples waiting for the writer before the model waits for it (bounds memory)."""


@dataclass
class SamplePrediction:
    """One sample's forecasts, targets kept in ``target_mask`` order.

    Attributes:
        row: the sample-index row.
        sample: the model input.
        targets: (N,) row indices of the predicted targets in ``sample.positions``.
        futures: (N, K, T_pred, 2) world metres.
        scores: (N, K) mode scores.
        step_ns: (T_pred,) times of the future steps.
        ood: the targets' out-of-distribution rows (``table.OodRows``), when the run checks them.
    """

    row: dict[str, Any]
    sample: SceneSample
    targets: NDArrayInt
    futures: NDArrayFloat
    scores: NDArrayFloat
    step_ns: NDArrayInt
    ood: OodRows | None = None

    @classmethod
    def of(cls, row: dict[str, Any], sample: SceneSample, forecast: Any, protocol: SampleProtocol, modes: int,
           dt_ns: int, ood: OodRows | None = None) -> tuple[SamplePrediction, int]:
        """The prediction of ``forecast`` ((targets, >= K, >= T_pred, 2) world metres, one per target of the
        sample) cut to K ``modes`` and the prediction horizon, with equal mode scores; targets with a non-finite
        forecast (unobserved at the current step) are left out. Returns it and how many were left out.
        ``dt_ns``: the log's median step, for future steps past the log's end."""
        obs_len, pred_len = protocol.obs_len, protocol.pred_len
        targets = np.flatnonzero(sample.target_mask)
        fut = np.asarray(forecast, np.float64)[:, :modes, :pred_len]
        ok = np.isfinite(fut).all(axis=(1, 2, 3))
        scores = np.full((int(ok.sum()), modes), 1.0 / modes)
        step_ns = future_times(sample, obs_len, pred_len, dt_ns)
        kept = None if ood is None else (ood[0][ok], ood[1][ok], ood[2][ok])
        return cls(row, sample, targets[ok], fut[ok], scores, step_ns, kept), int((~ok).sum())


@dataclass
class LogOutput:
    """A log of the shard being predicted: samples handed to the model (``expected``) and forecast so far."""

    log_id: str
    expected: int = 0
    finished: int = 0


def future_times(sample: SceneSample, obs_len: int, pred_len: int, dt_ns: int) -> NDArrayInt:
    """The true times of the future steps where the window has them, else current + k x the log's median step
    (ns on the log's clock)."""
    ts = np.asarray(sample.timestamps_ns, np.int64)
    current = int(ts[obs_len - 1])
    fut = np.zeros(pred_len, np.int64)
    have = ts[obs_len : obs_len + pred_len]
    fut[: len(have)] = have
    fallback = current + dt_ns * np.arange(1, pred_len + 1, dtype=np.int64)
    result: NDArrayInt = np.where(fut > 0, fut, fallback)
    return result


LogMcapWriter = Callable[[str, Iterator[SamplePrediction], Path], int]
"""Writes a log's MCAP (log id, its predictions as they come, target file); returns the original messages copied."""


def log_table(meta: PredictionMeta, log_id: str, done: list[SamplePrediction]) -> pa.Table:
    """The predictions rows of samples of one log."""
    return build_table(meta, [
        SampleForecast(log_id=log_id, sample_id=p.sample.sample_id,
                       track_ids=[p.sample.track_ids[i] for i in p.targets],
                       object_types=[OBJECT_TYPES[int(p.sample.object_types[i])] for i in p.targets],
                       futures=p.futures, scores=p.scores, step_ns=p.step_ns, ood=p.ood)
        for p in done
    ])


@contextmanager
def fast_gil_switching() -> Iterator[None]:
    """The writer thread holds the GIL for long stretches of JSON encoding; with the default 5 ms switch interval
    every small torch op of the model thread could wait that long for it. Restores the interval on exit."""
    previous = sys.getswitchinterval()
    sys.setswitchinterval(SWITCH_INTERVAL_S)
    try:
        yield
    finally:
        sys.setswitchinterval(previous)


@contextmanager
def shard_writer(meta: PredictionMeta, batch_size: int, out_dir: Path, index: int, entry: RunShardEntry,
                 write_mcap: LogMcapWriter | None) -> Iterator[ShardWriter]:
    """A ``ShardWriter`` for dataset shard ``index``: its Parquet file is written under a temporary name and
    moved into place when the block ends, after every log is written (``close``); on an error, queued work is
    dropped (``abort``) and the error re-raised.

    Files are named after the shard's index (``part-NNNNN``): names no committed shard uses, so a reader of the
    folder never sees them change; a crash leaves them uncommitted and the next writer removes them.
    """
    part = f"part-{index:05d}"
    parquet_rel, mcap_rel = f"{PREDICTIONS_DIR}/{part}.parquet", f"{MCAP_DIR}/{part}"
    # Per-column encodings (dictionaries for ids, byte-stream-split for the coordinate lists): ~1/3 smaller files.
    options = {k: v for k, v in parquet_options(meta.schema()).items() if k != "row_group_size"}
    with atomic_path(out_dir / parquet_rel) as tmp, pq.ParquetWriter(tmp, meta.schema(), **options) as parquet:
        sink = ShardWriter(meta, batch_size, parquet, out_dir / mcap_rel, entry, write_mcap)
        try:
            yield sink
            sink.close()
        except BaseException:
            sink.abort()
            raise
    t0 = time.perf_counter()
    entry["file"] = parquet_rel
    sink.files[parquet_rel] = file_entry(out_dir / parquet_rel, rows=entry["rows"])
    for name in sink.mcap_written:
        sink.files[f"{mcap_rel}/{name}"] = file_entry(out_dir / mcap_rel / name)
    sink.files_seconds = time.perf_counter() - t0


@contextmanager
def counted_shard_writer(meta: PredictionMeta, batch_size: int, out_dir: Path, index: int, entry: RunShardEntry,
                         write_mcap: LogMcapWriter | None, summary: PredictSummary) -> Iterator[ShardWriter]:
    """``shard_writer`` whose writer's counts and times go into ``summary`` however the block ends, and the
    shard's rows when it ends well (the one place both predict paths count a shard's output)."""
    sink: ShardWriter | None = None
    try:
        with shard_writer(meta, batch_size, out_dir, index, entry, write_mcap) as sink:
            yield sink
    finally:
        if sink is not None:
            summary.count_writer(sink)
    summary.rows += entry["rows"]


class ShardWriter:
    """Writes one shard's outputs on a background thread while the model runs (output encoding, compression and
    file writes overlap the forward passes; numpy, zstd, pyarrow and torch release the GIL).

    Logs are written one at a time, in shard order: a log's MCAP starts as soon as its first predictions arrive
    (the original recording is copied first) and its prediction messages and Parquet rows are written as each
    batch finishes, so one long log (ETH/UCY scenes) overlaps with the model too. Parquet row groups are exactly
    ``ROW_GROUP_ROWS`` rows (the last one shorter), whatever the batching.

    Args:
        meta: the run's table metadata; ``batch_size``: samples per batch (bounds the queue).
        parquet: the shard's predictions file; ``entry``: its manifest entry (``rows``, ``samples`` counted here).
        mcap_dir: where log MCAPs go, written by ``write_mcap`` (None: no MCAPs).
    """

    def __init__(self, meta: PredictionMeta, batch_size: int, parquet: pq.ParquetWriter, mcap_dir: Path,
                 entry: RunShardEntry, write_mcap: LogMcapWriter | None) -> None:
        self._meta, self._parquet, self._mcap_dir, self._entry = meta, parquet, mcap_dir, entry
        self._write_mcap = write_mcap
        self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="logpipe-predict-write")
        self._jobs: list[Future[None]] = []
        self._feeds: dict[str, queue.Queue[list[SamplePrediction] | None]] = {}
        self._groups = RowGroupWriter(parquet, ROW_GROUP_ROWS)
        self._queued = 0  # samples handed over and not yet taken by the writer
        self._limit = QUEUED_BATCHES * batch_size
        self._taken = threading.Condition()
        self.busy_seconds = 0.0  # writer-thread time spent writing (not waiting for input)
        self.wait_seconds = 0.0  # main-thread time spent waiting for the writer
        self.inline_seconds = 0.0  # main-thread time spent writing (``write_log_now``)
        self.mcap_files = 0
        self.original_messages = 0
        self.mcap_written: list[str] = []  # file names in mcap_dir, in log order
        self.files: dict[str, FileEntry] = {}  # what to commit, filled by ``shard_writer`` once all is written
        self.files_seconds = 0.0  # time ``shard_writer`` spent hashing them

    def add(self, out: LogOutput, predictions: list[SamplePrediction]) -> None:
        """Queue a batch's predictions of one log (starting the log's job at its first batch)."""
        self._raise_failed()
        if out.log_id not in self._feeds:
            feed: queue.Queue[list[SamplePrediction] | None] = queue.Queue()
            self._feeds[out.log_id] = feed
            self._jobs.append(self._pool.submit(self._write_log, out.log_id, feed))
        with self._taken:
            self._queued += max(len(predictions), 1)
        self._feeds[out.log_id].put(predictions)

    def add_rows(self, table: pa.Table, samples: int) -> None:
        """Queue predictions rows built elsewhere, of ``samples`` samples, for the Parquet file (the columnar path,
        ``logpipe.prediction.columnar``: Parquet only, no log MCAPs), waiting while ``QUEUED_BATCHES`` tables
        are queued (bounded memory)."""
        self._raise_failed()
        t0 = time.perf_counter()
        while len(self._jobs) >= QUEUED_BATCHES:
            self._jobs.pop(0).result()
        self.wait_seconds += time.perf_counter() - t0
        self._jobs.append(self._pool.submit(self._write_rows, table, samples))

    def _write_rows(self, table: pa.Table, samples: int) -> None:
        started = time.perf_counter()
        self._add_rows(table)
        self._entry["samples"] += samples
        self.busy_seconds += time.perf_counter() - started

    def throttle(self) -> None:
        """Wait while more than ``QUEUED_BATCHES`` batches' worth of samples are queued (bounded memory).

        Only call it when every log before the oldest unfinished one has been ended: the writer can then take
        every queued batch (it never waits for a log the caller has not finished).
        """
        t0 = time.perf_counter()
        with self._taken:
            while self._queued > self._limit:
                self._taken.wait(timeout=0.05)
                self._raise_failed()  # a failed writer no longer takes batches
        self.wait_seconds += time.perf_counter() - t0

    def end(self, out: LogOutput) -> None:
        """No more predictions for this log."""
        if out.log_id not in self._feeds:  # a log without predictions still gets its MCAP
            self.add(out, [])
        self._feeds.pop(out.log_id).put(None)

    def end_finished(self, pending: list[LogOutput], current: LogOutput) -> None:
        """End the oldest of the ``pending`` logs whose samples are all predicted (not ``current``: more of its
        samples may come), removing them from ``pending``."""
        while pending and pending[0].finished == pending[0].expected and pending[0] is not current:
            self.end(pending.pop(0))

    def close(self) -> None:
        """Wait for every log, write the last row group; re-raises a writer error."""
        t0 = time.perf_counter()
        for job in self._jobs:
            job.result()
        self._groups.flush()
        self._pool.shutdown()
        self.wait_seconds += time.perf_counter() - t0

    def abort(self) -> None:
        """Stop after an error elsewhere: end every open log and drop queued work."""
        for feed in self._feeds.values():
            feed.put(None)
        self._feeds.clear()
        self._pool.shutdown(wait=True, cancel_futures=True)

    def _raise_failed(self) -> None:
        while self._jobs and self._jobs[0].done():
            self._jobs.pop(0).result()

    def _write_log(self, log_id: str, feed: queue.Queue[list[SamplePrediction] | None]) -> None:
        started = time.perf_counter()
        waited = 0.0

        def predictions() -> Iterator[SamplePrediction]:
            nonlocal waited
            while True:
                t0 = time.perf_counter()
                item = feed.get()
                waited += time.perf_counter() - t0
                if item is None:
                    return
                with self._taken:
                    self._queued -= max(len(item), 1)
                    self._taken.notify()
                self._add_rows(log_table(self._meta, log_id, item))
                self._entry["samples"] += len(item)
                yield from item

        try:
            if self._write_mcap is not None:
                write_mcap = self._write_mcap
                self._write_log_mcap(log_id, lambda target: write_mcap(log_id, predictions(), target))
            else:
                for _ in predictions():
                    pass
        finally:
            self.busy_seconds += time.perf_counter() - started - waited

    def write_log_now(self, log_id: str, write: Callable[[Path], int]) -> None:
        """Write one log's MCAP on the calling thread: ``write(target file)`` returns the original messages it
        copied (the columnar path, which encodes its messages itself; its time counts as blocking IO)."""
        started = time.perf_counter()
        self._write_log_mcap(log_id, write)
        self.inline_seconds += time.perf_counter() - started

    def _write_log_mcap(self, log_id: str, write: Callable[[Path], int]) -> None:
        target = self._mcap_dir / f"{log_id}.mcap"
        if target.parent != self._mcap_dir:  # predict refused such ids; never write elsewhere
            raise DatasetError(f"log id {log_id!r} is not a single file name")
        self.original_messages += write(target)
        self.mcap_files += 1
        self.mcap_written.append(target.name)

    def _add_rows(self, table: pa.Table) -> None:
        self._entry["rows"] += table.num_rows
        self._groups.add(table)
