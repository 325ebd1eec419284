"""``logpipe predict``: forecast every prediction sample of a dataset; write the predictions table and, per
log, an MCAP with the original recording plus prediction channels.

Reads top-down: open the dataset and the predictor (a checkpoint, the shipped one for the dataset kind, or a
baseline) → check that they fit (kind, obs/pred lengths, frame rate, agent types, rasters, originals, log ids
that are safe file names) before any work → take the output folder's lock → select samples
(``SampleFilter``) → per dataset shard not yet committed: cut ``SceneSample``s, attach rasters, predict in
batches under ``torch.inference_mode`` → write the shard's Parquet and its logs' MCAPs (each file whole, under
a new name) → commit the shard by replacing the run manifest (``logpipe.artifact``).

Output folder (a committed artifact; the table and the manifest's metadata are ``logpipe.predictions``)::

    manifest.json                    settings, metadata, the finished shards and every committed file
    predictions/part-NNNNN.parquet   schemas/predictions.json, one file per dataset shard (NNNNN = its index)
    mcap/part-NNNNN/<log_id>.mcap    the original log + /logpipe/predictions (logpipe.Predictions),
                                     /logpipe/predictions/scene (foxglove.SceneUpdate: history, truth,
                                     modes) and, with rasters, /logpipe/raster (foxglove.CompressedImage),
                                     /logpipe/raster/grid (foxglove.Grid) in frame logpipe_raster, placed by
                                     /logpipe/raster/tf (foxglove.FrameTransform); Protobuf, see logpipe.foxglove

Frames and units: positions are metres in the log's world frame (``logpipe.types``); message times and
``timestamp_ns`` are ns on the log's clock; a sample's prediction time is its current (last observed) step.
Resuming: shards the committed manifest lists with the same settings are skipped; a shard interrupted midway
is redone from scratch (the files it left are not committed and are removed), so the rerun of an interrupted
run gives the same bytes as an uninterrupted one.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import queue
import sys
import threading
import time
from collections.abc import Callable, Iterable, Iterator, Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
import pyarrow.parquet as pq

from logpipe import __version__
from logpipe import foxglove as fx
from logpipe.artifact import MANIFEST, FileEntry, file_entry, output_errors, unsafe_file_name
from logpipe.contracts import json_schema
from logpipe.dataset import Dataset
from logpipe.errors import DatasetError, LogpipeError
from logpipe.executor import default_workers
from logpipe.io import as_numpy, atomic_path, parquet_options, read_table, sha256_file, sha256_tree
from logpipe.mcap_merge import NewChannel, NewMessage, Source, write_merged
from logpipe.mcapio import WORLD_FRAME
from logpipe.model.device import check_device_name, resolve_device
from logpipe.model.registry import (
    ChosenPredictor,
    check_fit,
    choose_predictor,
    load_net,
    resolve_inference,
    seen_in_training,
)
from logpipe.predictions import (
    MCAP_DIR,
    PREDICTIONS_DIR,
    PredictionMeta,
    PredictionRunWriter,
    RunSettings,
    RunShardEntry,
    SampleForecast,
    build_table,
)
from logpipe.progress import report_total
from logpipe.rasters import RasterShards, find_raster_run
from logpipe.shards import log_slices
from logpipe.types import OBJECT_TYPES, NDArrayFloat, NDArrayInt, SceneSample

try:  # orjson encodes numpy arrays ~30x faster than json; the output is the same compact JSON
    import orjson

    def dumps(obj: Any) -> bytes:
        """Compact JSON (numpy arrays as nested lists)."""
        return orjson.dumps(obj, option=orjson.OPT_SERIALIZE_NUMPY)

except ImportError:  # pragma: no cover - orjson is a dependency; keep working without it

    def dumps(obj: Any) -> bytes:
        """Compact JSON (numpy arrays as nested lists)."""
        return json.dumps(obj, separators=(",", ":"), default=lambda a: a.tolist()).encode()


PREDICTIONS_TOPIC = "/logpipe/predictions"
SCENE_TOPIC = "/logpipe/predictions/scene"
RASTER_TOPIC = "/logpipe/raster"
RASTER_GRID_TOPIC = "/logpipe/raster/grid"
RASTER_TF_TOPIC = "/logpipe/raster/tf"
RASTER_FRAME = "logpipe_raster"
ORIGINAL_FORMATS = ("rosbag", "mcap")
"""Formats whose original file is copied into the output MCAP; other logs use the MCAP ingest wrote."""
_ROW_GROUP_ROWS = 256 * 1024


def default_modes(protocol_name: str) -> int:
    """K when ``--modes`` is not given: 20 for pedestrian protocols (ETH/UCY, Social-GAN best-of-20), 6 for the
    vehicle ones (Argoverse K=6, ROS logs at the Argoverse horizon)."""
    return 20 if protocol_name.startswith(("ethucy", "apolloscape")) else 6


# ---------------------------------------------------------------------------------------------------------
# Inputs: which samples, which predictor.


@dataclass(frozen=True)
class SampleFilter:
    """Which samples to predict; empty fields select everything.

    Attributes:
        log_ids: only these logs.
        split: only logs of this split (``eth/test``, ``hash/val``; see ``Dataset.logs_in_split``).
        start_ns: only samples whose prediction time (current step) is >= this, ns on the log clock.
        end_ns: ... and <= this.
        object_types: only targets of these classes (``OBJECT_TYPES``); samples left without targets are dropped.
    """

    log_ids: tuple[str, ...] = ()
    split: str | None = None
    start_ns: int | None = None
    end_ns: int | None = None
    object_types: tuple[str, ...] = ()

    def to_dict(self) -> dict[str, Any]:
        """Plain dict (run settings)."""
        return dataclasses.asdict(self)


def parse_filter(items: Sequence[str]) -> SampleFilter:
    """``SampleFilter`` from ``--filter`` strings: ``log=ID[,ID..]``, ``split=eth/test``,
    ``time=START_NS:END_NS`` (either side may be empty), ``type=pedestrian[,cyclist..]``; repeatable.

    Raises:
        LogpipeError: an unknown key, a malformed time range or an unknown object type.
    """
    logs: list[str] = []
    types: list[str] = []
    split = start = end = None
    for item in items:
        key, sep, value = item.partition("=")
        if not sep:
            raise LogpipeError(f"--filter expects KEY=VALUE (log=, split=, time=, type=), got {item!r}")
        if key == "log":
            logs += [v for v in value.split(",") if v]
        elif key == "split":
            split = value
        elif key == "time":
            lo, colon, hi = value.partition(":")
            try:
                start = int(lo) if lo else None
                end = int(hi) if hi else None
            except ValueError:
                colon = ""
            if not colon:
                raise LogpipeError(f"--filter time= expects START_NS:END_NS (integers, ns), got {value!r}")
        elif key == "type":
            bad = [t for t in value.split(",") if t not in OBJECT_TYPES]
            if bad:
                raise LogpipeError(f"--filter type=: unknown object types {bad}; known: {', '.join(OBJECT_TYPES)}")
            types += value.split(",")
        else:
            raise LogpipeError(f"--filter: unknown key {key!r}; use log=, split=, time= or type=")
    return SampleFilter(tuple(logs), split, start, end, tuple(types))


def find_original(row: dict[str, Any], inputs: Sequence[Path], dataset: Dataset) -> Source:
    """The recording a log came from: the bag/MCAP under one of ``inputs`` (checked by sha256) for ROS/MCAP
    logs, else the MCAP ingest wrote.

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


