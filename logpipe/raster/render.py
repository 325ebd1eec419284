"""One raster shard, the unit of work of ``logpipe rasterise``: render its samples and write its files.

``render_shard`` runs wherever the executor puts it (inline, a pool process or a Ray task): it takes a picklable
``ShardTask``, reads the shard's logs from the track shards, draws each sample's raster straight into the shard
array, writes ``shard-TAG-NNNNN.npy``, ``index-TAG-NNNNN.parquet`` (``schemas/raster.json``) and the previews
that fall in it, and returns counts plus the manifest entries the stage commits. Each file is written to a
temporary name and renamed. A worker keeps the last few map rasterisers between shards (``clear_worker_cache``
drops them).
"""

from __future__ import annotations

import re
import time
from collections import OrderedDict
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa

from logpipe.contracts import arrow_schema
from logpipe.dataset.shards import log_slices
from logpipe.errors import DatasetError
from logpipe.maps import load_map
from logpipe.raster.centre import LogView
from logpipe.raster.preview import write_preview
from logpipe.raster.rasteriser import Rasteriser, RasterSpec
from logpipe.raster.runs import index_file, shard_file
from logpipe.storage.artifact import file_entry
from logpipe.storage.io import atomic_path, read_table, sha256_file, write_parquet
from logpipe.types import OBJECT_TYPES, NDArrayByte, NDArrayFloat


@dataclass(frozen=True)
class ShardTask:
    """One raster shard to render and write (picklable: sent to a worker process or Ray task).

    Attributes:
        root: dataset folder; ``out``: the run folder the shard goes into.
        shard: shard number; ``tag``: the run's inputs tag (in the file names); ``first``: sample number of its
            first row (previews are numbered by it).
        samples: the shard's sample-index rows.
        spec, centre: the run's raster spec and centre rule; ``preview``: previews of samples numbered below it.
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


def clear_worker_cache() -> None:
    """Drop this process's cached rasterisers (inline runs: do not keep city maps alive after the stage)."""
    _WORKER_RASTERISERS.clear()


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


def render_shard(task: ShardTask) -> dict[str, Any]:
    """Render one shard, write its ``.npy`` and index.

    Returns:
        ``shard``, ``rendered`` (samples), ``empty``, ``no_centre``, ``heading_source`` and ``centre_role``
        counts, ``previews`` (PNG paths),
        ``render_seconds``, ``entry`` (the run manifest's shard entry) and ``files`` (manifest file entries by
        path in the run folder).
    """
    spec, out = task.spec, task.out
    npy, idx = out / shard_file(task.shard, task.tag), out / index_file(task.shard, task.tag)
    tracks = _TrackReader(task.root, task.track_shards)
    empty_rasteriser = Rasteriser(None, spec)
    counts: dict[str, Any] = {
        "shard": task.shard,
        "rendered": len(task.samples),
        "empty": 0,
        "no_centre": 0,
        "blank_with_map": 0,
        "heading_source": {"column": 0, "motion": 0, "lane": 0, "none": 0},
        "centre_role": {"ego": 0, "focal": 0, "target": 0},
        "road_vehicles": [0, 0],
        "previews": [],
    }
    view_cache: tuple[str, LogView] | None = None
    images = np.zeros((len(task.samples), *spec.shape), dtype=np.uint8)
    index_rows: list[dict[str, Any]] = []
    t0 = time.perf_counter()
    for row_i, sample in enumerate(task.samples):
        log_id = str(sample["log_id"])
        if view_cache is None or view_cache[0] != log_id:
            view_cache = (log_id, LogView(tracks.get(log_id)))
        # Drawn straight into the shard row (zeroed by np.zeros): no per-raster allocation or copy.
        index_rows.append(_render_row(task, view_cache[1], sample, row_i, images[row_i], empty_rasteriser, counts))
    counts["render_seconds"] = time.perf_counter() - t0
    with atomic_path(npy) as tmp, tmp.open("wb") as fh:
        np.save(fh, images, allow_pickle=False)
    write_parquet(pa.Table.from_pylist(index_rows, schema=arrow_schema("raster")), idx)
    counts["entry"] = {"file": npy.name, "index": idx.name, "rows": len(task.samples), "sha256": sha256_file(npy)}
    counts["files"] = {npy.name: file_entry(npy), idx.name: file_entry(idx, rows=len(index_rows)),
                       **{f"previews/{Path(p).name}": file_entry(Path(p)) for p in counts["previews"]}}
    return counts


