"""Vehicles driving routes on a lane graph (``logpipe.synthetic.lanes``): route planning (a random successor
at every fork), a speed profile limited by curvature and braking, and IDM car following to the vehicle ahead
on the vehicle's own route; one simulated window of an AV, an AGENT and other vehicles.

Frames and units: positions are metres in the AV1 city frame, speeds m/s, accelerations m/s², time steps 0.1 s.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from logpipe.synthetic.lanes import LaneGraph
from logpipe.types import NDArrayBool, NDArrayFloat, NDArrayInt

ROUTE_DS_M = 0.5
"""Resampling step of a route polyline (m): speed limits and positions are looked up on this grid."""


@dataclass(frozen=True)
class SimConfig:
    """Vehicle model and window layout. Lengths in metres, speeds m/s, accelerations m/s², times s.

    Attributes:
        dt: step (0.1 s = AV1's 10 Hz). steps: recorded steps per window (AV1: 20 observed + 30 future).
        obs_len: observed steps (the AGENT is picked among vehicles that meet a fork after step ``obs_len``).
        warmup: simulated steps before the first recorded one (speeds settle, gaps form).
        v_desired: range of each vehicle's free-road speed. a_max: largest acceleration.
        b_comfort: deceleration planned for ahead of curves. b_max: hardest braking (the clamp).
        a_lat: lateral acceleration allowed in curves (v <= sqrt(a_lat / curvature)).
        gap_min: IDM standstill gap. headway: IDM time headway. length: vehicle length (gap is bumper to bumper).
        others: range of other vehicles per window. spawn_radius: others start within this of the ego.
        spawn_sep: smallest distance between two vehicles' start points.
        lateral_sd: stationary standard deviation of a vehicle's slow lateral wander off the centerline.
        lateral_max: clamp of that wander. noise_sd: white position noise (tracking noise), 0 = none.
        lookahead: route length beyond the distance a vehicle can cover, for braking ahead of curves.
    """

    dt: float = 0.1
    steps: int = 50
    obs_len: int = 20
    warmup: int = 10
    v_desired: tuple[float, float] = (8.0, 16.0)
    a_max: float = 2.0
    b_comfort: float = 2.0
    b_max: float = 6.0
    a_lat: float = 2.5
    gap_min: float = 2.0
    headway: float = 1.2
    length: float = 4.5
    others: tuple[int, int] = (6, 14)
    spawn_radius: float = 50.0
    spawn_sep: float = 10.0
    lateral_sd: float = 0.15
    lateral_max: float = 0.5
    noise_sd: float = 0.0
    lookahead: float = 40.0



@dataclass
class Route:
    """A vehicle's path: lanes in order, resampled every ``ROUTE_DS_M`` m.

    Attributes:
        lanes: lane indices; each is a successor of the one before.
        lane_start: (len(lanes),) arc length (m) at which each lane begins.
        xy: (n, 2) points, metres, city frame; ``s`` (n,) their arc length. heading: (n,) rad CCW from +x.
        v_allow: (n,) m/s, the speed that still allows braking at ``b_comfort`` to every curve limit ahead.
        forks: (lane position in ``lanes``, options) at every lane with two or more allowed successors.
    """

    lanes: list[int]
    lane_start: NDArrayFloat
    xy: NDArrayFloat
    s: NDArrayFloat
    heading: NDArrayFloat
    v_allow: NDArrayFloat
    forks: list[tuple[int, int]] = field(default_factory=list)

    def at(self, s: float) -> tuple[float, float, float]:
        """(x, y, heading) at arc length ``s`` (clamped to the route)."""
        k = min(max(s / ROUTE_DS_M, 0.0), len(self.s) - 1.0)
        i = min(int(k), len(self.s) - 2)
        f = k - i
        x = self.xy[i, 0] * (1 - f) + self.xy[i + 1, 0] * f
        y = self.xy[i, 1] * (1 - f) + self.xy[i + 1, 1] * f
        return float(x), float(y), float(self.heading[i])

    def lane_at(self, s: float) -> int:
        """Position in ``lanes`` of the lane holding arc length ``s``."""
        return max(int(np.searchsorted(self.lane_start, s, side="right")) - 1, 0)


def plan_route(graph: LaneGraph, allowed: NDArrayBool, start: int, length: float, rng: np.random.Generator,
               cfg: SimConfig, v_desired: float, max_expansions: int = 200) -> Route | None:
    """A random walk along successors from lane ``start`` over allowed lanes, at least ``length`` m long.

    At a fork each allowed successor is equally likely; a branch that dead-ends (or leaves the allowed lanes)
    before ``length`` is backtracked. None when no such route exists within ``max_expansions`` lane visits.
    """
    path = [start]
    total = [float(graph.lengths[start])]
    options: list[list[int]] = [_shuffled([s for s in graph.successors[start] if allowed[s]], rng)]
    expansions = 0
    while total[-1] < length:
        if expansions > max_expansions:
            return None
        if not options[-1]:
            path.pop()
            total.pop()
            options.pop()
            if not path:
                return None
            continue
        nxt = options[-1].pop()
        expansions += 1
        path.append(nxt)
        total.append(total[-1] + float(graph.lengths[nxt]))
        options.append(_shuffled([s for s in graph.successors[nxt] if allowed[s]], rng))
    return build_route(graph, allowed, path, cfg, v_desired)


def _shuffled(items: list[int], rng: np.random.Generator) -> list[int]:
    if len(items) > 1:
        order = rng.permutation(len(items))
        items = [items[i] for i in order.tolist()]
    return items


def build_route(graph: LaneGraph, allowed: NDArrayBool, lanes: list[int], cfg: SimConfig,
                v_desired: float) -> Route:
    """Resample the lanes' joined centerline and compute its speed limit profile."""
    pieces = [graph.lines[lanes[0]]] + [graph.lines[i][1:] for i in lanes[1:]]  # shared joint vertex once
    pts = np.concatenate(pieces)
    seg = np.hypot(*np.diff(pts, axis=0).T)
    keep = np.concatenate([[True], seg > 1e-6])
    pts = pts[keep]
    arc = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(pts, axis=0).T))])
    s = np.arange(0.0, arc[-1], ROUTE_DS_M)
    xy = np.stack([np.interp(s, arc, pts[:, 0]), np.interp(s, arc, pts[:, 1])], axis=1)
    d = np.diff(xy, axis=0, append=xy[-1:] + (xy[-1:] - xy[-2:-1]))
    heading = np.unwrap(np.arctan2(d[:, 1], d[:, 0]))
    # Curvature over a 3 m baseline: AV1 centerlines are polylines, so per-vertex kinks would look like tight turns.
    w = max(round(3.0 / ROUTE_DS_M), 1)
    idx = np.arange(len(s))
    turn = np.abs(heading[np.minimum(idx + w, len(s) - 1)] - heading[np.maximum(idx - w, 0)])
    kappa = turn / (2 * w * ROUTE_DS_M)
    v_curve = np.minimum(np.sqrt(cfg.a_lat / np.maximum(kappa, 1e-6)), v_desired)
    # v_allow(s)^2 = min over s' >= s of v_curve(s')^2 + 2 b (s' - s): reverse running minimum.
    c = v_curve**2 + 2 * cfg.b_comfort * s
    v_allow = np.sqrt(np.maximum(np.minimum.accumulate(c[::-1])[::-1] - 2 * cfg.b_comfort * s, 0.0))
    starts = np.concatenate([[0.0], np.cumsum(graph.lengths[lanes])[:-1]])
    forks = [(k, int(lane)) for k, lane in enumerate(lanes[:-1])
             if sum(1 for t in graph.successors[lane] if allowed[t]) >= 2]
    return Route(list(lanes), starts, xy, s, heading, v_allow, forks)