# ---------------------------------------------------------------------------------------------------------
# The stage.


@dataclass
class _Run:
    """Everything fixed for one invocation (shared by the per-shard work)."""

    dataset: Dataset
    chosen: ChosenPredictor
    modes: int
    seed: int
    batch_size: int
    filter: SampleFilter
    rasters: RasterShards | None
    raster_images: bool
    write_mcap: bool
    logs: dict[str, dict[str, Any]]
    samples_by_log: dict[str, list[dict[str, Any]]]
    originals: dict[str, Source]
    manifest_sha256: str
    meta: PredictionMeta
    raster_ids: frozenset[str]
    forecast: Callable[[list[SceneSample]], Sequence[Any]] | None = None
    """Where forecasts come from instead of ``chosen.model`` (``--backend ray``: results of the actors)."""


def predict_dataset(
    dataset_dir: Path,
    out_dir: Path,
    *,
    checkpoint: Path | None = None,
    predictor: str | None = None,
    modes: int | None = None,
    seed: int = 0,
    noise_scale: float | None = None,
    constant_velocity_modes: int | None = None,
    context_max_neighbours: int | None = None,
    as_trained: bool = False,
    sample_filter: SampleFilter | None = None,
    inputs: Sequence[Path] = (),
    raster_run: str | None = None,
    raster_images: bool = True,
    write_mcap: bool = True,
    batch_size: int = 64,
    threads: int = 0,
    progress: Callable[[int], None] | None = None,
    device: str = "auto",
    backend: str = "local",
    workers: int = 0,
) -> dict[str, Any]:
    """Predict every selected sample of ``dataset_dir`` into ``out_dir``; returns the run summary (``--json``).

    Args:
        dataset_dir: an ingested dataset.
        out_dir: output folder (see the module docstring); rerunning with the same settings resumes.
        checkpoint: a checkpoint folder (default: ``default_checkpoint`` for the dataset kind and filter split).
        predictor: a baseline instead (``cv``, ``linear``, ``kalman``, ``cv_sampler``).
        modes: K futures per target (default: the K the checkpoint's inference settings were chosen at, else
            ``default_modes``).
        seed: fixes every random draw (noise z, sampler); same seed and settings give the same output.
        noise_scale: standard deviation of the network's noise z (1 = as trained, eq. 21); the spread of the
            K futures. Default: the checkpoint's inference settings (chosen on validation data, ``meta.json``
            ``inference``), else 1. Recorded in ``checkpoint_id`` when not 1.
        constant_velocity_modes: how many of the K futures are the constant-velocity forecast (the network's
            step outputs held at zero). Default: the checkpoint's inference settings, else its training config.
            Recorded in ``checkpoint_id`` when set.
        context_max_neighbours: at most this many of the agents within the checkpoint's ``context_radius_m``
            (the nearest) join each target's context. Default: the checkpoint's inference settings, else all.
            Recorded in ``checkpoint_id`` when set.
        as_trained: ignore the checkpoint's stored inference settings (noise scale 1, its training config).
        sample_filter: which samples (default: all).
        inputs: the roots ROS bags / MCAP files were ingested from (their originals are copied into the output);
            default: the manifest's ``input_roots`` (absolute paths), when ingest records them.
        raster_run: the raster run folder under ``rasters/`` (default: the only one that fits).
        raster_images: add the raster of each sample (PNG image and grid) to the MCAPs when rasters exist.
        write_mcap: write the per-log MCAPs (off: the predictions table only).
        batch_size: samples per forward pass.
        threads: torch intra-op threads (0 = the cores this process may use).
        progress: called with the number of samples each batch finished.
        device: where a checkpoint's network runs: ``auto`` (CUDA when torch can use a GPU, else the CPU), ``cpu``
            or ``cuda`` (autocast there; see ``logpipe.model.device``). Baselines run on the CPU whatever it says.
        backend: ``local`` (this process) or ``ray``: forecasts on Ray actors (``logpipe.model.ray_predict``;
            ``dataset_dir`` must be on a file system every node shares), outputs written here, the same bytes.
        workers: Ray actors (0: one per GPU of the cluster, else one per CPU); ``local`` ignores it.

    Raises:
        LogpipeError: a bad option, a checkpoint that does not fit the dataset, missing rasters or originals;
            all raised before any output is written.
    """
    import torch

    started = time.perf_counter()
    dataset = Dataset.open(dataset_dir)
    sample_filter = sample_filter or SampleFilter()
    chosen = choose_predictor(dataset, checkpoint, predictor, split=sample_filter.split)
    # Baselines are numpy: the value is checked but no device is used (summary "device": None).
    check_device_name(device)
    torch_device = resolve_device(device) if chosen.checkpoint is not None else None
    stored = None if as_trained else chosen.stored_settings
    modes = modes or (stored.num_modes if stored is not None else default_modes(dataset.protocol.name))
    if modes < 1 or batch_size < 1:
        raise LogpipeError(f"--modes and --batch-size must be >= 1, got {modes} and {batch_size}")
    if backend not in ("local", "ray"):
        raise LogpipeError(f"--backend must be local or ray, got {backend!r}")
    inference = resolve_inference(chosen, num_modes=modes, noise_scale=noise_scale,
                                  constant_velocity_modes=constant_velocity_modes,
                                  context_max_neighbours=context_max_neighbours, as_trained=as_trained)
    logs_table = _selected_logs(dataset, sample_filter)
    problems = check_fit(dataset, chosen, logs_table)
    warnings = seen_in_training(chosen, logs_table)
    samples_by_log = _selected_samples(dataset, logs_table, sample_filter)
    # Looked up when used or named, so several runs are an error only where the choice matters and a named run
    # that does not exist is always reported.
    rasters = (find_raster_run(dataset_dir, raster_run, chosen.raster_channels if chosen.needs_raster else None)
               if chosen.needs_raster or raster_images or raster_run is not None else None)
    if chosen.needs_raster:
        problems += _raster_problems(dataset_dir, rasters, samples_by_log)
    if problems:
        where = chosen.checkpoint or "predictor"
        raise LogpipeError(f"{where} does not fit {dataset_dir}: " + "; ".join(problems))
    logs = {str(r["log_id"]): r for r in logs_table.to_pylist()}
    _check_log_ids(dataset, logs)
    # Where bags/MCAP inputs are: --inputs, else the roots ingest recorded (manifest "input_roots", if it does).
    roots = list(inputs) or [Path(p) for p in dataset.manifest.get("input_roots", [])]
    originals = {log_id: find_original(row, roots, dataset) for log_id, row in logs.items()} if write_mcap else {}
    manifest_sha = sha256_file(dataset.root / MANIFEST)
    settings: RunSettings = {
        "dataset_manifest_sha256": manifest_sha, "predictor": chosen.name, "checkpoint_id": chosen.checkpoint_id,
        "num_modes": modes, "seed": seed, "batch_size": batch_size, "filter": sample_filter.to_dict(),
        "protocol": dataset.protocol.to_dict(), "write_mcap": write_mcap,
        "raster_run": rasters.run_dir.name if rasters is not None and raster_images else None,
    }
    protocol = dataset.protocol
    meta = PredictionMeta(
        predictor=chosen.name, checkpoint_id=chosen.checkpoint_id, protocol=protocol.name, obs_len=protocol.obs_len,
        pred_len=protocol.pred_len, num_modes=modes, checkpoint_sha256=chosen.weights_sha256, seed=seed,
        dataset_manifest_sha256=manifest_sha, noise_scale=inference.noise_scale,
        constant_velocity_modes=inference.constant_velocity_modes,
        context_max_neighbours=inference.context_max_neighbours,
    )
    PredictionRunWriter.refuse_other_folders(out_dir)
    summary: dict[str, Any] = {
        "dataset": str(dataset_dir), "out": str(out_dir), "predictor": chosen.name,
        "checkpoint_id": chosen.checkpoint_id, "num_modes": modes, "seed": seed,
        "checkpoint": str(chosen.checkpoint) if chosen.checkpoint is not None else None,
        "raster_run": rasters.run_dir.name if rasters is not None else None,
        "inference": inference.summary() if chosen.checkpoint is not None else None, "warnings": warnings,
        "protocol": dataset.protocol.to_dict(), "logs_selected": len(logs),
        "samples_selected": sum(len(v) for v in samples_by_log.values()), "shards_skipped_done": 0,
        "samples": 0, "targets": 0, "rows": 0, "targets_unobserved": 0, "samples_without_targets": 0,
        "mcap_files": 0, "original_messages": 0, "model_seconds": 0.0, "io_seconds": 0.0, "io_wait_seconds": 0.0,
        "io_busy_seconds": 0.0, "device": None if torch_device is None else str(torch_device), "backend": backend,
    }
    previous_threads = torch.get_num_threads()
    previous_switch = sys.getswitchinterval()
    try:
        with output_errors(), PredictionRunWriter(out_dir) as writer:
            shards, files = writer.committed(settings)
            if backend == "local":  # with ray the actors load it
                load_net(chosen, dataset, batch_size, torch_device or "cpu")
            run = _Run(dataset, chosen, modes, seed, batch_size, sample_filter, rasters, raster_images, write_mcap,
                       logs, samples_by_log, originals, manifest_sha, meta,
                       frozenset(rasters.index.column("sample_id").to_pylist()) if rasters is not None
                       else frozenset())
            done = {s["shard"] for s in shards}
            done_names = {Path(d).name for d in done}  # progress counts the samples of the shards left to do
            report_total(progress, sum(len(rows) for log_id, rows in samples_by_log.items()
                                       if Path(str(logs[log_id]["shard"])).name not in done_names))
            torch.set_num_threads(threads or default_workers())
            # The writer thread (``_ShardWriter``) holds the GIL for long stretches of JSON encoding; with the
            # default 5 ms switch interval every small torch op of the model thread could wait that long for it.
            sys.setswitchinterval(_SWITCH_INTERVAL_S)
            if backend == "ray":
                pending = [(i, p) for i, p in enumerate(dataset.shard_paths)
                           if p.relative_to(dataset.root).as_posix() not in done]
                run.forecast = _ray_forecasts(run, pending, workers, threads, device)
                summary["device"] = None  # chosen on each actor
            uncommitted = writer.manifest is None
            for index, path in enumerate(dataset.shard_paths):
                key = path.relative_to(dataset.root).as_posix()
                if key in done:
                    summary["shards_skipped_done"] += 1
                    continue
                entry, new_files = _predict_shard(run, index, key, path, out_dir, summary, progress)
                shards.append(entry)
                files.update(new_files)
                uncommitted = True
                if new_files:  # one commit per shard with outputs; empty shards ride along with the next one
                    writer.commit(settings, meta, shards, files)
                    uncommitted = False
            if uncommitted:
                writer.commit(settings, meta, shards, files)
    finally:
        torch.set_num_threads(previous_threads)
        sys.setswitchinterval(previous_switch)
    summary["shards"] = len(shards)
    summary["rows_total"] = sum(int(s["rows"]) for s in shards)
    summary["seconds"] = round(time.perf_counter() - started, 3)
    summary["samples_per_s"] = round(summary["samples"] / summary["seconds"], 1) if summary["seconds"] else None
    summary["model_seconds"] = round(summary["model_seconds"], 3)
    summary["io_seconds"] = round(summary["io_seconds"], 3)
    summary["io_wait_seconds"] = round(summary["io_wait_seconds"], 3)
    summary["io_busy_seconds"] = round(summary["io_busy_seconds"], 3)
    return summary


