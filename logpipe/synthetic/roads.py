"""The road network the pre-training traffic (``logpipe.synthetic.flow``) drives on, built from any ``MapStore``.

A ``Roads`` holds, per vehicle lane: its centerline resampled every ~``DS_M`` m (one flat array for all lanes, so
positions of all vehicles are looked up with one gather), successors and predecessors, same-direction left and
right neighbours, width, speed limit and what controls its end (a traffic light, a stop line or an unsignalled
junction entry), plus the conflict points where two lanes' centerlines cross.

Where each comes from:

* links: the store's ``successors``/``predecessors`` (AV2, CommonRoad) or, for AV1 centerline npz files,
  ``logpipe.synthetic.lanes.derive_successors`` (end vertex = start vertex);
* neighbours: the store's ``left/right_neighbor_id`` (same direction only); AV1: derived by geometry
  (``derive_neighbours``: a parallel lane 2.5-4.8 m to one side at a quarter, half and three quarters of the lane);
* widths and speed limits: ``LaneExtras`` from the source (CommonRoad bounds and ``R2-1``/``274`` speed signs);
  else ``DEFAULT_WIDTH_M`` and the source's default limit;
* junction control: CommonRoad traffic lights (their real cycle) and stop lines; elsewhere a lane whose
  successors cross another lane is a junction entry, signalled or all-way-stop by a seeded draw per junction.

Frames and units: metres in the map's own frame (AV1/AV2 city frame, CommonRoad scenario frame), speeds m/s.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from logpipe.maps import FeatureKind, MapStore
from logpipe.synthetic.lanes import derive_successors
from logpipe.types import NDArrayBool, NDArrayFloat, NDArrayInt

DS_M = 0.5
"""Target spacing of the resampled centerlines (m)."""
DEFAULT_WIDTH_M = 3.6
"""Lane width where the map gives none (AV1 centerlines), metres."""
CONFLICT_DIST_M = 2.0
"""Two lanes conflict where their centerlines pass within this distance (m) of each other."""
NO_VEHICLES = frozenset({"BIKE", "BUS", "bicycleLane", "busLane", "sidewalk", "crosswalk"})
"""Lane types no simulated car drives on (AV2 ``lane_type``, CommonRoad ``laneletType``)."""


@dataclass(frozen=True)
class Signal:
    """A traffic light's cycle: green, then yellow, then red, seconds; ``offset_s`` shifts it in time."""

    green_s: float
    yellow_s: float
    red_s: float
    offset_s: float

    def is_red(self, t_s: float) -> bool:
        """Red or yellow at time ``t_s`` (a vehicle that can still stop does)."""
        period = self.green_s + self.yellow_s + self.red_s
        return (t_s + self.offset_s) % period >= self.green_s


@dataclass
class LaneExtras:
    """What a map source knows beyond the store, by lane id: widths (m), speed limits (m/s), the signal at a
    lane's end, lanes ending at a stop line without a light (a stop sign)."""

    widths: dict[str, float] = field(default_factory=dict)
    limits: dict[str, float] = field(default_factory=dict)
    signals: dict[str, Signal] = field(default_factory=dict)
    stop_lines: set[str] = field(default_factory=set)


