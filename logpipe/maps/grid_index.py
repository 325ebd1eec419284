"""The spatial index of one map feature kind: a uniform grid over the map's world frame (metres).

Features are bucketed by the centre of their bounding box and stored contiguously in cell order (``Layer``),
so a window query is a handful of ``searchsorted`` calls and contiguous slices instead of a scan of the city.
Polylines longer than one cell are cut into chunks that share their end vertex (the segments drawn are
unchanged); the few polygons larger than a cell (AV2 drivable areas) sit in an "oversize" list tested by
bounding box. ``BandOrder`` reorders a layer's chunks by bands of grid rows for the rasteriser.
"""

from __future__ import annotations

import bisect
import math
from array import array
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from logpipe.maps.feature_kinds import POLYGON_KINDS, FeatureKind
from logpipe.types import NDArrayBool, NDArrayFloat, NDArrayInt

MAX_TURN_DEG = 30.0
"""Centerline chunks turn by at most this much, so one direction per chunk describes every segment."""

DEFAULT_CELL_M = 32.0
"""Grid cell edge in metres: about the median AV1 lane length x 2, so few lanes are cut into chunks."""

MAX_DENSE_CELLS = 1 << 22
"""Grids up to this many cells (32 MiB of starts; a 65 km square city at 32 m) get a dense per-cell start
table, so a window row is two lookups; larger (sparse, far-flung) maps fall back to bisecting the keys."""


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
            chunks = [geom] if ok else split_polyline(geom, self.cell, max_turn)
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
    one, i.e. ``split_polyline`` would return it whole. Vectorised over all polylines (most AV1 lanes),
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


def split_polyline(pts: NDArrayFloat, cell: float, max_turn: float = math.inf) -> list[NDArrayFloat]:
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


def chain_polylines(geoms: Sequence[NDArrayFloat]) -> list[tuple[NDArrayFloat, int]]:
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