def _check_log_ids(dataset: Dataset, logs: dict[str, dict[str, Any]]) -> None:
    """Refuse, before any output, a selected log whose id cannot be a file name: MCAPs are named after log ids,
    and an id like ``../../x`` would put one outside ``--out``."""
    for log_id in logs:
        reason = unsafe_file_name(log_id)
        if reason:
            raise DatasetError(f"{dataset.root}: log id {log_id[:80]!r} {reason}; log ids become file names, so "
                               "predict refuses it (damaged or hand-made dataset? re-ingest it)")


def _selected_logs(dataset: Dataset, f: SampleFilter) -> pa.Table:
    logs = dataset.logs()
    keep = set(logs.column("log_id").to_pylist())
    if f.log_ids:
        missing = sorted(set(f.log_ids) - keep)
        if missing:
            raise DatasetError(f"{dataset.root}: no logs {missing}")
        keep &= set(f.log_ids)
    if f.split is not None:
        keep &= set(dataset.logs_in_split(f.split))
    return logs.filter(pc.is_in(logs.column("log_id"), value_set=pa.array(sorted(keep), pa.string())))


def _selected_samples(dataset: Dataset, logs: pa.Table, f: SampleFilter) -> dict[str, list[dict[str, Any]]]:
    samples = dataset.samples()
    mask = pc.is_in(samples.column("log_id"), value_set=logs.column("log_id"))
    if f.start_ns is not None:
        mask = pc.and_(mask, pc.greater_equal(samples.column("current_ns"), f.start_ns))
    if f.end_ns is not None:
        mask = pc.and_(mask, pc.less_equal(samples.column("current_ns"), f.end_ns))
    by_log: dict[str, list[dict[str, Any]]] = {}
    for row in samples.filter(mask).to_pylist():
        by_log.setdefault(row["log_id"], []).append(row)
    return by_log


