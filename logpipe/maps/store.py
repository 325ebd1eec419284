"""Canonical HD-map store and its spatial index.

Every map adapter produces a ``MapStore``: one Arrow table in ``schemas/map.json`` (a row per polyline or
polygon, with kind, id and optional lane attributes) plus flat NumPy geometry for fast lookups.

Geometry lives in the map's world frame (metres). The index is per kind (``Layer``): features are bucketed
into a uniform grid by the centre of their bounding box and stored contiguously in cell order, so a window
query is a handful of ``searchsorted`` calls and contiguous slices instead of a scan of the city. Polylines
longer than one cell are cut into chunks that share their end vertex (the segments drawn are unchanged);
the few polygons larger than a cell (AV2 drivable areas) sit in an "oversize" list tested by bounding box.
"""

from __future__ import annotations

import bisect
import math
from array import array
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from enum import StrEnum
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt
import pyarrow as pa
import pyarrow.parquet as pq

from logpipe.contracts import arrow_schema, conform
from logpipe.errors import DatasetError
from logpipe.io import write_parquet
from logpipe.types import NDArrayBool, NDArrayFloat, NDArrayInt


class FeatureKind(StrEnum):
    """What a map feature is; polylines (centerlines, boundaries) versus polygons (areas)."""

    LANE_CENTERLINE = "lane_centerline"
    LANE_BOUNDARY = "lane_boundary"
    DRIVABLE_AREA = "drivable_area"
    CROSSING = "crossing"


KINDS: tuple[FeatureKind, ...] = tuple(FeatureKind)
POLYGON_KINDS: frozenset[FeatureKind] = frozenset({FeatureKind.DRIVABLE_AREA, FeatureKind.CROSSING})

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

MAX_TURN_DEG = 30.0
"""Centerline chunks turn by at most this much, so one direction per chunk describes every segment."""

DEFAULT_CELL_M = 32.0
"""Grid cell edge in metres: about the median AV1 lane length x 2, so few lanes are cut into chunks."""

MAX_DENSE_CELLS = 1 << 22
"""Grids up to this many cells (32 MiB of starts; a 65 km square city at 32 m) get a dense per-cell start
table, so a window row is two lookups; larger (sparse, far-flung) maps fall back to bisecting the keys."""


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
        if len(pts) < need or not np.isfinite(pts).all():
            return  # degenerate or broken geometry cannot be drawn; adapters count what they keep
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


@dataclass(frozen=True)
class Window:
    """Geometry of one kind that may intersect a query box (a superset: callers clip or test further).

    Attributes:
        points: (n, 2) vertices, metres, world frame; features are stored back to back.
        offsets: (k + 1,) feature ``i`` is ``points[offsets[i]:offsets[i + 1]]``.
        chunks: (k,) index of each chunk in its ``Layer`` (``layer.features[chunks]`` are table rows).
    """

    points: NDArrayFloat
    offsets: NDArrayInt
    chunks: NDArrayInt

    def __len__(self) -> int:
        return len(self.chunks)


