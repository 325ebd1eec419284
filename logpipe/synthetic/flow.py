"""Open-boundary traffic on a ``Roads`` network: vehicles enter where lanes start, leave where they end, and
in between follow cars (IDM), choose turns at forks, change lanes (MOBIL), merge, stop at lights and stop lines,
yield at crossing conflicts, and now and then brake to a standstill and restart (stop-and-go).

Per step (``DT_S`` = 0.1 s), for every vehicle: ``logpipe.synthetic.rules.obstacle_ahead`` finds the nearest
thing to keep a gap to along its planned lanes (a car, including cars on a lane merging into or forking from
its own and cars still half in the lane they leave; a red light or stop line; the first conflict point it could
not claim); IDM turns that gap into an acceleration (jerk-limited); every second ``rules.lane_change`` asks
MOBIL whether a neighbour lane is better and safe (a lane that ends forces it).

Frames and units: metres in the map's frame, m/s, m/s², seconds. Lateral offsets are metres to the left of
the lane's centerline.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from logpipe.synthetic import rules
from logpipe.synthetic.roads import Roads
from logpipe.types import NDArrayFloat, NDArrayInt

DT_S = 0.1
"""Simulation and output step (s): 10 Hz, the rate of every real log the pre-training set stands in for."""


@dataclass(frozen=True)
class FlowConfig:
    """Traffic demand and driver model. Speeds m/s, accelerations m/s², times s, lengths m.

    Attributes:
        speed_factor: each driver's desired speed = lane limit x a draw from this range (capped at v_cap).
        v_cap: top speed of anyone (35 m/s = 126 km/h). a_max, b_comfort: IDM acceleration / comfortable braking.
        b_max: hardest braking. jerk: largest change of acceleration per second (both ways).
        headway: IDM time headway range. gap_min: IDM standstill gap. a_lat: lateral acceleration in curves,
            whose curvature is measured over ``curve_baseline_m`` (polyline kinks are not turns).
        enter_free: a car entering an empty lane keeps its drawn speed (else at most 3 m/s: traffic from a
            standstill upstream).
        demand: arrivals per second per entry lane, drawn once per scene from this range.
        fill: initial vehicles per 100 m of lane. disturb_per_s: rate at which a driver brakes to a stop for no
            map reason (stop-and-go), lasting ``disturb_wait`` once stopped.
        lc_duration: a lane change's lateral move takes this long. politeness, lc_threshold, b_safe: MOBIL.
        stop_wait: a full stop at a stop line lasts this long. car / truck: (length, width) ranges;
            truck_share: share of trucks.
    """

    speed_factor: tuple[float, float] = (0.75, 1.25)
    v_cap: float = 35.0
    a_max: float = 1.8
    b_comfort: float = 2.5
    b_max: float = 7.0
    jerk: float = 12.0
    headway: tuple[float, float] = (0.9, 1.8)
    gap_min: float = 2.0
    a_lat: float = 2.5
    curve_baseline_m: float = 20.0
    enter_free: bool = False
    demand: tuple[float, float] = (0.02, 0.12)
    fill: float = 1.0
    disturb_per_s: float = 1 / 240
    disturb_wait: tuple[float, float] = (0.5, 4.0)
    lc_duration: tuple[float, float] = (2.0, 5.0)
    politeness: float = 0.3
    lc_threshold: float = 0.3
    b_safe: float = 3.5
    stop_wait: tuple[float, float] = (1.0, 3.0)
    car: tuple[tuple[float, float], tuple[float, float]] = ((4.0, 5.2), (1.7, 2.0))
    truck: tuple[tuple[float, float], tuple[float, float]] = ((7.0, 12.0), (2.3, 2.6))
    truck_share: float = 0.05


@dataclass
class Vehicle:
    """One simulated car. ``plan``: lanes after the current one. ``lc_*``: the running lane change (lateral
    offset ``lc_from`` at its start, ``lc_t`` s into ``lc_dur``; ``lc_old`` the lane left, -1 when none;
    ``lc_shift`` arc on the old lane minus arc on the new). ``stopped_at``/``wait``: the stop line served and the
    wait there. ``disturb``: seconds left of a stop-and-go standstill. ``held``/``why``: what the car last kept
    its gap to (``car``, ``control``, ``yield``, ``free``; diagnostics). ``claims``: conflict points it holds."""

    vid: int
    lane: int
    s: float
    v: float
    length: float
    width: float
    v_want: float
    headway: float
    plan: list[int] = field(default_factory=list)
    a: float = 0.0
    d: float = 0.0
    d_rate: float = 0.0
    lc_from: float = 0.0
    lc_t: float = 0.0
    lc_dur: float = 0.0
    lc_old: int = -1
    lc_shift: float = 0.0
    stopped_at: int = -1
    wait: float = 0.0
    disturb: float = 0.0
    standstill: bool = False
    born: int = 0
    leader_v: float = 0.0
    held: bool = False
    why: str = "free"
    claims: set[tuple[int, int, int]] = field(default_factory=set)
    a_want: float = 0.0
    last_lc: int = -1000


@dataclass
class Tracks:
    """What a scene recorded: rows (step, vehicle, x, y, heading, speed, acceleration), vehicle sizes, events.

    Attributes:
        step, vid: (R,) ints. xy: (R, 2) metres. heading: (R,) rad. speed, accel: (R,) m/s, m/s².
        sizes: vid -> (length, width, is_truck). events: (step, vid, kind) with kind one of ``EVENTS``; the
            step is the first recorded one that shows it (a stop: the car stands at that step).
        steps: recorded steps.
    """

    step: NDArrayInt
    vid: NDArrayInt
    xy: NDArrayFloat
    heading: NDArrayFloat
    speed: NDArrayFloat
    accel: NDArrayFloat
    sizes: dict[int, tuple[float, float, bool]]
    events: list[tuple[int, int, str]]
    steps: int


EVENTS = ("lane_change", "forced_lane_change", "turn", "merge", "junction_stop", "stop_and_go", "red_light_stop")
"""Behaviour events a scene counts (``simulate``)."""


class Flow:
    """One scene's traffic. ``region`` (xmin, ymin, xmax, ymax) limits it to lanes inside (AV1 city maps);
    vehicles on a lane outside leave. Use ``simulate``."""

    def __init__(self, roads: Roads, cfg: FlowConfig, rng: np.random.Generator,
                 region: tuple[float, float, float, float] | None = None) -> None:
        self.roads, self.cfg, self.rng = roads, cfg, rng
        mids = np.array([roads.pts[roads.start[k] + roads.count[k] // 2] for k in range(len(roads))])
        if region is None:
            self.inside = np.ones(len(roads), dtype=bool)
        else:
            self.inside = (mids[:, 0] >= region[0]) & (mids[:, 0] <= region[2]) & \
                          (mids[:, 1] >= region[1]) & (mids[:, 1] <= region[3])
        self.entries = [k for k in range(len(roads)) if self.inside[k]
                        and not any(self.inside[p] for p in roads.pred[k])]
        self.demand = {k: float(rng.uniform(*cfg.demand)) for k in self.entries}
        self.queue = dict.fromkeys(self.entries, 0)
        self.vcurve = _curve_limits(roads, cfg.a_lat, cfg.curve_baseline_m)
        self.cars: list[Vehicle] = []
        self.next_id = 1
        self.t = 0
        self.clock0 = float(rng.uniform(0.0, 300.0))  # where in their cycles the lights are at step 0, s
        self.events: list[tuple[int, int, str]] = []
        self.sizes: dict[int, tuple[float, float, bool]] = {}
        self.owner: dict[tuple[int, int, int], int] = {}

    # --- vehicles

    def new_vehicle(self, lane: int, s: float, v: float | None = None) -> Vehicle:
        """A driver drawn from the config on ``lane`` at arc ``s`` (not yet added)."""
        cfg, rng = self.cfg, self.rng
        truck = bool(rng.random() < cfg.truck_share)
        (l_lo, l_hi), (w_lo, w_hi) = cfg.truck if truck else cfg.car
        limit = float(self.roads.limits[lane])
        car = Vehicle(vid=self.next_id, lane=lane, s=s, v=0.0, length=float(rng.uniform(l_lo, l_hi)),
                      width=float(rng.uniform(w_lo, w_hi)),
                      v_want=min(limit * float(rng.uniform(*cfg.speed_factor)), cfg.v_cap) * (0.85 if truck else 1.0),
                      headway=float(rng.uniform(*cfg.headway)), born=self.t)
        car.v = min(car.v_want, float(self.vcurve[lane])) * float(rng.uniform(0.6, 1.0)) if v is None else v
        self.sizes[car.vid] = (car.length, car.width, truck)
        self.next_id += 1
        self.extend_plan(car)
        return car

    def extend_plan(self, car: Vehicle, horizon: float = rules.LOOKAHEAD_M + 20.0) -> None:
        """Choose successors at random (a straight one twice as likely as a turn) until the plan covers
        ``horizon`` m beyond the vehicle or reaches the network's (or region's) end."""
        roads = self.roads
        ahead = roads.lens[car.lane] - car.s + sum(roads.lens[k] for k in car.plan)
        last = car.plan[-1] if car.plan else car.lane
        while ahead < horizon:
            options = [k for k in roads.succ[last] if self.inside[k]]
            if not options:
                return
            weights = np.array([1.0 if roads.turn[k] else 2.0 for k in options])
            last = options[int(self.rng.choice(len(options), p=weights / weights.sum()))]
            car.plan.append(last)
            ahead += roads.lens[last]

    def fill(self) -> None:
        """Place vehicles along the region's lanes (``cfg.fill`` per 100 m, spaced by at least 12 m)."""
        roads = self.roads
        for lane in np.flatnonzero(self.inside).tolist():
            n = self.rng.poisson(self.cfg.fill * roads.lens[lane] / 100.0)
            points = [p for c in roads.conflicts[lane] for p in (c[0], c[3])]
            for s in np.sort(self.rng.uniform(0, roads.lens[lane], n)).tolist():
                if all(abs(s - p) > 10.0 for p in points) and self.clear(lane, s, 12.0):
                    self.cars.append(self.new_vehicle(lane, s))

    def clear(self, lane: int, s: float, gap: float, occ: rules.Occupancy | None = None) -> bool:
        """No vehicle within ``gap`` m of arc ``s`` on ``lane``, its conflicting lanes or its neighbours."""
        occ = rules.occupancy(self.roads, self.cars) if occ is None else occ
        near = [lane, *self.roads.pred[lane], *self.roads.succ[lane]]
        near += [c[1] for c in self.roads.conflicts[lane]]
        for k in near:
            for s_j, j in occ.get(k, ()):
                other = self.cars[j]
                if other.lane == k and k != lane:
                    pos_gap = gap  # other lanes: any car on them counts as near when the lanes touch there
                    xy, _ = self.roads.at(np.array([k]), np.array([s_j]))
                    me, _ = self.roads.at(np.array([lane]), np.array([s]))
                    if float(np.hypot(*(xy[0] - me[0]))) < pos_gap:
                        return False
                elif k == lane and abs(s_j - s) < gap:
                    return False
        return True

    def spawn(self) -> None:
        """Poisson arrivals at each entry lane; a car waits (off-map) until its entry is clear."""
        occ: rules.Occupancy | None = None
        for lane in self.entries:
            self.queue[lane] += int(self.rng.poisson(self.demand[lane] * DT_S))
            if not self.queue[lane]:
                continue
            occ = rules.occupancy(self.roads, self.cars) if occ is None else occ
            if self.clear(lane, 0.0, 10.0, occ):
                gap, v_lead = rules.first_gap(self.roads, self.cars, lane)
                car = self.new_vehicle(lane, 0.0)
                if math.isfinite(gap) or not self.cfg.enter_free:
                    car.v = max(min(car.v, (gap - self.cfg.gap_min) / car.headway, v_lead + 3.0), 0.0)
                self.cars.append(car)
                self.queue[lane] -= 1
                occ = None

    # --- one step

    def step(self) -> None:
        """Advance every vehicle by ``DT_S``."""
        cfg, roads = self.cfg, self.roads
        occ = rules.occupancy(roads, self.cars)
        t_s = self.clock0 + self.t * DT_S
        accel = np.zeros(len(self.cars))
        for i, car in enumerate(self.cars):
            gap, v_lead = rules.obstacle_ahead(self, occ, i, t_s)
            car.leader_v = v_lead
            accel[i] = car.a_want = self.idm(car, gap, v_lead)
        for i, car in enumerate(self.cars):
            if (car.vid + self.t) % 10 == 0:  # each driver considers a lane change once a second, staggered
                rules.lane_change(self, occ, i)
        jerk = cfg.jerk * DT_S
        for i, car in enumerate(self.cars):
            want = float(accel[i])
            a = min(max(want, car.a - jerk), car.a + jerk)
            if want < -cfg.b_comfort * 1.5:
                a = max(want, car.a - 4 * jerk)  # an emergency brake builds up four times faster
            a = max(min(a, cfg.a_max), -cfg.b_max, -car.v / DT_S)
            v_new = car.v + a * DT_S
            car.s += 0.5 * (car.v + v_new) * DT_S
            car.v, car.a = v_new, a
            self.lateral(car)
        self.advance()
        self.spawn()
        self.t += 1

    def idm(self, car: Vehicle, gap: float, v_lead: float) -> float:
        """IDM acceleration towards the desired speed (lane, curve, disturbance) given the gap to what is ahead."""
        cfg, roads = self.cfg, self.roads
        v0 = min(car.v_want, float(self.vcurve[car.lane]))
        if car.plan:
            to_next = roads.lens[car.lane] - car.s
            nxt = car.plan[0]
            v_next = min(float(self.vcurve[nxt]), float(roads.limits[nxt]) * 1.2)
            v0 = min(v0, math.sqrt(v_next**2 + 2 * cfg.b_comfort * max(to_next, 0.0)))
        if car.disturb > 0:
            v0 = 0.0
        v0 = max(v0, 0.1)
        brake_term = car.v * (car.v - v_lead) / (2 * math.sqrt(cfg.a_max * cfg.b_comfort))
        s_star = cfg.gap_min + max(car.v * car.headway + brake_term, 0.0)
        free = 1 - (car.v / v0) ** 4 if car.v <= v0 else -(1 - v0 / car.v) * 2
        inter = (s_star / max(gap, 0.2)) ** 2 if math.isfinite(gap) else 0.0
        return cfg.a_max * (free - inter)

    def lateral(self, car: Vehicle) -> None:
        """Move the lateral offset along a lane change's quintic profile (zero lateral speed at both ends)."""
        if car.lc_dur <= 0:
            car.d_rate = 0.0
            return
        car.lc_t += DT_S * min(1.0, car.v / 4.0)  # a slow car moves across slowly: no sideways crab at a crawl
        tau = min(car.lc_t / car.lc_dur, 1.0)
        shape = 10 * tau**3 - 15 * tau**4 + 6 * tau**5
        d_new = car.lc_from * (1 - shape)
        car.d_rate = (d_new - car.d) / DT_S
        car.d = d_new
        if tau >= 1.0:
            car.lc_old, car.d, car.d_rate, car.lc_dur = -1, 0.0, 0.0, 0.0

    def advance(self) -> None:
        """Carry vehicles over lane ends along their plans; remove those that leave; count events."""
        roads, kept = self.roads, []
        for car in self.cars:
            gone = False
            while car.s >= roads.lens[car.lane]:
                if not car.plan:
                    gone = True
                    break
                car.s -= roads.lens[car.lane]
                prev, car.lane = car.lane, car.plan.pop(0)
                if car.lc_old >= 0:  # still finishing the move: block the lane beside the new one on that side
                    side = int(roads.left[car.lane] if car.d > 0 else roads.right[car.lane])
                    car.lc_old = side if side >= 0 and side != prev else -1
                    if side >= 0:
                        car.lc_shift = roads.project(side, self.positions_of(car)) - car.s
                if roads.turn[car.lane]:
                    self.events.append((self.t + 1, car.vid, "turn"))
                if len(roads.pred[car.lane]) >= 2:
                    self.events.append((self.t + 1, car.vid, "merge"))
                self.extend_plan(car)
            if not gone:
                self.standstill_events(car)
                kept.append(car)
            else:
                for k in car.claims:
                    if self.owner.get(k) == car.vid:
                        del self.owner[k]
        self.cars = kept

    def standstill_events(self, car: Vehicle) -> None:
        """A stop near a controlled lane end is a junction stop; any other stop and restart is stop-and-go."""
        if car.disturb > 0 and car.v < 0.3:
            car.disturb -= DT_S
        if car.v < 0.3 and not car.standstill:
            car.standstill = True
            to_end = self.roads.lens[car.lane] - car.s
            controlled = car.lane in self.roads.signals or car.lane in self.roads.stops
            if controlled and to_end < 25.0:
                kind = "red_light_stop" if car.lane in self.roads.signals else "junction_stop"
                self.events.append((self.t + 1, car.vid, kind))
            else:
                self.events.append((self.t + 1, car.vid, "stop_and_go"))
        elif car.v > 3.0:
            car.standstill = False
        if car.disturb <= 0 and car.v > 5.0 and self.rng.random() < self.cfg.disturb_per_s * DT_S:
            car.disturb = float(self.rng.uniform(*self.cfg.disturb_wait))

    def positions_of(self, car: Vehicle) -> NDArrayFloat:
        """(2,) position of one car (centerline + lateral offset)."""
        xy, h = self.roads.at(np.array([car.lane]), np.array([car.s]))
        out: NDArrayFloat = xy[0] + car.d * np.array([-math.sin(h[0]), math.cos(h[0])])
        return out

    def positions(self) -> tuple[NDArrayFloat, NDArrayFloat]:
        """(n, 2) positions and (n,) headings of the current vehicles (centerline + lateral offset)."""
        if not self.cars:
            return np.zeros((0, 2)), np.zeros(0)
        lane = np.array([c.lane for c in self.cars])
        s = np.array([c.s for c in self.cars])
        xy, h = self.roads.at(lane, s)
        d = np.array([c.d for c in self.cars])
        xy = xy + np.stack([-np.sin(h), np.cos(h)], axis=1) * d[:, None]
        slip = np.arctan2(np.array([c.d_rate for c in self.cars]), np.maximum([c.v for c in self.cars], 0.5))
        return xy, h + slip