def _raster_problems(dataset_dir: Path, rasters: RasterShards | None,
                     samples_by_log: dict[str, list[dict[str, Any]]]) -> list[str]:
    if rasters is None:
        return [f"the checkpoint uses the environment net but {dataset_dir} has no raster run with the channels "
                "it expects; run `logpipe rasterise`"]
    have = set(rasters.index.column("sample_id").to_pylist())
    missing = [s["sample_id"] for rows in samples_by_log.values() for s in rows if s["sample_id"] not in have]
    if missing:
        return [f"raster run {rasters.run_dir.name} lacks {len(missing)} selected samples (e.g. {missing[0]}); "
                "re-run `logpipe rasterise`"]
    return []


# ---------------------------------------------------------------------------------------------------------
# One shard: samples → model → Parquet + MCAPs.


@dataclass
class _SamplePrediction:
    """One sample's forecasts, targets kept in ``target_mask`` order.

    Attributes:
        row: the sample-index row.
        sample: the model input.
        targets: (N,) row indices of the predicted targets in ``sample.positions``.
        futures: (N, K, T_pred, 2) world metres.
        scores: (N, K) mode scores.
        step_ns: (T_pred,) times of the future steps.
    """

    row: dict[str, Any]
    sample: SceneSample
    targets: NDArrayInt
    futures: NDArrayFloat
    scores: NDArrayFloat
    step_ns: NDArrayInt


@dataclass
class _LogOutput:
    log_id: str
    expected: int = 0
    finished: int = 0


_SWITCH_INTERVAL_S = 1e-4
"""GIL switch interval while predicting (see ``predict_dataset``)."""
_QUEUED_BATCHES = 2
"""Batches' worth of predicted samples waiting for the writer before the model waits for it (bounds memory)."""