@dataclass
class Roads:
    """Vehicle lanes of one map (see the module docstring). Indices are lane positions 0..L-1.

    Attributes:
        name: the map's name. lane_ids: (L,) map ids. pts: (P, 2) all resampled centerline points, metres;
            heading: (P,) rad CCW from +x. start: (L,) each lane's first row in ``pts``; count: (L,) its rows;
            step: (L,) metres between its rows. lengths: (L,) m.
        succ / pred: links. left / right: same-direction neighbour or -1. widths: (L,) m. limits: (L,) m/s.
        signals: lane -> its end's signal. stops: lanes ending at a stop line (full stop, then go).
        junction: (L,) the lane ends at a junction entry (its successors cross other lanes).
        conflicts: per lane, (first arc on it, other lane, first arc on the other, last arc on it, last arc on the
            other) of the stretch where the two centerlines pass within ``CONFLICT_DIST_M`` (m), by first arc.
        turn: (L,) +1 left, -1 right, 0 straight: the heading change over the lane (> 30 deg counts).
    """

    name: str
    lane_ids: list[str]
    pts: NDArrayFloat
    heading: NDArrayFloat
    start: NDArrayInt
    count: NDArrayInt
    step: NDArrayFloat
    lengths: NDArrayFloat
    succ: list[list[int]]
    pred: list[list[int]]
    left: NDArrayInt
    right: NDArrayInt
    widths: NDArrayFloat
    limits: NDArrayFloat
    signals: dict[int, Signal]
    stops: set[int]
    junction: NDArrayBool
    conflicts: list[list[tuple[float, int, float, float, float]]]
    turn: NDArrayInt
    lens: list[float] = field(default_factory=list)

    def __post_init__(self) -> None:
        self.lens = self.lengths.tolist()  # plain floats: the per-car rules index them thousands of times a step

    def __len__(self) -> int:
        return len(self.lane_ids)

    def at(self, lane: NDArrayInt, s: NDArrayFloat) -> tuple[NDArrayFloat, NDArrayFloat]:
        """(n, 2) points and (n,) headings at arc ``s`` (m, clamped to the lane) on ``lane``, vectorised."""
        k = np.clip(s / self.step[lane], 0.0, self.count[lane] - 1.000001)
        i = k.astype(np.int64)
        f = (k - i)[:, None]
        row = self.start[lane] + i
        xy = self.pts[row] * (1 - f) + self.pts[row + 1] * f
        h0 = self.heading[row]
        turn = (self.heading[row + 1] - h0 + np.pi) % (2 * np.pi) - np.pi
        # headings blend between points, so an offset from the centerline moves smoothly round a bend
        return xy, h0 + turn * f[:, 0]

    def project(self, lane: int, xy: NDArrayFloat) -> float:
        """Arc (m) of the point of ``lane``'s centerline nearest ``xy``."""
        rows = self.pts[self.start[lane]:self.start[lane] + self.count[lane]]
        k = min(int(np.argmin(np.hypot(rows[:, 0] - xy[0], rows[:, 1] - xy[1]))), len(rows) - 2)
        best, best_d = k * float(self.step[lane]), np.inf
        for j in (k - 1, k):  # the segments on either side of the nearest point
            if j < 0:
                continue
            seg = rows[j + 1] - rows[j]
            t = float(np.clip(np.dot(xy - rows[j], seg) / max(float(np.dot(seg, seg)), 1e-12), 0.0, 1.0))
            d = float(np.hypot(*(rows[j] + t * seg - xy)))
            if d < best_d:
                best, best_d = (j + t) * float(self.step[lane]), d
        return best

    def entries(self) -> NDArrayInt:
        """Lanes with no predecessor: where traffic enters the map."""
        return np.array([i for i, p in enumerate(self.pred) if not p], dtype=np.int64)


def polylines(store: MapStore) -> tuple[list[str], list[NDArrayFloat], dict[str, dict[str, object]]]:
    """Lane ids, centerlines (travel order, metres) and attribute rows of a store's vehicle lanes."""
    rows = store.rows(FeatureKind.LANE_CENTERLINE)
    table = store.table.take(rows).to_pydict()
    ids = [str(i) for i in table["feature_id"]]
    lines = [np.asarray(store.geometry(int(r)), dtype=np.float64) for r in rows.tolist()]
    attrs = {ids[k]: {c: table[c][k] for c in table if c not in ("xs", "ys")} for k in range(len(ids))}
    keep = [k for k, i in enumerate(ids)
            if not (set(str(attrs[i].get("lane_type") or "").split("/")) & NO_VEHICLES) and len(lines[k]) >= 2]
    return [ids[k] for k in keep], [lines[k] for k in keep], attrs


def build_roads(store: MapStore, extras: LaneExtras, default_limit: float, rng: np.random.Generator,
                name: str | None = None) -> Roads:
    """The ``Roads`` of a store (module docstring). ``rng`` draws the control of unsignalled junctions."""
    ids, lines, attrs = polylines(store)
    index = {lane: k for k, lane in enumerate(ids)}
    have_links = any(attrs[i].get("successors") for i in ids)
    if have_links:
        succ = [[index[str(s)] for s in (attrs[i].get("successors") or []) if str(s) in index] for i in ids]  # type: ignore[attr-defined]
    else:
        succ = derive_successors(lines)
    pred: list[list[int]] = [[] for _ in ids]
    for a, nxt in enumerate(succ):
        for b in nxt:
            pred[b].append(a)
    have_neighbours = any(attrs[i].get("left_neighbor_id") or attrs[i].get("right_neighbor_id") for i in ids)
    if have_neighbours:
        left = np.array([index.get(str(attrs[i].get("left_neighbor_id")), -1) for i in ids], dtype=np.int64)
        right = np.array([index.get(str(attrs[i].get("right_neighbor_id")), -1) for i in ids], dtype=np.int64)
    else:
        left, right = derive_neighbours(lines)
    pts, heading, start, count, step, lengths = resample_all(lines)
    roads = Roads(
        name=name or store.map_id, lane_ids=ids, pts=pts, heading=heading, start=start, count=count, step=step,
        lengths=lengths, succ=succ, pred=pred, left=left, right=right,
        widths=np.array([extras.widths.get(i, DEFAULT_WIDTH_M) for i in ids]),
        limits=np.array([extras.limits.get(i, default_limit) for i in ids]),
        signals={index[i]: s for i, s in extras.signals.items() if i in index},
        stops={index[i] for i in extras.stop_lines if i in index},
        junction=np.zeros(len(ids), dtype=bool), conflicts=[[] for _ in ids],
        turn=np.zeros(len(ids), dtype=np.int64),
    )
    roads.conflicts = find_conflicts(roads)
    roads.turn = np.array([_turn(heading[start[k]:start[k] + count[k]]) for k in range(len(ids))], dtype=np.int64)
    _mark_junctions(roads, rng)
    return roads