@dataclass
class SimWindow:
    """One simulated window (row 0 is the AV).

    Attributes:
        positions: (A, steps, 2) metres, city frame, as written to the CSV.
        speeds: (A, steps) m/s. accels: (A, steps) m/s² applied over each step.
        routes: per vehicle. s: (A, steps) arc length along its route, m.
        agent: row of the AGENT (the focal vehicle). min_gap: smallest bumper-to-bumper gap between two
            vehicles on the same lane over the recorded steps (m; inf when no lane held two).
        fork_choices: (fork lane id, chosen successor lane id) passed by any vehicle during the recorded steps.
    """

    positions: NDArrayFloat
    speeds: NDArrayFloat
    accels: NDArrayFloat
    routes: list[Route]
    s: NDArrayFloat
    agent: int
    min_gap: float
    fork_choices: list[tuple[str, str]]


def simulate_window(graph: LaneGraph, allowed: NDArrayBool, rng: np.random.Generator, cfg: SimConfig,
                    starts: NDArrayInt | None = None, tries: int = 20) -> SimWindow | None:
    """Simulate one window on the allowed lanes (None when no ego route fits after ``tries`` start lanes, or no
    other vehicle could be placed near it).

    Args:
        graph: the city lane graph.
        allowed: (L,) lanes vehicles may use (the split's region).
        rng: the window's own generator (the window depends on nothing else).
        cfg: vehicle model.
        starts: candidate ego start lanes (default: every allowed lane).
    """
    duration = (cfg.warmup + cfg.steps) * cfg.dt
    pool = np.flatnonzero(allowed) if starts is None else starts
    if not len(pool):
        return None
    ego_route: Route | None = None
    for _ in range(tries):
        lane = int(pool[rng.integers(len(pool))])
        v_des = float(rng.uniform(*cfg.v_desired))
        ego_route = plan_route(graph, allowed, lane, v_des * duration + cfg.lookahead, rng, cfg, v_des)
        if ego_route is not None:
            offset = float(rng.uniform(0.0, graph.lengths[lane]))
            break
    if ego_route is None:
        return None
    routes = [ego_route]
    desired = [v_des]
    s0 = [offset]
    centre = np.array(ego_route.at(offset)[:2])
    near = np.flatnonzero(allowed & (np.hypot(*(graph.mids - centre).T) < cfg.spawn_radius))
    n_others = int(rng.integers(cfg.others[0], cfg.others[1] + 1))
    spawned = [centre]
    for _ in range(4 * n_others):
        if len(routes) > n_others or not len(near):
            break
        lane = int(near[rng.integers(len(near))])
        off = float(rng.uniform(0.0, graph.lengths[lane]))
        v_des = float(rng.uniform(*cfg.v_desired))
        route = plan_route(graph, allowed, lane, off + v_des * duration + cfg.lookahead, rng, cfg, v_des)
        if route is None:
            continue
        p = np.array(route.at(off)[:2])
        if min(float(np.hypot(*(p - q))) for q in spawned) < cfg.spawn_sep:
            continue
        # Converging lanes: two starts far apart in the plane can be close along the route they will share.
        trial = [*routes, route]
        table = [_lane_starts(r) for r in trial]
        gaps, _ = _leaders(trial, table, np.array([*s0, off]), cfg)
        if (gaps < cfg.gap_min + cfg.length).any():
            continue
        spawned.append(p)
        routes.append(route)
        desired.append(v_des)
        s0.append(off)
    if len(routes) < 2:
        return None  # an AV1 file always has an AGENT besides the AV
    return _run(graph, routes, np.array(desired), np.array(s0), rng, cfg)