class Layer:
    """All features of one kind, reordered by grid cell, with the grid that finds them.

    Polylines are cut into chunks (sharing their joining vertex, so the drawn segments are unchanged)
    that are at most one cell wide and, for centerlines, turn by at most ``max_turn_deg`` between their
    first and any later segment, so each chunk has one meaningful travel direction (``chord_angle``).

    Attributes:
        kind: the feature kind.
        points: (N, 2) metres, world frame, chunks back to back in cell order.
        offsets: (F + 1,) chunk bounds into ``points``; ``counts`` (F,) their vertex counts.
        features: (F,) store table row of each chunk.
        chord_angle: (F,) rad CCW from world +x of each chunk's first-to-last vertex vector.
        lo, hi: (F, 2) bounding-box corners, metres.
        cell: grid cell edge, metres; ``origin`` (2,) world position of cell (0, 0)'s corner.
        ncols: grid columns (x). Rows are not bounded: keys are only sorted, never a dense array.
        n_regular: chunks [0, n_regular) fit in one cell and are sorted by ``keys``; the rest are oversize.
        keys: ``row * ncols + col`` of each regular chunk, ascending (a Python list, for ``bisect``).
        chunk_index: (F,) ``arange(F)``, sliced (never rebuilt) to list the chunks of index ranges.
        nrows: grid rows holding regular chunks.
        cell_start: (nrows * ncols + 1,) first chunk of each cell key (chunks of key ``k`` are
            ``[cell_start[k], cell_start[k + 1])``), or None when the grid exceeds ``MAX_DENSE_CELLS``.
    """

    def __init__(
        self,
        kind: FeatureKind,
        geometries: Sequence[NDArrayFloat],
        rows: Sequence[int],
        cell: float = DEFAULT_CELL_M,
        max_turn_deg: float = MAX_TURN_DEG,
    ) -> None:
        self.kind = kind
        self.cell = float(cell)
        max_turn = math.radians(max_turn_deg) if kind is FeatureKind.LANE_CENTERLINE else math.inf
        pieces: list[NDArrayFloat] = []
        piece_rows: list[int] = []
        simple = (
            np.ones(len(geometries), dtype=bool)
            if kind in POLYGON_KINDS
            else _fits_one_chunk(geometries, self.cell, max_turn)
        )
        for geom, row, ok in zip(geometries, rows, simple.tolist(), strict=True):
            chunks = [geom] if ok else _split_polyline(geom, self.cell, max_turn)
            pieces.extend(chunks)
            piece_rows.extend([row] * len(chunks))
        counts = np.array([len(p) for p in pieces], dtype=np.int64)
        flat = np.concatenate(pieces) if pieces else np.zeros((0, 2))
        starts = np.concatenate([[0], np.cumsum(counts)[:-1]]).astype(np.int64) if pieces else counts
        if pieces:
            lo = np.minimum.reduceat(flat, starts, axis=0)
            hi = np.maximum.reduceat(flat, starts, axis=0)
            chord = flat[starts + counts - 1] - flat[starts]
        else:
            lo = hi = chord = np.zeros((0, 2))
        self.origin = lo.min(axis=0) if len(lo) else np.zeros(2)
        self._ox, self._oy = float(self.origin[0]), float(self.origin[1])  # plain floats for the query path
        extent = (hi - lo).max(axis=1) if len(lo) else np.zeros(0)
        regular = extent <= self.cell
        cells = np.floor(((lo + hi) / 2.0 - self.origin) / self.cell).astype(np.int64)
        span = (hi.max(axis=0) - self.origin) if len(hi) else np.zeros(2)
        self.ncols = int(span[0] // self.cell) + 2
        keys_all = cells[:, 1] * self.ncols + cells[:, 0]
        reg_idx = np.flatnonzero(regular)
        order = np.concatenate([reg_idx[np.argsort(keys_all[reg_idx], kind="stable")], np.flatnonzero(~regular)])
        self.n_regular = len(reg_idx)
        self.keys: list[int] = keys_all[order[: self.n_regular]].tolist()
        self.counts: NDArrayInt = counts[order]
        self.offsets: NDArrayInt = np.concatenate([[0], np.cumsum(self.counts)]).astype(np.int64)
        self.points: NDArrayFloat = np.concatenate([pieces[i] for i in order.tolist()]) if pieces else np.zeros((0, 2))
        self.features: NDArrayInt = np.asarray(piece_rows, dtype=np.int64)[order]
        self.chord_angle: NDArrayFloat = np.arctan2(chord[order, 1], chord[order, 0]) if pieces else np.zeros(0)
        self.lo: NDArrayFloat = lo[order]
        self.hi: NDArrayFloat = hi[order]
        self.chunk_index: NDArrayInt = np.arange(len(self.features), dtype=np.int64)  # sliced, never rebuilt
        self.nrows = self.keys[-1] // self.ncols + 1 if self.keys else 0
        self.cell_start: array[int] | None = None
        if self.nrows * self.ncols <= MAX_DENSE_CELLS:
            # A stdlib array, not NumPy: indexing it from Python is ~5x faster than NumPy scalar indexing.
            cells_all = np.arange(self.nrows * self.ncols + 1, dtype=np.int64)
            starts_all = np.searchsorted(np.asarray(self.keys, dtype=np.int64), cells_all).astype(np.int64)
            self.cell_start = array("q", starts_all.tobytes())

    def __len__(self) -> int:
        return len(self.features)

    def cell_span(self, xmin: float, ymin: float, xmax: float, ymax: float) -> tuple[int, int, int, int] | None:
        """Grid (c0, c1, r0, r1), inclusive, holding every regular chunk that may overlap the box; None when
        there is none.

        A regular chunk is filed under the cell of its box centre and is at most one cell wide, so it
        reaches at most half a cell past that cell: widening the query by half a cell finds all of them.
        """
        if not self.n_regular:
            return None
        half = self.cell / 2.0
        ox, oy, cell = self._ox, self._oy, self.cell
        c0 = max(math.floor((xmin - half - ox) / cell), 0)
        c1 = min(math.floor((xmax + half - ox) / cell), self.ncols - 1)
        r0 = max(math.floor((ymin - half - oy) / cell), 0)
        r1 = min(math.floor((ymax + half - oy) / cell), self.nrows - 1)
        return (c0, c1, r0, r1) if c0 <= c1 and r0 <= r1 else None

    def oversize_hits(self, xmin: float, ymin: float, xmax: float, ymax: float) -> list[int]:
        """Oversize chunks (not in the grid) whose bounding box overlaps the box, ascending."""
        if self.n_regular == len(self.features):
            return []
        lo, hi = self.lo[self.n_regular :], self.hi[self.n_regular :]
        hit = (hi[:, 0] >= xmin) & (lo[:, 0] <= xmax) & (hi[:, 1] >= ymin) & (lo[:, 1] <= ymax)
        found: list[int] = (np.flatnonzero(hit) + self.n_regular).tolist()
        return found

    def candidate_ranges(self, xmin: float, ymin: float, xmax: float, ymax: float) -> list[tuple[int, int]]:
        """Chunk index ranges ``[a, b)`` that may overlap the box; a superset, merged and ascending."""
        out: list[tuple[int, int]] = []
        span = self.cell_span(xmin, ymin, xmax, ymax)
        if span is not None:
            c0, c1, r0, r1 = span
            keys, cs, ncols = self.keys, self.cell_start, self.ncols
            # Plain Python per row: a window spans ~6 rows, far too few to pay for NumPy calls.
            for r in range(r0, r1 + 1):
                base = r * ncols
                a, b = _key_range(cs, keys, base + c0, base + c1)
                if b > a:
                    if out and out[-1][1] == a:
                        out[-1] = (out[-1][0], b)
                    else:
                        out.append((a, b))
        out.extend((i, i + 1) for i in self.oversize_hits(xmin, ymin, xmax, ymax))
        return out

    def window(self, xmin: float, ymin: float, xmax: float, ymax: float) -> Window:
        """Geometry of every chunk that may overlap the box (metres, world frame), from contiguous slices."""
        ranges = self.candidate_ranges(xmin, ymin, xmax, ymax)
        if not ranges:
            return Window(np.zeros((0, 2)), np.zeros(1, dtype=np.int64), np.zeros(0, dtype=np.int64))
        off = self.offsets
        if len(ranges) == 1:
            a, b = ranges[0]
            pts = self.points[off[a] : off[b]]
            offsets = off[a : b + 1] - off[a]
            idx = self.chunk_index[a:b]
        else:
            # Slices only, no per-range arithmetic: the counts are precomputed per chunk.
            pts = np.concatenate([self.points[off[a] : off[b]] for a, b in ranges])
            counts = np.concatenate([self.counts[a:b] for a, b in ranges])
            offsets = np.zeros(len(counts) + 1, dtype=np.int64)
            np.cumsum(counts, out=offsets[1:])
            idx = np.concatenate([self.chunk_index[a:b] for a, b in ranges])
        return Window(pts, offsets, idx)

    def overlapping(self, xmin: float, ymin: float, xmax: float, ymax: float) -> NDArrayInt:
        """Chunk indices whose bounding box overlaps the box (exact, for queries and tests)."""
        ranges = self.candidate_ranges(xmin, ymin, xmax, ymax)
        if not ranges:
            return np.zeros(0, dtype=np.int64)
        idx = np.concatenate([np.arange(a, b) for a, b in ranges])
        lo, hi = self.lo[idx], self.hi[idx]
        hit = (hi[:, 0] >= xmin) & (lo[:, 0] <= xmax) & (hi[:, 1] >= ymin) & (lo[:, 1] <= ymax)
        found: NDArrayInt = idx[hit]
        return found


class BandOrder:
    """A second order of a layer's chunks, for reading a window in few contiguous slices.

    Grid rows are grouped into bands of ``rows`` rows and the regular chunks sorted by (band, column),
    stably (so by row, then layer order, within a column); oversize chunks follow in layer order. A window
    is then one slice per band it touches (~2 for a raster) instead of one per grid row (~6). The slices
    are a superset (whole bands of rows): callers cull.

    Attributes:
        layer: the layer ordered.
        rows: grid rows per band.
        order: (F,) layer chunk at each position; ``position`` (F,) its inverse.
        start: (nbands * ncols + 1,) first position of each (band, column) key, or None beyond
            ``MAX_DENSE_CELLS`` (then ``keys``, the sorted key of each regular position, is bisected).
    """

    def __init__(self, layer: Layer, rows: int) -> None:
        self.layer = layer
        self.rows = max(int(rows), 1)
        ncols = layer.ncols
        reg_keys = np.asarray(layer.keys, dtype=np.int64)
        band_keys = (reg_keys // ncols // self.rows) * ncols + reg_keys % ncols
        reg_order = np.argsort(band_keys, kind="stable")
        self.order: NDArrayInt = np.concatenate([reg_order, np.arange(layer.n_regular, len(layer), dtype=np.int64)])
        self.position: NDArrayInt = np.empty_like(self.order)
        self.position[self.order] = np.arange(len(self.order), dtype=np.int64)
        self.keys: list[int] = band_keys[reg_order].tolist()
        nbands = -(-layer.nrows // self.rows)
        self.start: array[int] | None = None
        if nbands * ncols <= MAX_DENSE_CELLS:
            starts = np.searchsorted(band_keys[reg_order], np.arange(nbands * ncols + 1, dtype=np.int64))
            self.start = array("q", starts.astype(np.int64).tobytes())

    def ranges(self, xmin: float, ymin: float, xmax: float, ymax: float) -> list[tuple[int, int]]:
        """Position ranges ``[a, b)`` holding every chunk that may overlap the box (a superset)."""
        layer = self.layer
        out: list[tuple[int, int]] = []
        span = layer.cell_span(xmin, ymin, xmax, ymax)
        if span is not None:
            c0, c1, r0, r1 = span
            ncols, start, keys = layer.ncols, self.start, self.keys
            for band in range(r0 // self.rows, r1 // self.rows + 1):
                base = band * ncols
                a, b = _key_range(start, keys, base + c0, base + c1)
                if b > a:
                    out.append((a, b))
        position = self.position
        out.extend((int(position[i]), int(position[i]) + 1) for i in layer.oversize_hits(xmin, ymin, xmax, ymax))
        return out


def _key_range(start: Sequence[int] | None, keys: Sequence[int], first: int, last: int) -> tuple[int, int]:
    """[a, b) of the chunks sorted by key whose key lies in [first, last]: from the dense start table when there
    is one (``start[k]`` = first chunk with key >= k), else by bisecting the sorted keys."""
    if start is not None:
        return int(start[first]), int(start[last + 1])
    a = bisect.bisect_left(keys, first)
    return a, bisect.bisect_right(keys, last, lo=a)


def _fits_one_chunk(geoms: Sequence[NDArrayFloat], cell: float, max_turn: float) -> NDArrayBool:
    """Per polyline: already at most ``cell`` wide with every segment within ``max_turn`` rad of its first
    one, i.e. ``_split_polyline`` would return it whole. Vectorised over all polylines (most AV1 lanes),
    so only the rest pay for the per-vertex loop."""
    if not geoms:
        return np.zeros(0, dtype=bool)
    counts = np.array([len(g) for g in geoms], dtype=np.int64)
    flat = np.concatenate(geoms)
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]]).astype(np.int64)
    ext = (np.maximum.reduceat(flat, starts, axis=0) - np.minimum.reduceat(flat, starts, axis=0)).max(axis=1)
    d = np.diff(flat, axis=0)
    theta = np.arctan2(d[:, 1], d[:, 0])
    owner = np.repeat(np.arange(len(geoms)), counts)[:-1]
    dev = np.abs((theta - theta[starts][owner] + math.pi) % (2 * math.pi) - math.pi)
    dev[(starts + counts - 1)[:-1]] = 0.0  # the pseudo-segment joining one polyline to the next
    worst = np.maximum.reduceat(dev, starts) if len(dev) else np.zeros(len(geoms))
    ok: NDArrayBool = (ext <= cell) & (worst <= max_turn) & (counts >= 2)
    ok |= counts <= 2
    return ok


def _split_polyline(pts: NDArrayFloat, cell: float, max_turn: float = math.inf) -> list[NDArrayFloat]:
    """Cut a polyline into consecutive chunks at most ``cell`` wide whose segments stay within
    ``max_turn`` rad of the chunk's first segment.

    Chunks share their joining vertex, so the set of segments is exactly the original one. A single
    segment longer than a cell becomes its own (oversize) chunk.
    """
    if len(pts) <= 2:
        return [pts]
    d = np.diff(pts, axis=0)
    ang = np.unwrap(np.arctan2(d[:, 1], d[:, 0]))
    ext = pts.max(axis=0) - pts.min(axis=0)
    if max(ext[0], ext[1]) <= cell and float(ang.max() - ang.min()) <= max_turn:
        return [pts]  # the common case (straight AV1 lanes): no Python loop
    chunks: list[NDArrayFloat] = []
    # Plain floats in the loop: per-vertex NumPy calls on 2-element arrays cost ~20x more.
    xs, ys = pts[:, 0].tolist(), pts[:, 1].tolist()
    turn = ang.tolist()
    start = 0
    x0 = x1 = xs[0]
    y0 = y1 = ys[0]
    for j in range(1, len(xs)):
        x, y = xs[j], ys[j]
        nx0, nx1, ny0, ny1 = min(x0, x), max(x1, x), min(y0, y), max(y1, y)
        # Segment j-1 runs from vertex j-1 to j; it would join the chunk that starts at vertex `start`.
        too_wide = max(nx1 - nx0, ny1 - ny0) > cell
        turned = abs(turn[j - 1] - turn[start]) > max_turn
        if (too_wide or turned) and j - 1 > start:
            chunks.append(pts[start:j])
            start = j - 1
            px, py = xs[j - 1], ys[j - 1]
            nx0, nx1, ny0, ny1 = min(px, x), max(px, x), min(py, y), max(py, y)
        x0, x1, y0, y1 = nx0, nx1, ny0, ny1
    chunks.append(pts[start:])
    return chunks


def _chain_polylines(geoms: Sequence[NDArrayFloat]) -> list[tuple[NDArrayFloat, int]]:
    """Join polylines end-to-start where the junction is unambiguous (exactly one ends and exactly one
    starts at the same vertex, compared bit for bit). Returns (geometry, index of its first input)."""
    starts: dict[bytes, list[int]] = {}
    ends: dict[bytes, list[int]] = {}
    for i, g in enumerate(geoms):
        starts.setdefault(g[0].tobytes(), []).append(i)
        ends.setdefault(g[-1].tobytes(), []).append(i)
    succ: dict[int, int] = {}
    has_pred: set[int] = set()
    for i, g in enumerate(geoms):
        key = g[-1].tobytes()
        nxt = starts.get(key, [])
        if len(nxt) == 1 and len(ends[key]) == 1 and nxt[0] != i:
            succ[i] = nxt[0]
            has_pred.add(nxt[0])
    seen: set[int] = set()
    out: list[tuple[NDArrayFloat, int]] = []
    # Chain heads first; then whatever is left (pure cycles), in input order for determinism.
    for head in [i for i in range(len(geoms)) if i not in has_pred] + list(range(len(geoms))):
        if head in seen:
            continue
        parts: list[NDArrayFloat] = []
        j: int | None = head
        while j is not None and j not in seen:
            seen.add(j)
            parts.append(geoms[j] if not parts else geoms[j][1:])
            j = succ.get(j)
        out.append((np.concatenate(parts) if len(parts) > 1 else parts[0], head))
    return out


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
            chains = _chain_polylines([self.geometry(r) for r in rows])
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