def _render_row(task: ShardTask, view: LogView, sample: dict[str, Any], row_i: int, image: NDArrayByte,
                empty_rasteriser: Rasteriser, counts: dict[str, Any]) -> dict[str, Any]:
    """Draw one sample into ``image`` (its shard row), count it, write its preview if it gets one; returns its
    index row."""
    log_id = str(sample["log_id"])
    map_path = task.map_files.get(log_id)
    ras = empty_rasteriser
    if map_path is not None:
        ras = _worker_rasteriser(map_path, task.map_hashes[str(map_path)], task.spec)
    c = view.centre(sample, task.centre, ras.store)
    if c is None:
        counts["no_centre"] += 1
        res = empty_rasteriser.render(0.0, 0.0, None, warn=False, out=image)
        src = "none"
    else:
        res = ras.render(c.x, c.y, c.heading, warn=False, out=image)
        src = c.heading_source if task.spec.rotate else "none"
        counts["centre_role"][c.role or "focal"] += 1
        seen, on_road = _road_vehicles(task.spec, view, sample, image, res.affine)
        counts["road_vehicles"][0] += seen
        counts["road_vehicles"][1] += on_road
    counts["heading_source"][src] += 1
    if res.empty:
        counts["empty"] += 1
        if map_path is not None:  # the log has a map, yet nothing of it is drawn: worth a line in the summary
            counts["blank_with_map"] += 1
    k = task.first + row_i
    if k < task.preview and c is not None:
        png = task.out / "previews" / f"{k:05d}_{_safe(str(sample['sample_id']))}.png"
        write_preview(png, res.image, res.affine, task.spec, view, sample, c)
        counts["previews"].append(str(png))
    return {
        "sample_id": str(sample["sample_id"]),
        "log_id": log_id,
        "shard": shard_file(task.shard, task.tag),
        "row": row_i,
        "centre_track_id": c.track_id if c else None,
        "centre_role": c.role if c else None,
        "centre_x": c.x if c else None,
        "centre_y": c.y if c else None,
        "heading": res.heading,
        "heading_source": src,
        "affine": [float(v) for v in res.affine.reshape(-1)],
        "map_id": task.map_ids.get(log_id),
        "map_file": str(map_path) if map_path is not None else None,
        "empty": res.empty,
    }


def _safe(name: str) -> str:
    """``name`` as a file-name part: runs of other characters than ``[A-Za-z0-9._-]`` become ``_``, at most 80."""
    return re.sub(r"[^A-Za-z0-9._-]+", "_", name)[:80]


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
        """The log's rows of its track shard (``DatasetError`` when the logs table or the shard lacks it)."""
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


ROAD_VEHICLE_TYPES = tuple(OBJECT_TYPES.index(t) for t in ("vehicle", "bus_truck", "motorcyclist"))
"""Codes of the agents that belong on the road (``RasteriseSummary.road_vehicles``); cyclists and pedestrians may
use paths the map does not draw."""


def _road_vehicles(spec: RasterSpec, view: LogView, sample: dict[str, Any], image: NDArrayByte,
                   affine: NDArrayFloat) -> tuple[int, int]:
    """(observed positions of road vehicles inside the raster, how many of them are on drivable pixels) over the
    sample's observed steps: a check that map and tracks share a frame (a pixel counts as drivable when at least
    half covered: value >= 128 of the anti-aliased fill). (0, 0) without a ``drivable_area`` channel or where the
    raster has no drivable pixel at all (a map without drivable areas: AV1's centerline files)."""
    if "drivable_area" not in spec.channels:
        return 0, 0
    drivable = image[spec.channels.index("drivable_area")]
    if not drivable.any():
        return 0, 0  # a map without drivable areas (AV1 centerlines) or none here: nothing to check against
    w = view.windows
    lo, hi = w.span(int(sample["start_step"]), int(sample["current_step"]))
    rows = lo + np.flatnonzero(np.isin(w.types[lo:hi], ROAD_VEHICLE_TYPES))
    uv = np.rint(np.stack([w.x[rows], w.y[rows]], axis=1) @ affine[:, :2].T + affine[:, 2]).astype(np.int64)
    size = spec.size_px
    inside = (uv >= 0).all(axis=1) & (uv < size).all(axis=1)
    return int(inside.sum()), int((drivable[uv[inside, 1], uv[inside, 0]] >= 128).sum())