def resample_all(lines: Sequence[NDArrayFloat]) -> tuple[NDArrayFloat, NDArrayFloat, NDArrayInt, NDArrayInt,
                                                         NDArrayFloat, NDArrayFloat]:
    """Every centerline resampled at an even step near ``DS_M``: (points, headings, start, count, step, length)."""
    pts_l, head_l, start, count, step, lengths = [], [], [], [], [], []
    row = 0
    for line in lines:
        seg = np.hypot(*np.diff(line, axis=0).T)
        p = line[np.concatenate([[True], seg > 1e-6])]
        arc = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(p, axis=0).T))])
        total = max(float(arc[-1]), 1e-3)
        n = max(math.ceil(total / DS_M) + 1, 2)
        s = np.linspace(0.0, total, n)
        xy = np.stack([np.interp(s, arc, p[:, 0]), np.interp(s, arc, p[:, 1])], axis=1) if len(p) > 1 \
            else np.repeat(p[:1], n, axis=0)
        d = np.diff(xy, axis=0)
        h = np.arctan2(d[:, 1], d[:, 0])
        pts_l.append(xy)
        head_l.append(np.concatenate([h, h[-1:]]))
        start.append(row)
        count.append(n)
        step.append(total / (n - 1))
        lengths.append(total)
        row += n
    return (np.concatenate(pts_l), np.concatenate(head_l), np.array(start, dtype=np.int64),
            np.array(count, dtype=np.int64), np.array(step), np.array(lengths))


def derive_neighbours(lines: Sequence[NDArrayFloat], lo: float = 2.5, hi: float = 4.8,
                      max_turn_deg: float = 12.0) -> tuple[NDArrayInt, NDArrayInt]:
    """Same-direction neighbours from geometry (AV1 centerlines carry none): lane B is A's left (right)
    neighbour when at 25, 50 and 75 % of A's length the nearest point of B lies ``lo``-``hi`` m to A's left
    (right), travelling within ``max_turn_deg`` of A's direction."""
    pts, heading, start, count, _, _ = resample_all(lines)
    owner = np.repeat(np.arange(len(lines)), count)
    cell = hi
    keys = np.floor(pts / cell).astype(np.int64)
    grid: dict[tuple[int, int], list[int]] = {}
    for r, (cx, cy) in enumerate(keys.tolist()):
        grid.setdefault((cx, cy), []).append(r)
    left = np.full(len(lines), -1, dtype=np.int64)
    right = np.full(len(lines), -1, dtype=np.int64)
    max_turn = math.radians(max_turn_deg)
    for a in range(len(lines)):
        votes: list[tuple[int, int]] = []
        for q in (0.25, 0.5, 0.75):
            r = int(start[a] + round(q * (count[a] - 1)))
            votes.append(_side_neighbour(r, a, pts, heading, owner, grid, cell, lo, hi, max_turn))
        if votes[0][0] >= 0 and all(v == votes[0] for v in votes):
            (left if votes[0][1] > 0 else right)[a] = votes[0][0]
    return left, right


def _side_neighbour(  # noqa: PLR0913  one query point against the prepared grid
    r: int, a: int, pts: NDArrayFloat, heading: NDArrayFloat, owner: NDArrayInt,
                    grid: dict[tuple[int, int], list[int]], cell: float, lo: float, hi: float,
                    max_turn: float) -> tuple[int, int]:
    """(lane, side +1 left / -1 right) of the nearest parallel point ``lo``-``hi`` m beside row ``r``."""
    cx, cy = (int(v) for v in np.floor(pts[r] / cell))
    cands = [q for dx in (-1, 0, 1) for dy in (-1, 0, 1) for q in grid.get((cx + dx, cy + dy), ())]
    best, best_d = (-1, 0), math.inf
    h = heading[r]
    for q in cands:
        if owner[q] == a or abs((heading[q] - h + math.pi) % (2 * math.pi) - math.pi) > max_turn:
            continue
        dx, dy = pts[q] - pts[r]
        lateral = -math.sin(h) * dx + math.cos(h) * dy
        along = math.cos(h) * dx + math.sin(h) * dy
        if lo <= abs(lateral) <= hi and abs(along) < 1.0 and abs(lateral) < best_d:
            best, best_d = (int(owner[q]), 1 if lateral > 0 else -1), abs(lateral)
    return best


