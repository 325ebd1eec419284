"""Canonical HD-map store: one map as an Arrow table, with per-kind spatial layers for fast lookups.

Every map adapter produces a ``MapStore`` (through ``MapBuilder``): one Arrow table in ``schemas/map.json`` (a
row per polyline or polygon, with kind, id and optional lane attributes) plus flat NumPy geometry. Geometry lives
in the map's world frame (metres). The spatial index each kind is queried through is ``grid_index.Layer``.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt
import pyarrow as pa
import pyarrow.parquet as pq

from logpipe.contracts import arrow_schema, conform
from logpipe.errors import DatasetError
from logpipe.maps.feature_kinds import KINDS, POLYGON_KINDS, FeatureKind
from logpipe.maps.grid_index import DEFAULT_CELL_M, Layer, chain_polylines
from logpipe.storage.artifact import FileEntry, file_entry
from logpipe.storage.io import write_parquet
from logpipe.types import NDArrayFloat, NDArrayInt

# Attribute columns an adapter may fill (everything in schemas/map.json except geometry and bookkeeping).
ATTRIBUTE_COLUMNS: tuple[str, ...] = (
    "lane_id",
    "side",
    "direction",
    "is_intersection",
    "turn_direction",
    "has_traffic_control",
    "lane_type",
    "mark_type",
    "left_neighbor_id",
    "right_neighbor_id",
    "predecessors",
    "successors",
)

MAP_COORD_LIMIT_M = 1e7
"""Largest |x| or |y| of a map vertex, in metres (10,000 km: above any UTM northing or city frame)."""


def map_schema() -> pa.Schema:
    """Arrow schema of the map store (``schemas/map.json``)."""
    return arrow_schema("map")


@dataclass
class MapBuilder:
    """Collects features from an adapter and turns them into a ``MapStore``.

    Attributes:
        map_id: city or map name written into every row.
        source: adapter name written into every row (``argoverse1_npz``, ``av2_json``, ...).
    """

    map_id: str
    source: str
    _rows: list[dict[str, Any]] = field(default_factory=list)

    def add(
        self,
        kind: FeatureKind,
        feature_id: str,
        xy: npt.ArrayLike,
        *,
        derived: bool = False,
        **attributes: Any,
    ) -> None:
        """Add one feature.

        Args:
            kind: what the feature is.
            feature_id: id unique within (map, kind).
            xy: (n, 2) vertices in metres, map world frame; polylines need n >= 2, polygons n >= 3.
            derived: the geometry was computed by logpipe rather than read.
            attributes: values for ``ATTRIBUTE_COLUMNS`` (unknown keys are an error).
        """
        pts = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        if kind in POLYGON_KINDS and len(pts) > 3 and np.array_equal(pts[0], pts[-1]):
            pts = pts[:-1]  # store open rings; the renderer closes them
        need = 3 if kind in POLYGON_KINDS else 2
        # Every map format's one plausibility check: NaN, inf, 1e400 or 1e300 in a vertex is damage, an error
        # naming the feature (not a feature silently dropped, nor an OverflowError in the grid index later).
        bad = ~(np.abs(pts) < MAP_COORD_LIMIT_M)
        if bad.any():
            value = pts.reshape(-1)[int(np.flatnonzero(bad.reshape(-1))[0])]
            raise ValueError(f"{kind} {str(feature_id)[:60]!r}: vertex coordinate {value!r} is not finite or beyond "
                             f"{MAP_COORD_LIMIT_M:.0e} m")
        if len(pts) < need:
            return  # degenerate geometry cannot be drawn; adapters count what they keep
        unknown = set(attributes) - set(ATTRIBUTE_COLUMNS)
        if unknown:
            raise ValueError(f"unknown map attributes {sorted(unknown)}")
        row: dict[str, Any] = {
            "map_id": self.map_id,
            "feature_id": str(feature_id),
            "kind": str(kind),
            "xs": pts[:, 0],
            "ys": pts[:, 1],
            "derived": derived,
            "source": self.source,
        }
        row.update(attributes)
        self._rows.append(row)

    def __len__(self) -> int:
        return len(self._rows)

    def build(self) -> MapStore:
        """The store, rows sorted by (kind, feature_id) so the same input always gives the same table."""
        kind_rank = {str(k): i for i, k in enumerate(KINDS)}
        rows = sorted(self._rows, key=lambda r: (kind_rank[r["kind"]], _id_key(r["feature_id"])))
        schema = map_schema()
        columns: dict[str, Any] = {}
        for f in schema:
            if f.name in ("xs", "ys"):
                columns[f.name] = pa.array([r[f.name] for r in rows], type=f.type)
            else:
                columns[f.name] = pa.array([r.get(f.name) for r in rows], type=f.type)
        table = pa.table(columns, schema=schema)
        return MapStore(table)


def _id_key(feature_id: str) -> tuple[int, int, str]:
    # Numeric ids sort numerically (AV1/AV2 lane ids), everything else lexically after them.
    head = feature_id.split(":", 1)[0]
    if head.lstrip("-").isdigit():
        return (0, int(head), feature_id)
    return (1, 0, feature_id)


class MapStore:
    """One map: the canonical Arrow table plus per-kind spatial layers built on first use.

    Attributes:
        table: rows in ``schemas/map.json``.
        map_id: the map's name (all rows share it).
    """

    def __init__(self, table: pa.Table, *, cell: float = DEFAULT_CELL_M) -> None:
        self.table = conform(table, map_schema())
        ids = self.table.column("map_id").unique().to_pylist()
        if len(ids) > 1:
            raise DatasetError(f"a map store holds one map, found {ids}")
        self.map_id: str = ids[0] if ids else ""
        self.cell = cell
        xs = self.table.column("xs").combine_chunks()
        ys = self.table.column("ys").combine_chunks()
        self._offsets: NDArrayInt = np.asarray(xs.offsets, dtype=np.int64) - int(xs.offsets[0].as_py())
        self._points: NDArrayFloat = np.stack(
            [np.asarray(xs.flatten(), dtype=np.float64), np.asarray(ys.flatten(), dtype=np.float64)], axis=1
        ).reshape(-1, 2)
        kinds = np.asarray(self.table.column("kind").to_numpy(zero_copy_only=False), dtype=object)
        self._kind_rows: dict[FeatureKind, NDArrayInt] = {
            k: np.nonzero(kinds == str(k))[0].astype(np.int64) for k in KINDS
        }
        self._layers: dict[FeatureKind, Layer] = {}
        self._render_layers: dict[FeatureKind, Layer] = {}

    # ---- construction and IO -------------------------------------------------------------------------

    @classmethod
    def read(cls, path: Path) -> MapStore:
        """Load a store written by ``write``."""
        return cls(pq.read_table(path))

    def write(self, path: Path) -> None:
        """Write the table as Parquet, atomically and byte-reproducibly."""
        write_parquet(self.table, path)

    # ---- plain accessors -----------------------------------------------------------------------------

    def __len__(self) -> int:
        return int(self.table.num_rows)

    def geometry(self, row: int) -> NDArrayFloat:
        """(n, 2) vertices of table row ``row``, metres, world frame."""
        return self._points[self._offsets[row] : self._offsets[row + 1]]

    def rows(self, kind: FeatureKind) -> NDArrayInt:
        """Table rows of one kind."""
        return self._kind_rows[kind]

    def counts(self) -> dict[str, int]:
        """Number of features per kind."""
        return {str(k): len(v) for k, v in self._kind_rows.items()}

    @property
    def bounds(self) -> tuple[float, float, float, float]:
        """(xmin, ymin, xmax, ymax) of all vertices, metres; zeros for an empty map."""
        if not len(self._points):
            return (0.0, 0.0, 0.0, 0.0)
        lo = self._points.min(axis=0)
        hi = self._points.max(axis=0)
        return (float(lo[0]), float(lo[1]), float(hi[0]), float(hi[1]))

    def feature_ids(self, rows: Iterable[int]) -> list[str]:
        """``feature_id`` of the given table rows."""
        col = self.table.column("feature_id")
        return [str(col[int(r)].as_py()) for r in rows]

    # ---- spatial -------------------------------------------------------------------------------------

    def layer(self, kind: FeatureKind) -> Layer:
        """The indexed layer of one kind (built once, on first use)."""
        layer = self._layers.get(kind)
        if layer is None:
            rows = self._kind_rows[kind]
            layer = Layer(kind, [self.geometry(int(r)) for r in rows], rows.tolist(), self.cell)
            self._layers[kind] = layer
        return layer

    def render_layer(self, kind: FeatureKind) -> Layer:
        """The layer the rasteriser draws: like ``layer`` but polylines that continue one another (one
        feature ends exactly where exactly one other starts, e.g. a lane and its only successor) are
        joined into chains before chunking. The drawn segments are identical; there are about a quarter
        fewer, longer chunks, and OpenCV's per-polyline overhead dominates drawing. A chunk's
        ``features`` entry is the first feature of its chain.
        """
        if kind in POLYGON_KINDS:
            return self.layer(kind)
        layer = self._render_layers.get(kind)
        if layer is None:
            rows = self._kind_rows[kind].tolist()
            chains = chain_polylines([self.geometry(r) for r in rows])
            layer = Layer(kind, [g for g, _ in chains], [rows[i] for _, i in chains], self.cell)
            self._render_layers[kind] = layer
        return layer

    def query(self, kind: FeatureKind, xmin: float, ymin: float, xmax: float, ymax: float) -> NDArrayInt:
        """Table rows of ``kind`` with a chunk whose bounding box overlaps the box (metres, world frame),
        ascending. Chunk boxes are tighter than a whole feature's box, so a long curved lane whose box
        merely covers the query is not returned."""
        layer = self.layer(kind)
        return np.unique(layer.features[layer.overlapping(xmin, ymin, xmax, ymax)])

    def distance_to(self, kind: FeatureKind, xy: npt.ArrayLike, max_dist: float = 10.0) -> NDArrayFloat:
        """Distance in metres from each query point to the nearest polyline of ``kind`` (segments, not just
        vertices); ``inf`` when none is within ``max_dist``. Polygons are measured to their outline."""
        q = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        out = np.full(len(q), np.inf)
        if not len(q):
            return out
        layer = self.layer(kind)
        lo = q.min(axis=0) - max_dist
        hi = q.max(axis=0) + max_dist
        idx = layer.overlapping(float(lo[0]), float(lo[1]), float(hi[0]), float(hi[1]))
        if not len(idx):
            return out
        a_list, b_list = [], []
        for i in idx.tolist():
            p = layer.points[layer.offsets[i] : layer.offsets[i + 1]]
            if kind in POLYGON_KINDS:
                p = np.vstack([p, p[:1]])
            a_list.append(p[:-1])
            b_list.append(p[1:])
        a = np.concatenate(a_list)
        b = np.concatenate(b_list)
        ab = b - a
        denom = np.maximum((ab**2).sum(axis=1), 1e-12)
        for s in range(0, len(q), 256):  # bounded memory: 256 points x all nearby segments at a time
            qq = q[s : s + 256, None, :]
            t = np.clip(((qq - a) * ab).sum(axis=2) / denom, 0.0, 1.0)
            d = np.sqrt((((a + t[..., None] * ab) - qq) ** 2).sum(axis=2)).min(axis=1)
            out[s : s + 256] = np.where(d <= max_dist, d, np.inf)
        return out

    def lane_direction_at(self, x: float, y: float, max_dist: float = 3.0) -> float | None:
        """Travel direction (rad, CCW from world +x) of the centerline segment nearest to (x, y), or None
        when no centerline is within ``max_dist`` metres. Used as the heading of a stationary agent."""
        layer = self.render_layer(FeatureKind.LANE_CENTERLINE)  # same segments; the rasteriser built it
        idx = layer.overlapping(x - max_dist, y - max_dist, x + max_dist, y + max_dist)
        best, best_d = None, max_dist
        q = np.array([x, y])
        for i in idx.tolist():
            p = layer.points[layer.offsets[i] : layer.offsets[i + 1]]
            a, ab = p[:-1], np.diff(p, axis=0)
            t = np.clip(((q - a) * ab).sum(axis=1) / np.maximum((ab**2).sum(axis=1), 1e-12), 0.0, 1.0)
            d = np.hypot(*(a + t[:, None] * ab - q).T)
            j = int(np.argmin(d))
            if d[j] <= best_d:
                best_d, best = float(d[j]), float(math.atan2(ab[j, 1], ab[j, 0]))
        return best

    def is_empty_near(self, x: float, y: float, radius: float) -> bool:
        """True when no feature of any kind has a bounding box within ``radius`` metres of (x, y)."""
        return all(not len(self.layer(k).overlapping(x - radius, y - radius, x + radius, y + radius)) for k in KINDS)


def write_stores(stores: dict[str, MapStore], root: Path, folder: str) -> dict[str, FileEntry]:
    """Write each store to ``root/folder/<name>.parquet`` (a folder nobody reads yet: ingest's staging); returns
    the files' entries by path relative to ``root``."""
    files: dict[str, FileEntry] = {}
    for name, store in sorted(stores.items()):
        rel = f"{folder}/{name}.parquet"
        store.write(root / rel)
        files[rel] = file_entry(root / rel)
    return files
