"""``logpipe rasterise``: one map raster per prediction sample, stored beside the sample index.

Layout (inside the dataset folder)::

    DATASET/rasters/<run_id>/
      manifest.json        spec (size, extent, channels, rotation, ...), its fingerprint, centre rule,
                           dataset and map identities, shards with rows and sha256; written last
      shard-00000.npy      uint8 (N, C, H, W), N <= shard_size samples in sample-index order
      index-00000.parquet  schemas/raster.json rows of that shard (sample_id -> shard, row, affine, ...)
      previews/*.png       with --preview N: raster + observed (solid) and future (dotted) tracks

``run_id`` hashes everything that changes pixels (the spec, the centre rule and the heading rule), so two
settings never share a folder and a reader asks for the settings it wants (``RasterShards.open``), which
fails loudly on a mismatch. Every file is written to a temporary name and renamed. A rerun skips shards
whose ``.npy`` and index are already there (they are deterministic), so it finishes interrupted work and
leaves finished work byte-identical.

Reads top-down: check the options and open the dataset → name the inputs (sample index, map files, shard size)
→ take the run folder's lock → one ``ShardTask`` per shard no commit names → render them on the executor
(``logpipe.raster.render``: centres and headings by ``logpipe.raster.centre``'s rules, previews by
``logpipe.raster.preview``), committing the manifest after each → the last commit marks the run complete.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import pyarrow as pa

from logpipe.dataset.reader import Dataset
from logpipe.errors import DatasetError
from logpipe.executor import Backend, run_ordered
from logpipe.maps import MapSource
from logpipe.progress import report_total
from logpipe.raster.coverage import blank_warnings, check_map_coverage
from logpipe.raster.rasteriser import RasterSpec
from logpipe.raster.render import ShardTask, clear_worker_cache, render_shard
from logpipe.raster.runs import (
    CENTRES,
    RASTER_DIR,
    CommittedShard,
    RasterRunCounts,
    RasterRunIdentity,
    RasterRunManifest,
    RasterRunWriter,
    RasterShardEntry,
    inputs_tag,
    run_id,
    shard_file,
)
from logpipe.storage.artifact import FileEntry, output_errors
from logpipe.storage.io import read_table, sha256_file
from logpipe.summaries import RasteriseSummary

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class _Job:
    """What one invocation renders, fixed before the lock is taken.

    Attributes:
        ds: the dataset; ``spec``, ``centre``: the run's settings; ``preview``: previews of the first N samples.
        identity: the inputs (sample index sha256, map file hashes, shard size), as the manifest records them.
        log_map: map id of each log; ``shard_of``: its track shard; ``map_files``: its map file (None: no map).
        map_hashes: sha256 of every map file, by path.
    """

    ds: Dataset
    spec: RasterSpec
    centre: str
    preview: int
    shard_size: int
    identity: RasterRunIdentity
    log_map: dict[str, str | None]
    shard_of: dict[str, str]
    map_files: dict[str, Path | None]
    map_hashes: dict[str, str]


def rasterise_dataset(  # noqa: PLR0913  public API: the command's options one to one
    dataset_dir: Path,
    maps: MapSource,
    centre: str = "ego",
    rotate: bool = False,
    preview: int = 0,
    *,
    spec: RasterSpec | None = None,
    shard_size: int = 256,
    force: bool = False,
    progress: Callable[[int], None] | None = None,
    workers: int = 1,
    backend: Backend = "local",
) -> RasteriseSummary:
    """Rasterise every sample of an ingested dataset.

    Args:
        dataset_dir: folder written by ``logpipe ingest``.
        maps: where to find each log's map (``MapSource(roots=...)``).
        centre: ``ego`` (ego, else focal) or ``focal``.
        rotate: rotate rasters to the centre's heading (overrides ``spec.rotate``).
        preview: write PNG previews of the first ``preview`` samples.
        spec: raster parameters (default ``RasterSpec()``: 224 px, 100 m, ``DEFAULT_CHANNELS``).
        shard_size: samples per ``.npy`` shard; one shard is held in memory while written
            (256 x 343 KiB with the default 7 channels).
        force: delete an existing run folder with the same settings that belongs to other data or maps.
        progress: called with the number of samples each finished shard covered.
        workers: shards rendered at once (0 = all cores); each worker process loads the maps it needs.
        backend: ``local`` (inline or a process pool) or ``ray`` (the run folder must be on a file system
            every node shares). Shards are written by the workers and are the same bytes either way.

    Returns:
        A JSON-able summary (run folder, spec, counts, timings, previews).

    Raises:
        DatasetError: not a dataset, bad ``centre``, or a stale run folder (different dataset or maps).
    """
    if centre not in CENTRES:
        raise DatasetError(f"--centre must be one of {CENTRES}, got {centre!r}")
    started = time.perf_counter()
    spec = RasterSpec(**{**_spec_kwargs(spec or RasterSpec()), "rotate": rotate})
    ds = Dataset.open(dataset_dir)
    maps = replace(maps, own={**ds.own_maps(), **maps.own})  # logs whose input carried their map use it
    logs = ds.logs()
    log_ids = logs.column("log_id").to_pylist()
    log_map = dict(zip(log_ids, logs.column("map_id").to_pylist(), strict=True))
    out = ds.root / RASTER_DIR / run_id(spec, centre)

    # Identity of the inputs: the sample index bytes, every map file this run resolves to, and the shard size
    # (it decides which sample lands in which file).
    map_files: dict[str, Path | None] = {lid: maps.resolve(mid, lid) for lid, mid in log_map.items()}
    check_map_coverage(ds.root, maps, log_map, map_files)
    map_hashes = {str(p): sha256_file(p) for p in sorted({p for p in map_files.values() if p is not None})}
    identity: RasterRunIdentity = {"samples_sha256": ds.manifest["tables"]["samples"]["sha256"], "maps": map_hashes,
                                   "shard_size": shard_size}
    job = _Job(ds, spec, centre, preview, shard_size, identity, log_map,
               dict(zip(log_ids, logs.column("shard").to_pylist(), strict=True)), map_files, map_hashes)
    with output_errors(), RasterRunWriter(out) as writer:
        return _rasterise_locked(writer, job, force, progress, workers, backend, started)


def _rasterise_locked(writer: RasterRunWriter, job: _Job, force: bool, progress: Callable[[int], None] | None,
                      workers: int, backend: Backend, started: float) -> RasteriseSummary:
    """``rasterise_dataset`` while holding the run folder's lock: render the shards no commit names, committing
    the manifest after each (so an interrupted run resumes), the last commit marking the run complete."""
    out = writer.root
    committed = writer.committed_shards(job.identity, force)
    samples = job.ds.samples()
    n = samples.num_rows
    report_total(progress, n)
    no_map = sorted(lid for lid, p in job.map_files.items() if p is None)
    summary: RasteriseSummary = {
        "run_dir": str(out),
        "run_id": out.name,
        "spec": job.spec.to_dict(),
        "fingerprint": job.spec.fingerprint(),
        "centre": job.centre,
        "samples": n,
        "rendered": 0,
        "skipped_existing": 0,
        "empty": 0,
        "no_centre": 0,
        "blank_with_map": 0,
        "warnings": [],
        "logs_without_map": len(no_map),
        "logs_without_map_examples": no_map[:20],
        "heading_source": {"column": 0, "motion": 0, "lane": 0, "none": 0},
        "centre_role": {"ego": 0, "focal": 0, "target": 0},
        "road_vehicles": {"observed": 0, "on_drivable": 0, "share": None},
        "previews": [],
    }
    # One per shard: committed entries now, new ones as they come back (None until then).
    shard_meta: list[RasterShardEntry | None] = []
    files: dict[str, FileEntry] = {}
    tasks = _plan(job, out, samples.to_pylist(), committed, shard_meta, files, summary, progress)
    render_seconds = 0.0

    def manifest(complete: bool) -> RasterRunManifest:
        done = [m for m in shard_meta if m is not None]
        return writer.manifest_of(job.spec, job.centre, job.identity, n, job.shard_size, done, files, complete,
                                  _index_counts(out, done) if complete else {})

    try:
        for res in run_ordered(render_shard, tasks, workers=workers, backend=backend):
            shard_meta[res["shard"]] = res["entry"]
            files.update(res["files"])
            writer.commit(manifest(complete=False))
            render_seconds += res["render_seconds"]
            _add_counts(summary, res)
            if progress:
                progress(res["rendered"])
    finally:
        clear_worker_cache()  # inline runs: do not keep city maps alive after the stage
    for warning in blank_warnings(summary, n, out):
        logger.warning("%s", warning)
    writer.commit(manifest(complete=True))
    summary["seconds"] = round(time.perf_counter() - started, 3)
    summary["render_seconds"] = round(render_seconds, 3)
    summary["rasters_per_s"] = round(summary["rendered"] / render_seconds, 1) if render_seconds > 0 else None
    return summary


def _plan(job: _Job, out: Path, rows: list[dict[str, Any]], committed: dict[str, CommittedShard],
          shard_meta: list[RasterShardEntry | None], files: dict[str, FileEntry], summary: RasteriseSummary,
          progress: Callable[[int], None] | None) -> list[ShardTask]:
    """The tasks of the shards still to render. Committed shards (with their previews, when they fall in
    ``--preview``) are counted as skipped and their entries and files appended to ``shard_meta`` / ``files``;
    each shard to render gets a None placeholder there, filled in order as its result comes back."""
    tag = inputs_tag(job.identity)
    tasks: list[ShardTask] = []
    for si in range(max(1, math.ceil(len(rows) / job.shard_size))):
        chunk = rows[si * job.shard_size : (si + 1) * job.shard_size]
        done = committed.get(shard_file(si, tag))
        if done is not None and (si * job.shard_size >= job.preview or done["previews"]):
            summary["skipped_existing"] += len(chunk)
            shard_meta.append(done["entry"])
            files.update(done["files"])
            if progress:
                progress(len(chunk))
            continue
        shard_meta.append(None)
        log_ids = sorted({str(r["log_id"]) for r in chunk})
        tasks.append(ShardTask(
            root=job.ds.root, out=out, shard=si, tag=tag, first=si * job.shard_size, samples=chunk, spec=job.spec,
            centre=job.centre, preview=job.preview,
            track_shards={lid: job.shard_of[lid] for lid in log_ids if lid in job.shard_of},
            map_ids={lid: job.log_map.get(lid) for lid in log_ids},
            map_files={lid: job.map_files.get(lid) for lid in log_ids},
            map_hashes=job.map_hashes,
        ))
    return tasks


def _add_counts(summary: RasteriseSummary, res: dict[str, Any]) -> None:
    """Add one rendered shard's counts and previews (``render_shard``'s result) to the summary."""
    summary["rendered"] += res["rendered"]
    summary["empty"] += res["empty"]
    summary["no_centre"] += res["no_centre"]
    summary["blank_with_map"] += res["blank_with_map"]
    for k, v in res["heading_source"].items():
        summary["heading_source"][k] += v
    for k, v in res["centre_role"].items():
        summary["centre_role"][k] += v
    road = summary["road_vehicles"]
    road["observed"] += res["road_vehicles"][0]
    road["on_drivable"] += res["road_vehicles"][1]
    road["share"] = round(road["on_drivable"] / road["observed"], 4) if road["observed"] else None
    summary["previews"].extend(res["previews"])


def _index_counts(out: Path, shard_meta: list[RasterShardEntry]) -> RasterRunCounts:
    """Counts over the whole run's index (not just this invocation), so the manifest is the same however
    many reruns it took to finish."""
    index = pa.concat_tables([read_table(out / s["index"]) for s in shard_meta])

    def tally(col: str) -> dict[str, int]:
        vals = [v if v is not None else "null" for v in index.column(col).to_pylist()]
        return {k: vals.count(k) for k in sorted(set(vals))}

    return {
        "empty": int(sum(index.column("empty").to_pylist())),
        "no_centre": index.column("centre_track_id").null_count,
        "heading_source": tally("heading_source"),
        "centre_role": tally("centre_role"),
    }


def _spec_kwargs(spec: RasterSpec) -> dict[str, Any]:
    return {
        "size_px": spec.size_px,
        "extent_m": spec.extent_m,
        "channels": spec.channels,
        "rotate": spec.rotate,
        "direction_bins": spec.direction_bins,
        "shift": spec.shift,
    }