class _ShardWriter:
    """Writes one shard's outputs on a background thread while the model runs (output encoding, compression and
    file writes overlap the forward passes; numpy, zstd, pyarrow and torch release the GIL).

    Logs are written one at a time, in shard order: a log's MCAP starts as soon as its first predictions arrive
    (the original recording is copied first) and its prediction messages and Parquet rows are written as each
    batch finishes, so one long log (ETH/UCY scenes) overlaps with the model too. Parquet row groups are exactly
    ``_ROW_GROUP_ROWS`` rows (the last one shorter), whatever the batching.
    """

    def __init__(self, run: _Run, parquet: pq.ParquetWriter, mcap_dir: Path, entry: RunShardEntry) -> None:
        self._run, self._parquet, self._mcap_dir, self._entry = run, parquet, mcap_dir, entry
        self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="logpipe-predict-write")
        self._jobs: list[Future[None]] = []
        self._feeds: dict[str, queue.Queue[list[_SamplePrediction] | None]] = {}
        self._buffered: list[pa.Table] = []
        self._buffered_rows = 0
        self._queued = 0  # samples handed over and not yet taken by the writer
        self._limit = _QUEUED_BATCHES * run.batch_size
        self._taken = threading.Condition()
        self.busy_seconds = 0.0  # writer-thread time spent writing (not waiting for input)
        self.wait_seconds = 0.0  # main-thread time spent waiting for the writer
        self.mcap_files = 0
        self.original_messages = 0
        self.mcap_written: list[str] = []  # file names in mcap_dir, in log order

    def add(self, out: _LogOutput, predictions: list[_SamplePrediction]) -> None:
        """Queue a batch's predictions of one log (starting the log's job at its first batch)."""
        self._raise_failed()
        if out.log_id not in self._feeds:
            feed: queue.Queue[list[_SamplePrediction] | None] = queue.Queue()
            self._feeds[out.log_id] = feed
            self._jobs.append(self._pool.submit(self._write_log, out.log_id, feed))
        with self._taken:
            self._queued += max(len(predictions), 1)
        self._feeds[out.log_id].put(predictions)

    def throttle(self) -> None:
        """Wait while more than ``_QUEUED_BATCHES`` batches' worth of samples are queued (bounded memory).

        Only call it when every log before the oldest unfinished one has been ended: the writer can then take
        every queued batch (it never waits for a log the caller has not finished).
        """
        t0 = time.perf_counter()
        with self._taken:
            while self._queued > self._limit:
                self._taken.wait(timeout=0.05)
                self._raise_failed()  # a failed writer no longer takes batches
        self.wait_seconds += time.perf_counter() - t0

    def end(self, out: _LogOutput) -> None:
        """No more predictions for this log."""
        if out.log_id not in self._feeds:  # a log without predictions still gets its MCAP
            self.add(out, [])
        self._feeds.pop(out.log_id).put(None)

    def close(self) -> None:
        """Wait for every log, write the last row group; re-raises a writer error."""
        t0 = time.perf_counter()
        for job in self._jobs:
            job.result()
        if self._buffered:
            self._parquet.write_table(pa.concat_tables(self._buffered), row_group_size=_ROW_GROUP_ROWS)
            self._buffered = []
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

    def _write_log(self, log_id: str, feed: queue.Queue[list[_SamplePrediction] | None]) -> None:
        run = self._run
        started = time.perf_counter()
        waited = 0.0

        def predictions() -> Iterator[_SamplePrediction]:
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
                self._add_rows(_log_table(run, log_id, item))
                self._entry["samples"] += len(item)
                yield from item

        try:
            if run.write_mcap:
                target = self._mcap_dir / f"{log_id}.mcap"
                if target.parent != self._mcap_dir:  # _check_log_ids refused such ids; never write elsewhere
                    raise DatasetError(f"log id {log_id!r} is not a single file name")
                self.original_messages += _write_log_mcap(run, log_id, predictions(), target)
                self.mcap_files += 1
                self.mcap_written.append(target.name)
            else:
                for _ in predictions():
                    pass
        finally:
            self.busy_seconds += time.perf_counter() - started - waited

    def _add_rows(self, table: pa.Table) -> None:
        if not table.num_rows:
            return
        self._entry["rows"] += table.num_rows
        self._buffered.append(table)
        self._buffered_rows += table.num_rows
        if self._buffered_rows >= _ROW_GROUP_ROWS:
            whole = pa.concat_tables(self._buffered)
            cut = whole.num_rows // _ROW_GROUP_ROWS * _ROW_GROUP_ROWS
            self._parquet.write_table(whole.slice(0, cut), row_group_size=_ROW_GROUP_ROWS)
            rest = whole.slice(cut)
            self._buffered = [rest] if rest.num_rows else []
            self._buffered_rows = rest.num_rows


def _predict_shard(run: _Run, index: int, key: str, path: Path, out_dir: Path, summary: dict[str, Any],
                   progress: Callable[[int], None] | None) -> tuple[RunShardEntry, dict[str, FileEntry]]:
    """Predict one dataset shard (``path``, named ``key`` in the run manifest) into new files; returns its
    manifest entry and the files to commit with it.

    Files are written under the shard's index (``part-NNNNN``): names no committed shard uses, so a reader of
    the folder never sees them change; a crash leaves them uncommitted and the next writer removes them.
    """
    entry: RunShardEntry = {"shard": key, "logs": 0, "samples": 0, "rows": 0, "file": None}
    t0 = time.perf_counter()
    in_shard = set(pc.unique(read_table(path, columns=["log_id"]).column("log_id")).to_pylist())
    shard_logs = [log_id for log_id in run.logs if log_id in in_shard]  # logs-table order, as batches were cut
    entry["logs"] = len(shard_logs)
    if not shard_logs:
        summary["io_seconds"] += time.perf_counter() - t0
        return entry, {}
    part = f"part-{index:05d}"
    parquet_rel = f"{PREDICTIONS_DIR}/{part}.parquet"
    mcap_rel = f"{MCAP_DIR}/{part}"
    tracks = read_table(path)  # a damaged shard is a one-line DatasetError
    summary["io_seconds"] += time.perf_counter() - t0
    # Per-column encodings (dictionaries for ids, byte-stream-split for the coordinate lists): ~1/3 smaller files.
    options = {k: v for k, v in parquet_options(run.meta.schema()).items() if k != "row_group_size"}
    with atomic_path(out_dir / parquet_rel) as tmp, pq.ParquetWriter(tmp, run.meta.schema(), **options) as parquet:
        sink = _ShardWriter(run, parquet, out_dir / mcap_rel, entry)
        try:
            _predict_logs(run, tracks, shard_logs, summary, progress, sink)
            sink.close()
        except BaseException:
            sink.abort()
            raise
        finally:
            summary["io_seconds"] += sink.busy_seconds  # overlapped with the model (writer thread)
            summary["io_busy_seconds"] += sink.busy_seconds
            summary["io_wait_seconds"] += sink.wait_seconds
            summary["mcap_files"] += sink.mcap_files
            summary["original_messages"] += sink.original_messages
    t0 = time.perf_counter()
    summary["rows"] += entry["rows"]
    entry["file"] = parquet_rel
    files = {parquet_rel: file_entry(out_dir / parquet_rel, rows=entry["rows"])}
    for name in sink.mcap_written:
        files[f"{mcap_rel}/{name}"] = file_entry(out_dir / mcap_rel / name)
    summary["io_seconds"] += time.perf_counter() - t0
    return entry, files


