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

Centre: ``centre="ego"`` uses the ego track at the sample's current step, falling back to the focal track
when the log has no ego (or the ego is not observed then); ``centre="focal"`` always uses the focal track.
Heading (``rotate=True``): the track's ``heading`` column at the current step when present, else the
direction of its own motion over the observed steps (``heading_from_motion``), else (a stationary agent)
the direction of the nearest lane centerline within 3 m; without any of these the raster is drawn north up
and the index says ``heading_source="none"``.
"""

from __future__ import annotations

import logging
import math
import re
import time
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pyarrow as pa

from logpipe.artifact import file_entry, output_errors
from logpipe.contracts import arrow_schema
from logpipe.dataset import Dataset
from logpipe.errors import DatasetError
from logpipe.executor import Backend, run_ordered
from logpipe.io import as_numpy, atomic_path, read_table, sha256_file, write_parquet
from logpipe.maps import MapSource, MapStore, load_map
from logpipe.progress import report_total
from logpipe.raster import Rasteriser, RasterSpec, direction_values, heading_from_motion
from logpipe.rasters import (
    CENTRES,
    LANE_HEADING_MAX_DIST_M,
    MIN_HEADING_DISP_M,
    RASTER_DIR,
    RasterRunWriter,
    index_file,
    inputs_tag,
    run_id,
    shard_file,
)
from logpipe.shards import log_slices
from logpipe.types import NDArrayByte, NDArrayFloat, NDArrayInt
from logpipe.windows import LogWindows

logger = logging.getLogger(__name__)

@dataclass
class _Centre:
    """Where one raster is centred.

    Attributes:
        track_id: the centre track, None when none was observed at the current step.
        role: ``ego`` or ``focal``.
        x, y: metres, world frame.
        heading: rad CCW from world +x, or None.
        heading_source: ``column`` | ``motion`` | ``none``.
    """

    track_id: str | None
    role: str | None
    x: float
    y: float
    heading: float | None
    heading_source: str


class _LogView:
    """One log's tracks for picking centres quickly: ``LogWindows``' per-track row lookups, roles and headings."""

    def __init__(self, tracks: pa.Table) -> None:
        self.windows = LogWindows(tracks)
        self.step, self.x, self.y = self.windows.steps, self.windows.x, self.windows.y
        self.role = as_numpy(tracks.column("role")).astype(str)
        head = tracks.column("heading")
        self.heading = np.asarray(as_numpy(head.fill_null(float("nan"))), dtype=np.float64)
        egos = [self.windows.names[c] for c in np.unique(self.windows.codes[self.windows.ego]).tolist()]
        self.ego: str | None = min(egos) if egos else None

    def rows(self, track_id: str, first: int, last: int) -> NDArrayInt:
        """Indices of the track's rows with ``first <= step <= last``, sorted by step."""
        return self.windows.track_rows(track_id, first, last)

    def centre(self, sample: dict[str, Any], rule: str, store: MapStore | None = None) -> _Centre | None:
        """The centre of one sample under ``rule`` (see module doc), or None when nobody is observed."""
        cur, start = int(sample["current_step"]), int(sample["start_step"])
        choices: list[tuple[str | None, str]] = []
        if rule == "ego" and self.ego is not None:
            choices.append((self.ego, "ego"))
        choices.append((sample.get("focal_track_id"), "focal"))
        for track_id, role in choices:
            if track_id is None:
                continue
            rows = self.rows(str(track_id), start, cur)
            if not len(rows) or self.step[rows[-1]] != cur:
                continue  # not observed at the current step
            last = rows[-1]
            h = float(self.heading[last])
            if math.isfinite(h):
                return _Centre(str(track_id), role, float(self.x[last]), float(self.y[last]), h, "column")
            xy = np.stack([self.x[rows], self.y[rows]], axis=1)
            hm = heading_from_motion(xy, MIN_HEADING_DISP_M)
            source = "motion" if hm is not None else "none"
            if hm is None and store is not None:
                # A stationary agent: take the direction of the lane it stands on (observed-time map data).
                hm = store.lane_direction_at(float(self.x[last]), float(self.y[last]), LANE_HEADING_MAX_DIST_M)
                source = "lane" if hm is not None else "none"
            return _Centre(str(track_id), role, float(self.x[last]), float(self.y[last]), hm, source)
        return None