def find_conflicts(roads: Roads) -> list[list[tuple[float, int, float, float, float]]]:
    """Per lane, the stretch (first arc, other lane, its first arc, last arc, its last arc; m) where its
    centerline comes within ``CONFLICT_DIST_M`` of another lane's, for lane pairs that are not linked, not
    neighbours and share neither a successor (a merge, handled as car following) nor a predecessor (a fork)."""
    owner = np.repeat(np.arange(len(roads)), roads.count)
    keys = np.floor(roads.pts / CONFLICT_DIST_M).astype(np.int64)
    grid: dict[tuple[int, int], list[int]] = {}
    for r, (cx, cy) in enumerate(keys.tolist()):
        grid.setdefault((cx, cy), []).append(r)
    found: dict[tuple[int, int], list[float]] = {}
    related: dict[tuple[int, int], bool] = {}
    for (cx, cy), rows in grid.items():
        near = [q for dx in (-1, 0, 1) for dy in (-1, 0, 1) for q in grid.get((cx + dx, cy + dy), ())]
        if len({int(owner[q]) for q in near}) < 2:
            continue
        for r in rows:
            a = int(owner[r])
            for q in near:
                b = int(owner[q])
                if b <= a:
                    continue
                if (a, b) not in related:
                    related[(a, b)] = not _unrelated(roads, a, b)
                if related[(a, b)] or float(np.hypot(*(roads.pts[r] - roads.pts[q]))) >= CONFLICT_DIST_M:
                    continue
                sa = float((r - roads.start[a]) * roads.step[a])
                sb = float((q - roads.start[b]) * roads.step[b])
                span = found.setdefault((a, b), [sa, sb, sa, sb])
                span[:] = [min(span[0], sa), min(span[1], sb), max(span[2], sa), max(span[3], sb)]
    out: list[list[tuple[float, int, float, float, float]]] = [[] for _ in range(len(roads))]
    for (a, b), (a0, b0, a1, b1) in sorted(found.items()):
        out[a].append((a0, b, b0, a1, b1))
        out[b].append((b0, a, a0, b1, a1))
    for lst in out:
        lst.sort()
    return out


def _unrelated(roads: Roads, a: int, b: int) -> bool:
    if b in roads.succ[a] or a in roads.succ[b] or b in (roads.left[a], roads.right[a]) \
            or a in (roads.left[b], roads.right[b]):
        return False
    return not (set(roads.succ[a]) & set(roads.succ[b]) or set(roads.pred[a]) & set(roads.pred[b]))


def _turn(h: NDArrayFloat) -> int:
    change = float(np.unwrap(h)[-1] - np.unwrap(h)[0]) if len(h) > 1 else 0.0
    return 0 if abs(change) < math.radians(30) else (1 if change > 0 else -1)


def _mark_junctions(roads: Roads, rng: np.random.Generator) -> None:
    """Lanes whose successors cross another lane end at a junction entry. Entries without a signal or stop line
    from the map get one per junction (entries whose ends lie within 40 m of each other): with probability 0.8 a
    light with random green/red times (opposite phases for crossing approaches), else an all-way stop."""
    entry = [a for a in range(len(roads)) if any(roads.conflicts[b] for b in roads.succ[a])]
    roads.junction[entry] = True
    todo = [a for a in entry if a not in roads.signals and a not in roads.stops]
    ends = {a: roads.pts[roads.start[a] + roads.count[a] - 1] for a in todo}
    while todo:
        seed = todo.pop(0)
        group = [seed] + [a for a in todo if float(np.hypot(*(ends[a] - ends[seed]))) < 40.0]
        todo = [a for a in todo if a not in group]
        if rng.random() < 0.8:
            green, red = float(rng.uniform(12, 30)), float(rng.uniform(12, 30))
            offset = float(rng.uniform(0, green + red + 3))
            h0 = roads.heading[roads.start[seed] + roads.count[seed] - 1]
            for a in group:
                h = roads.heading[roads.start[a] + roads.count[a] - 1]
                cross = abs(math.sin(h - h0)) > math.sin(math.radians(45))
                # Crossing approaches get the other half of the cycle, so they rarely meet on green.
                roads.signals[a] = Signal(green if not cross else red, 3.0, red if not cross else green,
                                          offset - (green + 3.0 if cross else 0.0))
        else:
            roads.stops.update(group)