def _run(graph: LaneGraph, routes: list[Route], desired: NDArrayFloat, s_init: NDArrayFloat,
         rng: np.random.Generator, cfg: SimConfig) -> SimWindow:
    n = len(routes)
    total = cfg.warmup + cfg.steps
    s = s_init.astype(np.float64).copy()
    v = np.array([float(rng.uniform(0.5, 1.0)) * min(desired[i], _allow(routes[i], s[i])) for i in range(n)])
    # Lane -> arc where it starts on each route, to find leaders on shared lanes (first occurrence: loops are rare).
    starts_of = [_lane_starts(r) for r in routes]
    gaps, _ = _leaders(routes, starts_of, s, cfg)
    # Start no closer than the car-following gap allows: spawns behind a slower car would otherwise brake past b_max.
    v = np.minimum(v, np.maximum((gaps - cfg.gap_min) / cfg.headway, 0.0))
    lateral = rng.normal(0.0, cfg.lateral_sd, n).clip(-cfg.lateral_max, cfg.lateral_max)
    rho = 0.98  # AR(1) per step: a wander with a ~5 s correlation time
    pos = np.zeros((n, cfg.steps, 2))
    speeds = np.zeros((n, cfg.steps))
    accels = np.zeros((n, cfg.steps))
    arcs = np.zeros((n, cfg.steps))
    min_gap = math.inf
    for t in range(total):
        gaps, leader = _leaders(routes, starts_of, s, cfg)
        dv = np.where(leader >= 0, v - v[np.maximum(leader, 0)], 0.0)  # closing speed, m/s
        v0 = np.array([max(min(desired[i], _allow(routes[i], s[i])), 0.1) for i in range(n)])
        # IDM: free-road term towards v0 (the curve-limited speed), interaction term from the leader's gap.
        s_star = cfg.gap_min + np.maximum(v * cfg.headway + v * dv / (2 * math.sqrt(cfg.a_max * cfg.b_comfort)), 0)
        interaction = np.where(np.isfinite(gaps), (s_star / np.maximum(gaps, 0.1)) ** 2, 0.0)
        a = cfg.a_max * (1 - (v / v0) ** 4 - interaction)
        a = np.clip(a, -cfg.b_max, cfg.a_max)
        a = np.maximum(a, -v / cfg.dt)  # stop, never reverse
        v_new = v + a * cfg.dt
        s = s + 0.5 * (v + v_new) * cfg.dt
        v = v_new
        lateral = rho * lateral + rng.normal(0.0, cfg.lateral_sd * math.sqrt(1 - rho**2), n)
        lateral = lateral.clip(-cfg.lateral_max, cfg.lateral_max)
        k = t - cfg.warmup
        if k < 0:
            continue
        for i, r in enumerate(routes):
            x, y, h = r.at(float(s[i]))
            pos[i, k] = (x - math.sin(h) * lateral[i], y + math.cos(h) * lateral[i])
        speeds[:, k], accels[:, k], arcs[:, k] = v, a, s
        min_gap = min(min_gap, same_lane_gap(routes, s, cfg.length))
    if cfg.noise_sd > 0:
        pos += rng.normal(0.0, cfg.noise_sd, pos.shape)
    choices: list[tuple[str, str]] = []
    future_forks = np.zeros(n, dtype=bool)
    obs_last = cfg.obs_len - 1  # the current step
    for i, r in enumerate(routes):
        first, last = r.lane_at(float(arcs[i, 0])), r.lane_at(float(arcs[i, -1]))
        for k, lane in r.forks:
            if first <= k < last:
                choices.append((graph.lane_ids[lane], graph.lane_ids[r.lanes[k + 1]]))
                if k >= r.lane_at(float(arcs[i, obs_last])):
                    future_forks[i] = True
    dist = np.hypot(*(pos[:, obs_last] - pos[0, obs_last]).T)
    # The AGENT: a vehicle that meets a fork after the current step (where the map decides), nearest the AV.
    score = dist - 1000.0 * future_forks
    score[0] = math.inf
    agent = int(np.argmin(score))
    return SimWindow(pos, speeds, accels, routes, arcs, agent, min_gap, choices)