def rasterise_dataset(
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
) -> dict[str, Any]:
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
    logs = ds.logs()
    log_map = dict(zip(logs.column("log_id").to_pylist(), logs.column("map_id").to_pylist(), strict=True))
    rid = run_id(spec, centre)
    out = ds.root / RASTER_DIR / rid

    # Identity of the inputs: the sample index bytes, every map file this run resolves to, and the shard size
    # (it decides which sample lands in which file).
    map_files: dict[str, Path | None] = {lid: maps.resolve(mid, lid) for lid, mid in log_map.items()}
    map_hashes = {str(p): sha256_file(p) for p in sorted({p for p in map_files.values() if p is not None})}
    identity = {"samples_sha256": ds.manifest["tables"]["samples"]["sha256"], "maps": map_hashes,
                "shard_size": shard_size}
    with output_errors(), RasterRunWriter(out) as writer:
        return _rasterise_locked(writer, ds, spec, centre, identity, map_files, map_hashes, preview,
                                 shard_size, force, progress, workers, backend, started)


def _rasterise_locked(
    writer: RasterRunWriter, ds: Dataset, spec: RasterSpec, centre: str, identity: dict[str, Any],
    map_files: dict[str, Path | None], map_hashes: dict[str, str], preview: int, shard_size: int, force: bool,
    progress: Callable[[int], None] | None, workers: int, backend: Backend, started: float,
) -> dict[str, Any]:
    """``rasterise_dataset`` while holding the run folder's lock: render the shards no commit names, committing
    the manifest after each (so an interrupted run resumes), the last commit marking the run complete."""
    out = writer.root
    rid = out.name
    committed = writer.committed_shards(identity, force)
    tag = inputs_tag(identity)
    samples = ds.samples()
    logs = ds.logs()
    log_map = dict(zip(logs.column("log_id").to_pylist(), logs.column("map_id").to_pylist(), strict=True))

    no_map = sorted(lid for lid, p in map_files.items() if p is None)
    n = samples.num_rows
    report_total(progress, n)
    n_shards = max(1, math.ceil(n / shard_size))
    rows = samples.to_pylist()
    summary: dict[str, Any] = {
        "run_dir": str(out),
        "run_id": rid,
        "spec": spec.to_dict(),
        "fingerprint": spec.fingerprint(),
        "centre": centre,
        "samples": n,
        "rendered": 0,
        "skipped_existing": 0,
        "empty": 0,
        "no_centre": 0,
        "logs_without_map": len(no_map),
        "logs_without_map_examples": no_map[:20],
        "heading_source": {"column": 0, "motion": 0, "lane": 0, "none": 0},
        "centre_role": {"ego": 0, "focal": 0},
        "previews": [],
    }
    shard_of = dict(zip(logs.column("log_id").to_pylist(), logs.column("shard").to_pylist(), strict=True))
    shard_meta: list[dict[str, Any]] = []
    tasks: list[_ShardTask] = []
    files: dict[str, Any] = {}
    for si in range(n_shards):
        chunk = rows[si * shard_size : (si + 1) * shard_size]
        npy = shard_file(si, tag)
        done = committed.get(npy)
        if done is not None and (si * shard_size >= preview or done["previews"]):
            summary["skipped_existing"] += len(chunk)
            shard_meta.append(done["entry"])
            files.update(done["files"])
            if progress:
                progress(len(chunk))
            continue
        shard_meta.append({})  # filled in order as the shard comes back
        log_ids = sorted({str(r["log_id"]) for r in chunk})
        tasks.append(
            _ShardTask(
                root=ds.root,
                out=out,
                shard=si,
                tag=tag,
                first=si * shard_size,
                samples=chunk,
                spec=spec,
                centre=centre,
                preview=preview,
                track_shards={lid: shard_of[lid] for lid in log_ids if lid in shard_of},
                map_ids={lid: log_map.get(lid) for lid in log_ids},
                map_files={lid: map_files.get(lid) for lid in log_ids},
                map_hashes=map_hashes,
            )
        )
    render_seconds = 0.0

    def manifest(complete: bool) -> dict[str, Any]:
        done = [m for m in shard_meta if m]
        return writer.manifest_of(spec, centre, identity, n, shard_size, done, files, complete,
                                  _index_counts(out, done) if complete else {})

    try:
        for res in run_ordered(_render_shard, tasks, workers=workers, backend=backend):
            shard_meta[res["shard"]] = res["entry"]
            files.update(res["files"])
            writer.commit(manifest(complete=False))
            render_seconds += res["render_seconds"]
            summary["rendered"] += res["rendered"]
            for key in ("empty", "no_centre"):
                summary[key] += res[key]
            for key in ("heading_source", "centre_role"):
                for k, v in res[key].items():
                    summary[key][k] += v
            summary["previews"].extend(res["previews"])
            if progress:
                progress(res["rendered"])
    finally:
        _WORKER_RASTERISERS.clear()  # inline runs: do not keep city maps alive after the stage
    if summary["empty"]:
        logger.warning(
            "%d of %d rasters are empty (centre off the map or no map); see `empty` in %s",
            summary["empty"],
            n,
            out / "index-*.parquet",
        )
    writer.commit(manifest(complete=True))
    summary["seconds"] = round(time.perf_counter() - started, 3)
    summary["render_seconds"] = round(render_seconds, 3)
    summary["rasters_per_s"] = round(summary["rendered"] / render_seconds, 1) if render_seconds > 0 else None
    return summary