def _predict_logs(run: _Run, tracks: pa.Table, shard_logs: list[str], summary: dict[str, Any],
                  progress: Callable[[int], None] | None, sink: _ShardWriter) -> None:
    """Predict every selected sample of the shard's logs, handing results to ``sink`` batch by batch and ending
    each log once all its samples are predicted.

    Batches span logs (Argoverse has one sample per log), so a log is finished when a batch has gone past it.
    """
    slices = log_slices(tracks)
    pending: list[_LogOutput] = []
    batch: list[tuple[_LogOutput, dict[str, Any], SceneSample]] = []
    for log_id in shard_logs:
        out = _LogOutput(log_id)
        pending.append(out)
        lo, hi = slices[log_id]
        windows = LogWindows(tracks.slice(lo, hi - lo), run.dataset.protocol.obs_len)
        for row in run.samples_by_log.get(log_id, []):
            sample = _model_input(run, windows, row)
            if sample is None:
                summary["samples_without_targets"] += 1
                if progress:
                    progress(1)
                continue
            out.expected += 1
            batch.append((out, row, sample))
            if len(batch) >= run.batch_size:
                _run_batch(run, batch, summary, progress, sink)
                batch = []
                _end_finished(pending, out, sink)
                sink.throttle()
        _end_finished(pending, out, sink)
    if batch:
        _run_batch(run, batch, summary, progress, sink)
    for out in pending:
        sink.end(out)


def _end_finished(pending: list[_LogOutput], current: _LogOutput, sink: _ShardWriter) -> None:
    """End the oldest logs whose samples are all predicted (not ``current``: more of its samples may come)."""
    while pending and pending[0].finished == pending[0].expected and pending[0] is not current:
        sink.end(pending.pop(0))


class LogWindows:
    """``dataset.scene_sample`` for many windows of one log: the log's columns are converted to numpy once and
    each window is two binary searches and a scatter (``scene_sample`` filters the Arrow table per window,
    ~4 ms per sample on crowded ETH/UCY logs). Same result, tested against ``scene_sample``.

    Args:
        tracks: one log's rows, sorted by step (as shards store them).
        obs_len: the protocol's observed steps.
    """

    def __init__(self, tracks: pa.Table, obs_len: int) -> None:
        self.obs_len = obs_len
        self.steps = as_numpy(tracks.column("step")).astype(np.int64)
        encoded = pc.dictionary_encode(tracks.column("track_id")).combine_chunks()
        self.names: list[str] = [str(n) for n in encoded.dictionary.to_pylist()]
        self.codes = encoded.indices.to_numpy().astype(np.int64)
        self.x = as_numpy(tracks.column("x")).astype(np.float64)
        self.y = as_numpy(tracks.column("y")).astype(np.float64)
        self.ts = as_numpy(tracks.column("timestamp_ns")).astype(np.int64)
        type_code = {t: i for i, t in enumerate(OBJECT_TYPES)}
        types = pc.dictionary_encode(tracks.column("object_type")).combine_chunks()
        lookup = np.array([type_code[t] for t in types.dictionary.to_pylist()], np.int64)
        self.types = lookup[types.indices.to_numpy()] if len(lookup) else np.zeros(0, np.int64)
        self.ego = as_numpy(pc.equal(tracks.column("role"), "ego")).astype(bool)

    def sample(self, row: dict[str, Any]) -> SceneSample:
        """The window of one sample-index row (agents in order of first appearance, NaN where unobserved)."""
        start, end = int(row["start_step"]), int(row["end_step"])
        lo, hi = np.searchsorted(self.steps, [start, end + 1])
        codes = self.codes[lo:hi]
        # Window-local agent numbering in order of first appearance (as dictionary_encode numbers them).
        uniq, first = np.unique(codes, return_index=True)
        order = uniq[np.argsort(first)]
        local = np.empty(len(self.names), np.int64)
        local[order] = np.arange(len(order))
        agent = local[codes]
        steps = self.steps[lo:hi] - start
        seq = end - start + 1
        positions = np.full((len(order), seq, 2), np.nan)
        positions[agent, steps, 0] = self.x[lo:hi]
        positions[agent, steps, 1] = self.y[lo:hi]
        timestamps = np.zeros(seq, np.int64)
        timestamps[steps] = self.ts[lo:hi]
        object_types = np.zeros(len(order), np.int64)
        object_types[agent] = self.types[lo:hi]
        ego_rows = agent[self.ego[lo:hi]]
        names = [self.names[c] for c in order.tolist()]
        targets = set(row["target_track_ids"])
        return SceneSample(
            sample_id=str(row["sample_id"]),
            positions=positions,
            timestamps_ns=timestamps,
            track_ids=names,
            object_types=object_types,
            target_mask=np.array([n in targets for n in names], dtype=bool),
            ego_index=int(ego_rows.min()) if len(ego_rows) else -1,
            obs_len=self.obs_len,
        )


def _model_input(run: _Run, windows: LogWindows, row: dict[str, Any]) -> SceneSample | None:
    """The sample with the object-type filter applied to its targets and its raster attached; None when no
    target is left."""
    sample = _with_targets(run, windows, row)
    if sample is None:
        return None
    if run.rasters is not None and sample.sample_id in run.raster_ids:
        sample.raster, sample.world_to_raster = run.rasters.get(sample.sample_id)
    return sample


def _with_targets(run: _Run, windows: LogWindows, row: dict[str, Any]) -> SceneSample | None:
    """The sample with the object-type filter applied to its targets; None when no target is left."""
    sample = windows.sample(row)
    if run.filter.object_types:
        keep = np.isin(np.asarray(OBJECT_TYPES)[sample.object_types], run.filter.object_types)
        sample.target_mask = sample.target_mask & keep
    return sample if sample.target_mask.any() else None


