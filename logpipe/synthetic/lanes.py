"""The lane graph synthetic traffic drives on: a city's AV1 lane centerlines with successor links, and the
held-out region that splits its lanes into training and test ones.

Lane links: the pickle-free AV1 ``.npz`` holds centerlines only, so successors are derived geometrically: lane B
follows lane A when B's first vertex lies within ``LINK_TOL_M`` of A's last vertex and their directions there
differ by less than ``LINK_MAX_TURN_DEG``. On the real city maps every such link has distance 0 (shared
vertices). A store that carries ``successors`` (AV1 vector-map XML) is used as is.

Held-out region: per city, a box covering the top ``holdout_fraction`` of lanes along the city's longer axis.
Test windows use only lanes wholly inside it; training windows only lanes at least ``holdout_margin_m`` outside
it, so no training trajectory (nor an ego-centred 100 m raster around it) touches the box.

Positions are metres in the AV1 city frame of the map.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pyarrow.compute as pc

from logpipe.maps import FeatureKind, MapStore, load_map
from logpipe.maps.argoverse1 import city_from_name
from logpipe.types import NDArrayBool, NDArrayFloat, NDArrayInt

LINK_TOL_M = 1.0
"""Largest end-to-start distance (m) of two lanes that are linked."""
LINK_MAX_TURN_DEG = 60.0
"""Largest direction change (deg) at a link: excludes the opposite-direction twin that starts where a lane ends."""

@dataclass
class LaneGraph:
    """Lane centerlines of one city and their successor links.

    Attributes:
        city: AV1 city name (MIA, PIT) written to CITY_NAME.
        lane_ids: (L,) map lane ids (strings).
        lines: per lane, (n, 2) vertices in travel order, metres, city frame.
        lengths: (L,) m. mids: (L, 2) mean vertex of each lane. lo, hi: (L, 2) bounding boxes.
        successors: per lane, indices of the lanes it continues into.
        derived_links: True when the links were computed from geometry (npz) rather than read (XML).
    """

    city: str
    lane_ids: list[str]
    lines: list[NDArrayFloat]
    lengths: NDArrayFloat
    mids: NDArrayFloat
    lo: NDArrayFloat
    hi: NDArrayFloat
    successors: list[list[int]]
    derived_links: bool

    @classmethod
    def from_store(cls, store: MapStore, city: str | None = None) -> LaneGraph:
        """The centerline layer of a map store; links from its ``successors`` column when filled, else geometry."""
        rows = store.rows(FeatureKind.LANE_CENTERLINE)
        lines = [np.asarray(store.geometry(int(r)), dtype=np.float64) for r in rows.tolist()]
        ids = store.feature_ids(rows.tolist())
        succ_col = store.table.column("successors").take(rows)
        have_links = succ_col.null_count < len(rows) and pc.sum(pc.list_value_length(succ_col)).as_py()
        lengths = np.array([float(np.hypot(*np.diff(p, axis=0).T).sum()) for p in lines])
        graph = cls(
            city=city or store.map_id,
            lane_ids=ids,
            lines=lines,
            lengths=lengths,
            mids=np.array([p.mean(axis=0) for p in lines]).reshape(-1, 2),
            lo=np.array([p.min(axis=0) for p in lines]).reshape(-1, 2),
            hi=np.array([p.max(axis=0) for p in lines]).reshape(-1, 2),
            successors=[],
            derived_links=not have_links,
        )
        if have_links:
            index = {lane: i for i, lane in enumerate(ids)}
            graph.successors = [
                [index[s] for s in (succ or []) if s in index] for succ in succ_col.to_pylist()
            ]
        else:
            graph.successors = derive_successors(lines)
        return graph

    @classmethod
    def from_path(cls, path: Path, city: str | None = None) -> LaneGraph:
        """Load a map file through ``logpipe.maps.load_map`` (npz, XML, store parquet)."""
        return cls.from_store(load_map(path), city or city_from_name(path))

    def __len__(self) -> int:
        return len(self.lines)

    @property
    def forks(self) -> NDArrayInt:
        """Lanes with two or more successors."""
        return np.array([i for i, s in enumerate(self.successors) if len(s) >= 2], dtype=np.int64)


def derive_successors(lines: Sequence[NDArrayFloat], tol: float = LINK_TOL_M,
                      max_turn_deg: float = LINK_MAX_TURN_DEG) -> list[list[int]]:
    """Successor links from geometry: B follows A when B starts within ``tol`` m of A's end and turns less than
    ``max_turn_deg`` there. Starts are bucketed in a grid of ``tol`` cells, so this is linear in the lanes."""
    starts = np.array([p[0] for p in lines]).reshape(-1, 2)
    ends = np.array([p[-1] for p in lines]).reshape(-1, 2)
    start_dir = np.array([p[1] - p[0] for p in lines]).reshape(-1, 2)
    end_dir = np.array([p[-1] - p[-2] for p in lines]).reshape(-1, 2)
    start_h = np.arctan2(start_dir[:, 1], start_dir[:, 0])
    end_h = np.arctan2(end_dir[:, 1], end_dir[:, 0])
    cells: dict[tuple[int, int], list[int]] = {}
    keys = np.floor(starts / tol).astype(np.int64)
    for i, (cx, cy) in enumerate(keys.tolist()):
        cells.setdefault((cx, cy), []).append(i)
    max_turn = math.radians(max_turn_deg)
    out: list[list[int]] = []
    for a, (ex, ey) in enumerate(np.floor(ends / tol).astype(np.int64).tolist()):
        found: list[int] = []
        for dx in (-1, 0, 1):
            for dy in (-1, 0, 1):
                for b in cells.get((ex + dx, ey + dy), ()):
                    if b == a or float(np.hypot(*(starts[b] - ends[a]))) > tol:
                        continue
                    turn = abs((start_h[b] - end_h[a] + math.pi) % (2 * math.pi) - math.pi)
                    if turn < max_turn:
                        found.append(b)
        out.append(sorted(found))
    return out


@dataclass(frozen=True)
class HoldOut:
    """The held-out box of one city, metres, city frame; ``margin`` keeps training lanes this far outside it."""

    xmin: float
    ymin: float
    xmax: float
    ymax: float
    margin: float

    @classmethod
    def for_graph(cls, graph: LaneGraph, fraction: float, margin: float) -> HoldOut:
        """A box over the top ``fraction`` of lanes (by mid point) along the city's longer axis, full width across."""
        lo, hi = graph.lo.min(axis=0), graph.hi.max(axis=0)
        axis = int(np.argmax(hi - lo))
        cut = float(np.quantile(graph.mids[:, axis], 1.0 - fraction))
        box = [float(lo[0]) - 1.0, float(lo[1]) - 1.0, float(hi[0]) + 1.0, float(hi[1]) + 1.0]
        box[axis] = cut
        return cls(box[0], box[1], box[2], box[3], margin)

    def inside(self, xy: NDArrayFloat) -> NDArrayBool:
        """(n,) points inside the box."""
        x, y = xy[..., 0], xy[..., 1]
        result: NDArrayBool = (x >= self.xmin) & (x <= self.xmax) & (y >= self.ymin) & (y <= self.ymax)
        return result

    def clear(self, xy: NDArrayFloat) -> NDArrayBool:
        """(n,) points at least ``margin`` outside the box (outside the box grown by the margin)."""
        m = self.margin
        x, y = xy[..., 0], xy[..., 1]
        near = (x >= self.xmin - m) & (x <= self.xmax + m) & (y >= self.ymin - m) & (y <= self.ymax + m)
        result: NDArrayBool = ~near
        return result

    def lane_masks(self, graph: LaneGraph) -> tuple[NDArrayBool, NDArrayBool]:
        """(train, test) lanes: wholly clear of the grown box, wholly inside the box."""
        train = np.array([bool(self.clear(p).all()) for p in graph.lines])
        test = np.array([bool(self.inside(p).all()) for p in graph.lines])
        return train, test