def simulate(roads: Roads, cfg: FlowConfig, rng: np.random.Generator, steps: int, warmup: int = 80,
             region: tuple[float, float, float, float] | None = None) -> Tracks:
    """Fill the network, run ``warmup`` steps unrecorded, then record ``steps`` steps (module docstring)."""
    flow = Flow(roads, cfg, rng, region)
    flow.fill()
    for _ in range(warmup):
        flow.step()
    flow.t, flow.events = 0, []
    rows: dict[str, list[NDArrayFloat]] = {k: [] for k in ("step", "vid", "x", "y", "h", "v", "a")}
    for k in range(steps):
        xy, h = flow.positions()
        rows["step"].append(np.full(len(flow.cars), k))
        rows["vid"].append(np.array([c.vid for c in flow.cars], dtype=np.int64))
        rows["x"].append(xy[:, 0])
        rows["y"].append(xy[:, 1])
        rows["h"].append(h)
        rows["v"].append(np.array([c.v for c in flow.cars]))
        rows["a"].append(np.array([c.a for c in flow.cars]))
        flow.step()
    cat = {k: np.concatenate(v) if v else np.zeros(0) for k, v in rows.items()}
    events = [e for e in flow.events if e[0] < steps]
    return Tracks(step=cat["step"].astype(np.int64), vid=cat["vid"].astype(np.int64),
                  xy=np.stack([cat["x"], cat["y"]], axis=1), heading=np.arctan2(np.sin(cat["h"]), np.cos(cat["h"])),
                  speed=cat["v"], accel=cat["a"], sizes=flow.sizes, events=events, steps=steps)


def _curve_limits(roads: Roads, a_lat: float, baseline_m: float = 20.0) -> NDArrayFloat:
    """Per lane, the speed (m/s) its sharpest bend allows at lateral acceleration ``a_lat``."""
    out = np.zeros(len(roads))
    for k in range(len(roads)):
        h = np.unwrap(roads.heading[roads.start[k]:roads.start[k] + roads.count[k]])
        w = max(round(baseline_m / 2 / max(roads.step[k], 1e-3)), 1)
        if len(h) <= 2 * w:
            kappa = abs(float(h[-1] - h[0])) / max(roads.lens[k], 1.0)
        else:
            kappa = float(np.abs(h[2 * w:] - h[:-2 * w]).max()) / (2 * w * float(roads.step[k]))
        out[k] = math.sqrt(a_lat / max(kappa, 1e-4))
    return out