def _run_batch(run: _Run, batch: list[tuple[_LogOutput, dict[str, Any], SceneSample]],
               summary: dict[str, Any], progress: Callable[[int], None] | None, sink: _ShardWriter) -> None:
    """Forecast one batch and hand each sample's result to its log."""
    import torch

    samples = [s for _, _, s in batch]
    t0 = time.perf_counter()
    with torch.inference_mode():
        # Predictors draw each sample's noise from (--seed, sample id): batching and resuming change nothing.
        futures = (run.forecast(samples) if run.forecast is not None
                   else run.chosen.model.predict(samples, run.modes, run.seed))
    summary["model_seconds"] += time.perf_counter() - t0
    protocol = run.dataset.protocol
    by_log: dict[str, tuple[_LogOutput, list[_SamplePrediction]]] = {}
    for (out, row, sample), forecast in zip(batch, futures, strict=True):
        targets = np.flatnonzero(sample.target_mask)
        fut = np.asarray(forecast, np.float64)[:, : run.modes, : protocol.pred_len]
        ok = np.isfinite(fut).all(axis=(1, 2, 3))
        summary["targets_unobserved"] += int((~ok).sum())
        scores = np.full((int(ok.sum()), run.modes), 1.0 / run.modes)
        step_ns = _future_times(sample, protocol.obs_len, protocol.pred_len, int(run.logs[out.log_id]["median_dt_ns"]))
        by_log.setdefault(out.log_id, (out, []))[1].append(
            _SamplePrediction(row, sample, targets[ok], fut[ok], scores, step_ns))
        out.finished += 1
        summary["targets"] += int(ok.sum())
    for out, predictions in by_log.values():  # batch order is log order
        sink.add(out, predictions)
    summary["samples"] += len(batch)
    if progress:
        progress(len(batch))


def _future_times(sample: SceneSample, obs_len: int, pred_len: int, dt_ns: int) -> NDArrayInt:
    """The true times of the future steps where the window has them, else current + k x the log's median step."""
    ts = np.asarray(sample.timestamps_ns, np.int64)
    current = int(ts[obs_len - 1])
    fut = np.zeros(pred_len, np.int64)
    have = ts[obs_len : obs_len + pred_len]
    fut[: len(have)] = have
    fallback = current + dt_ns * np.arange(1, pred_len + 1, dtype=np.int64)
    result: NDArrayInt = np.where(fut > 0, fut, fallback)
    return result


def _log_table(run: _Run, log_id: str, done: list[_SamplePrediction]) -> pa.Table:
    """The predictions rows of samples of one log (``logpipe.predictions`` decides the layout)."""
    return build_table(run.meta, [
        SampleForecast(log_id=log_id, sample_id=p.sample.sample_id,
                       track_ids=[p.sample.track_ids[i] for i in p.targets],
                       object_types=[OBJECT_TYPES[int(p.sample.object_types[i])] for i in p.targets],
                       futures=p.futures, scores=p.scores, step_ns=p.step_ns)
        for p in done
    ])


# ---------------------------------------------------------------------------------------------------------
# --backend ray: the local path's batches, forecast on Ray actors, written here as above. The Ray plumbing is
# ``logpipe.model.ray_predict`` (it loads the model, so not the core; stages never import each other); what a
# work item is stays here, next to the windowing both sides share, so the actors cut the same samples.

_RayItem = tuple[str, list[list[tuple[str, dict[str, Any]]]]]
"""A shard path and consecutive batches of it, cut as ``_predict_logs`` cuts them: (log id, sample-index row)."""
_ITEMS_PER_ACTOR = 4
"""Work items per actor: enough to even out uneven items, few enough that each amortises its shard read."""