def _lane_starts(route: Route) -> dict[int, float]:
    """Lane -> arc (m) where it starts on ``route`` (first occurrence: loops are rare)."""
    return {lane: float(route.lane_start[k]) for k, lane in reversed(list(enumerate(route.lanes)))}


def same_lane_gap(routes: Sequence[Route], s: NDArrayFloat, length: float) -> float:
    """Smallest bumper-to-bumper gap (m) between two vehicles on the same lane (inf when no lane holds two):
    negative means they overlap."""
    by_lane: dict[int, list[float]] = {}
    for r, sj in zip(routes, s.tolist(), strict=True):
        k = r.lane_at(sj)
        by_lane.setdefault(r.lanes[k], []).append(sj - float(r.lane_start[k]))
    best = math.inf
    for offs in by_lane.values():
        if len(offs) > 1:
            best = min(best, float(np.diff(np.sort(offs)).min()) - length)
    return best


def _allow(route: Route, s: float) -> float:
    k = min(int(s / ROUTE_DS_M), len(route.v_allow) - 1)
    return float(route.v_allow[max(k, 0)])


MERGE_LOOKAHEAD_M = 60.0
"""A vehicle is a leader for another as soon as a lane within this distance ahead of it is on the other's route:
at a merge the one nearer the joining lane leads (a zipper), instead of both discovering each other on it."""


def _leaders(routes: list[Route], starts_of: list[dict[int, float]], s: NDArrayFloat,
             cfg: SimConfig) -> tuple[NDArrayFloat, NDArrayInt]:
    """Per vehicle, bumper-to-bumper gap (m, inf when none) to the nearest vehicle ahead on its route's lanes
    (its current lane or one it enters within ``MERGE_LOOKAHEAD_M``), and that leader's row (-1 when none)."""
    n = len(routes)
    # Per vehicle: (lane, distance from the vehicle back to that lane's start; <= 0 ahead) for its near lanes.
    near: list[list[tuple[int, float]]] = []
    for j, r in enumerate(routes):
        sj = float(s[j])
        k = r.lane_at(sj)
        lanes = [(r.lanes[k], sj - float(r.lane_start[k]))]
        for m in range(k + 1, len(r.lanes)):
            back = sj - float(r.lane_start[m])
            if back < -MERGE_LOOKAHEAD_M:
                break
            lanes.append((r.lanes[m], back))
        near.append(lanes)
    gaps = np.full(n, math.inf)
    leader = np.full(n, -1, dtype=np.int64)
    for i in range(n):
        table = starts_of[i]
        si = float(s[i])
        for j in range(n):
            if j == i:
                continue
            for lane, back in near[j]:
                start = table.get(lane)
                if start is None:
                    continue
                ahead = start + back - si  # j's arc position on i's route minus i's
                if 0.0 <= ahead < gaps[i] + cfg.length:
                    gaps[i] = ahead - cfg.length
                    leader[i] = j
                break  # the first shared lane decides who is ahead
    return gaps, leader