@dataclass(frozen=True)
class _ShardTask:
    """One raster shard to render and write (picklable: sent to a worker process or Ray task).

    Attributes:
        root: dataset folder; ``out``: the run folder the shard goes into.
        shard: shard number; ``first``: sample number of its first row (previews are numbered by it).
        samples: the shard's sample-index rows.
        track_shards: track shard file of each of its logs; ``map_ids`` / ``map_files`` their map.
        map_hashes: sha256 of every map file of the run (workers cache maps by content).
    """

    root: Path
    out: Path
    shard: int
    tag: str
    first: int
    samples: list[dict[str, Any]]
    spec: RasterSpec
    centre: str
    preview: int
    track_shards: dict[str, str]
    map_ids: dict[str, str | None]
    map_files: dict[str, Path | None]
    map_hashes: dict[str, str]


_WORKER_RASTERISERS: OrderedDict[tuple[str, str], Rasteriser] = OrderedDict()
"""(map sha256, spec fingerprint) → rasteriser, kept by a worker process between shards (a city map takes
seconds to load and index); keyed by content so a changed map file is reloaded. At most 4, like
``MapSource``'s cache."""


def _worker_rasteriser(path: Path, sha: str, spec: RasterSpec) -> Rasteriser:
    key = (sha, spec.fingerprint())
    ras = _WORKER_RASTERISERS.get(key)
    if ras is None:
        ras = Rasteriser(load_map(path), spec)
        _WORKER_RASTERISERS[key] = ras
        while len(_WORKER_RASTERISERS) > 4:
            _WORKER_RASTERISERS.popitem(last=False)
    else:
        _WORKER_RASTERISERS.move_to_end(key)
    return ras