def _ray_forecasts(run: _Run, pending: list[tuple[int, Path]], workers: int, threads: int,
                   device: str) -> Callable[[list[SceneSample]], Sequence[Any]]:
    """``run.forecast`` for ``--backend ray``: returns, batch after batch, the actors' forecasts of the batches
    ``_predict_logs`` will cut from the ``pending`` shards (checked by sample id)."""
    from logpipe.model import ray_predict

    # Each actor runs torch on ``--threads`` threads (default 1) and reserves as many CPUs. The network's float32
    # reductions round by thread count, so outputs match a local run's bytes at the same --threads (tested).
    threads = threads or 1
    size, gpu = ray_predict.start(workers, threads)
    planned = [(path, _plan_batches(run, path)) for _, path in pending]
    per_item = max(1, -(-sum(len(b) for _, b in planned) // (_ITEMS_PER_ACTOR * size)))
    items: list[_RayItem] = [(str(path), batches[i : i + per_item])
                             for path, batches in planned for i in range(0, len(batches), per_item)]
    # Actors need neither the per-log tables nor the originals; a fresh RasterShards has no memory maps to pickle.
    rasters = run.rasters and RasterShards(run.rasters.run_dir, run.rasters.spec, run.rasters.index)
    actor_run = dataclasses.replace(run, logs={}, samples_by_log={}, originals={}, rasters=rasters)
    setup = functools.partial(_ray_actor, actor_run, threads, device)
    results = (batch for item in ray_predict.forecast_on_ray(setup, items, size=size, gpu=gpu, cpus=threads)
               for batch in item)

    def forecast(samples: list[SceneSample]) -> Sequence[Any]:
        ids, futures = next(results)
        if ids != [s.sample_id for s in samples]:
            raise LogpipeError(f"Ray returned forecasts of samples {ids[:3]}... for a batch of "
                               f"{[s.sample_id for s in samples][:3]}... (the actors cut other batches)")
        return futures  # type: ignore[no-any-return]

    return forecast


def _plan_batches(run: _Run, path: Path) -> list[list[tuple[str, dict[str, Any]]]]:
    """The batches ``_predict_logs`` cuts from one shard: samples left with targets, ``batch_size`` at a time."""
    tracks = read_table(path)
    slices = log_slices(tracks)
    kept: list[tuple[str, dict[str, Any]]] = []
    for log_id in (i for i in run.logs if i in slices):  # logs-table order, as _predict_shard takes them
        lo, hi = slices[log_id]
        windows = LogWindows(tracks.slice(lo, hi - lo), run.dataset.protocol.obs_len)
        kept += [(log_id, row) for row in run.samples_by_log.get(log_id, [])
                 if _with_targets(run, windows, row) is not None]
    return [kept[i : i + run.batch_size] for i in range(0, len(kept), run.batch_size)]


def _ray_actor(run: _Run, threads: int, device: str) -> Callable[[_RayItem], list[tuple[list[str], list[Any]]]]:
    """Runs once in each Ray actor: loads the model, sets ``threads`` torch threads; returns the forecast of a
    work item (sample ids and forecasts per batch), reading its shard from the shared file system (the last one
    read is kept)."""
    import torch

    load_net(run.chosen, run.dataset, run.batch_size,
             resolve_device(device) if run.chosen.checkpoint is not None else "cpu")
    torch.set_num_threads(threads)
    model = run.chosen.model
    assert model is not None
    shard: dict[str, Any] = {}

    def forecast(item: _RayItem) -> list[tuple[list[str], list[Any]]]:
        path, batches = item
        if shard.get("path") != path:
            tracks = read_table(Path(path))
            shard.clear()
            shard.update(path=path, tracks=tracks, slices=log_slices(tracks), windows={})
        windows: dict[str, LogWindows] = shard["windows"]
        out = []
        for batch in batches:
            samples = []
            for log_id, row in batch:
                if log_id not in windows:
                    lo, hi = shard["slices"][log_id]
                    windows[log_id] = LogWindows(shard["tracks"].slice(lo, hi - lo), run.dataset.protocol.obs_len)
                sample = _model_input(run, windows[log_id], row)
                if sample is None:
                    raise LogpipeError(f"{path}: sample {row['sample_id']} has no targets on a Ray actor")
                samples.append(sample)
            with torch.inference_mode():
                futures = model.predict(samples, run.modes, run.seed)
            out.append(([s.sample_id for s in samples], [np.asarray(f) for f in futures]))
        return out

    return forecast


# ---------------------------------------------------------------------------------------------------------
# MCAP output (the Foxglove messages are built by ``logpipe.foxglove``).


def _schema_bytes(name: str) -> bytes:
    return json.dumps(json_schema(name), sort_keys=True).encode()


def _new_channels(with_raster: bool, frame: str) -> list[NewChannel]:
    """Appended channels, indexed by ``NewMessage.channel``: predictions, scene and, with rasters, the raster
    frame's transform, the PNG and the grid the 3D panel draws."""
    channels = [
        NewChannel(PREDICTIONS_TOPIC, "logpipe.Predictions", "jsonschema", _schema_bytes("logpipe.Predictions"),
                   metadata={"frame_id": frame}),
        fx.new_channel(SCENE_TOPIC, "foxglove.SceneUpdate", frame),
    ]
    if with_raster:
        channels += [fx.new_channel(RASTER_TF_TOPIC, "foxglove.FrameTransform", frame),
                     fx.new_channel(RASTER_TOPIC, "foxglove.CompressedImage", RASTER_FRAME),
                     fx.new_channel(RASTER_GRID_TOPIC, "foxglove.Grid", RASTER_FRAME)]
    return channels


def _write_log_mcap(run: _Run, log_id: str, predictions: Iterable[_SamplePrediction], target: Path) -> int:
    """Original log + the prediction channels, one message per sample at its prediction time; returns the number
    of original messages copied."""
    row = run.logs[log_id]
    frame = _world_frame(row)
    with_raster = run.raster_images and run.rasters is not None
    layers = run.rasters.spec.channels if run.rasters is not None else ()
    horizon_ns = int(row["median_dt_ns"]) * run.dataset.protocol.pred_len

    def messages() -> Iterator[NewMessage]:
        for p in predictions:
            now = int(p.row["current_ns"])
            yield NewMessage(0, now, now, _predictions_json(run, log_id, frame, p))
            yield NewMessage(1, now, now, fx.forecast_scene_update(frame, now, horizon_ns, p.sample, p.targets,
                                                                   p.futures, p.scores))
            affine = p.sample.world_to_raster
            if with_raster and p.sample.raster is not None and affine is not None:
                rgb = fx.raster_rgb(np.asarray(p.sample.raster), layers)
                yield NewMessage(2, now, now, fx.raster_transform(frame, RASTER_FRAME, now, affine))
                yield NewMessage(3, now, now, fx.compressed_raster(RASTER_FRAME, now, rgb))
                yield NewMessage(4, now, now, fx.raster_grid(RASTER_FRAME, now, rgb, fx.raster_resolution(affine)))

    stats = write_merged(
        target, [run.originals[log_id]], _new_channels(with_raster, frame), messages(),
        metadata={"logpipe.predictions": {"log_id": log_id, "frame_id": frame, "predictor": run.chosen.name,
                                          "checkpoint_id": run.chosen.checkpoint_id, "num_modes": str(run.modes),
                                          "seed": str(run.seed), "logpipe_version": __version__}},
    )
    return stats.messages


def _world_frame(row: dict[str, Any]) -> str:
    """The frame x/y are in: a ROS log's world frame (``map``, ``odom``) so predictions sit in its tf tree;
    ``world`` (the frame ingest's MCAP uses) otherwise."""
    if row["source_format"] in ORIGINAL_FORMATS:
        attrs = json.loads(row["attributes"] or "{}")
        frame = attrs.get("world_frame")
        if isinstance(frame, str) and frame:
            return frame
    return WORLD_FRAME


def _predictions_json(run: _Run, log_id: str, frame: str, p: _SamplePrediction) -> bytes:
    protocol = run.dataset.protocol
    current = p.sample.positions[p.targets, protocol.obs_len - 1]
    message = {
        "log_id": log_id,
        "sample_id": p.sample.sample_id,
        "timestamp_ns": int(p.row["current_ns"]),
        "frame_id": frame,
        "predictor": run.chosen.name,
        "checkpoint_id": run.chosen.checkpoint_id,
        "obs_len": protocol.obs_len,
        "pred_len": protocol.pred_len,
        "num_modes": run.modes,
        "step_timestamps_ns": p.step_ns.tolist(),
        "track_id": [p.sample.track_ids[i] for i in p.targets],
        "object_type": [OBJECT_TYPES[int(p.sample.object_types[i])] for i in p.targets],
        "current_x": np.ascontiguousarray(current[:, 0]),
        "current_y": np.ascontiguousarray(current[:, 1]),
        "score": np.ascontiguousarray(p.scores),
        "x": np.ascontiguousarray(p.futures[..., 0]),
        "y": np.ascontiguousarray(p.futures[..., 1]),
    }
    return dumps(message)