def _render_shard(task: _ShardTask) -> dict[str, Any]:
    """Render one shard, write its ``.npy`` and index, return its counts and manifest entry."""
    spec, out = task.spec, task.out
    npy, idx = out / shard_file(task.shard, task.tag), out / index_file(task.shard, task.tag)
    tracks = _TrackReader(task.root, task.track_shards)
    empty_rasteriser = Rasteriser(None, spec)
    counts: dict[str, Any] = {
        "shard": task.shard,
        "rendered": len(task.samples),
        "empty": 0,
        "no_centre": 0,
        "heading_source": {"column": 0, "motion": 0, "lane": 0, "none": 0},
        "centre_role": {"ego": 0, "focal": 0},
        "previews": [],
    }
    view_cache: tuple[str, _LogView] | None = None
    images = np.zeros((len(task.samples), *spec.shape), dtype=np.uint8)
    index_rows: list[dict[str, Any]] = []
    t0 = time.perf_counter()
    for row_i, sample in enumerate(task.samples):
        log_id = str(sample["log_id"])
        if view_cache is None or view_cache[0] != log_id:
            view_cache = (log_id, _LogView(tracks.get(log_id)))
        view = view_cache[1]
        map_path = task.map_files.get(log_id)
        ras = empty_rasteriser
        if map_path is not None:
            ras = _worker_rasteriser(map_path, task.map_hashes[str(map_path)], spec)
        c = view.centre(sample, task.centre, ras.store)
        if c is None:
            counts["no_centre"] += 1
            res = empty_rasteriser.render(0.0, 0.0, None, warn=False, out=images[row_i])
            cx: float | None = None
            cy: float | None = None
            src = "none"
        else:
            # Drawn straight into the shard row (zeroed by np.zeros): no per-raster allocation or copy.
            res = ras.render(c.x, c.y, c.heading, warn=False, out=images[row_i])
            cx, cy = c.x, c.y
            src = c.heading_source if spec.rotate else "none"
            counts["centre_role"][c.role or "focal"] += 1
        counts["heading_source"][src] += 1
        if res.empty:
            counts["empty"] += 1
        index_rows.append(
            {
                "sample_id": str(sample["sample_id"]),
                "log_id": log_id,
                "shard": npy.name,
                "row": row_i,
                "centre_track_id": c.track_id if c else None,
                "centre_role": c.role if c else None,
                "centre_x": cx,
                "centre_y": cy,
                "heading": res.heading,
                "heading_source": src,
                "affine": [float(v) for v in res.affine.reshape(-1)],
                "map_id": task.map_ids.get(log_id),
                "map_file": str(map_path) if map_path is not None else None,
                "empty": res.empty,
            }
        )
        k = task.first + row_i
        if k < task.preview and c is not None:
            png = out / "previews" / f"{k:05d}_{_safe(str(sample['sample_id']))}.png"
            _write_preview(png, res.image, res.affine, spec, view, sample, c)
            counts["previews"].append(str(png))
    counts["render_seconds"] = time.perf_counter() - t0
    with atomic_path(npy) as tmp, tmp.open("wb") as fh:
        np.save(fh, images, allow_pickle=False)
    write_parquet(pa.Table.from_pylist(index_rows, schema=arrow_schema("raster")), idx)
    counts["entry"] = _shard_entry(npy, idx, len(task.samples))
    counts["files"] = {npy.name: file_entry(npy), idx.name: file_entry(idx, rows=len(index_rows)),
                       **{f"previews/{Path(p).name}": file_entry(Path(p)) for p in counts["previews"]}}
    return counts


class _TrackReader:
    """A log's track rows, reading each track shard once (shards hold whole logs sorted by log id), instead
    of one filtered Parquet read per log."""

    def __init__(self, root: Path, shard_of: dict[str, str]) -> None:
        self.root = root
        self.shard_of = shard_of
        self._shard: str | None = None
        self._table: pa.Table | None = None
        self._slices: dict[str, tuple[int, int]] = {}

    def get(self, log_id: str) -> pa.Table:
        shard = self.shard_of.get(log_id)
        if shard is None:
            raise DatasetError(f"{self.root}: no log {log_id!r} in the logs table")
        if shard != self._shard:
            table = read_table(self.root / shard)
            self._slices = log_slices(table)
            self._shard, self._table = shard, table
        assert self._table is not None
        if log_id not in self._slices:
            raise DatasetError(f"{self.root}: log {log_id!r} missing from {shard}")
        start, end = self._slices[log_id]
        return self._table.slice(start, end - start)


def _index_counts(out: Path, shard_meta: list[dict[str, Any]]) -> dict[str, Any]:
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


def _shard_entry(npy: Path, idx: Path, rows: int) -> dict[str, Any]:
    return {"file": npy.name, "index": idx.name, "rows": rows, "sha256": sha256_file(npy)}


def _safe(name: str) -> str:
    return re.sub(r"[^A-Za-z0-9._-]+", "_", name)[:80]


# ---- previews ---------------------------------------------------------------------------------------------

_PREVIEW_SCALE = 3  # 224 px -> 672 px so tracks stay readable


def _write_preview(
    png: Path,
    image: NDArrayByte,
    affine: NDArrayFloat,
    spec: RasterSpec,
    view: _LogView,
    sample: dict[str, Any],
    centre: _Centre,
) -> None:
    """Colour composite of the raster with observed (solid) and future (dotted) tracks drawn over it."""
    ch = {name: image[i] for i, name in enumerate(spec.channels)}
    size = spec.size_px
    bgr = np.zeros((size, size, 3), np.float32)
    if "drivable_area" in ch:
        bgr += ch["drivable_area"][..., None].astype(np.float32) / 255.0 * np.array([60, 60, 60], np.float32)
    if "crossing" in ch:
        bgr += ch["crossing"][..., None].astype(np.float32) / 255.0 * np.array([120, 60, 0], np.float32)
    if "lane_boundary" in ch:
        bgr += ch["lane_boundary"][..., None].astype(np.float32) / 255.0 * np.array([0, 140, 170], np.float32)
    # Direction quadrants (BGR): up = green, down = blue, left = orange, right = magenta.
    quadrant_colours = {
        "lane_up": (80, 200, 80),
        "lane_down": (220, 120, 40),
        "lane_left": (40, 160, 255),
        "lane_right": (255, 80, 220),
    }
    for name, rgb in quadrant_colours.items():
        if name in ch:
            a = ch[name].astype(np.float32)[..., None] / 255.0
            bgr = bgr * (1 - a) + np.array(rgb, np.float32) * a
    if "lane_centerline" in ch:
        line = ch["lane_centerline"].astype(np.float32) / 255.0
        colour = np.full((size, size, 3), 200.0, np.float32)
        if "lane_direction" in ch:
            # Hue from the direction sector, so opposite lanes read as different colours.
            k = spec.direction_bins
            vals = direction_values(k)
            d = ch["lane_direction"]
            sector = np.argmin(np.abs(d[..., None].astype(np.int64) - vals[None, None, :]), axis=2)
            hsv = np.stack([(sector * 180 // k).astype(np.uint8), np.full_like(d, 200), np.full_like(d, 255)], axis=2)
            hue = cv2.cvtColor(hsv, cv2.COLOR_HSV2BGR).astype(np.float32)
            colour = np.where((d > 0)[..., None], hue, colour)
        bgr = bgr * (1 - line[..., None]) + colour * line[..., None]
    big = cv2.resize(
        np.clip(bgr, 0, 255).astype(np.uint8),
        None,
        fx=_PREVIEW_SCALE,
        fy=_PREVIEW_SCALE,
        interpolation=cv2.INTER_NEAREST,
    )
    start, cur, end = int(sample["start_step"]), int(sample["current_step"]), int(sample["end_step"])
    targets = {str(t) for t in sample.get("target_track_ids") or []}
    for track_id in view.windows.track_ids():
        rows = view.rows(track_id, start, end)
        if not len(rows):
            continue
        xy = np.stack([view.x[rows], view.y[rows]], axis=1)
        uv = (xy @ affine[:, :2].T + affine[:, 2] + 0.5) * _PREVIEW_SCALE
        obs = view.step[rows] <= cur
        role = view.role[rows[0]]
        # BGR: centre/ego cyan, focal/targets red, everyone else white.
        if track_id == centre.track_id or role == "ego":
            pen: tuple[int, int, int] = (255, 255, 0)
        elif track_id in targets or role == "focal":
            pen = (0, 0, 255)
        else:
            pen = (235, 235, 235)
        pts = np.round(uv * 16).astype(np.int32)
        if obs.sum() >= 2:
            cv2.polylines(big, [pts[obs]], False, pen, 2, cv2.LINE_AA, 4)
        for p in pts[~obs][::2]:
            cv2.circle(big, (int(p[0]), int(p[1])), 2 * 16, pen, -1, cv2.LINE_AA, 4)
        if obs.any():
            q = pts[obs][-1]
            cv2.circle(big, (int(q[0]), int(q[1])), 4 * 16, pen, 1, cv2.LINE_AA, 4)
    orient = f"heading={centre.heading_source}" if spec.rotate else "north up"
    label = f"{sample['sample_id']}  centre={centre.role}  {orient}"
    cv2.putText(big, label, (6, 18), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (255, 255, 255), 1, cv2.LINE_AA)
    png.parent.mkdir(parents=True, exist_ok=True)
    ok, buf = cv2.imencode(".png", big)
    if not ok:
        raise DatasetError(f"could not encode preview {png}")
    with atomic_path(png) as tmp:
        tmp.write_bytes(buf.tobytes())
