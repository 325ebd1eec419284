"""Driving rules of ``logpipe.synthetic.flow``: what is ahead of a vehicle (cars, lights, stop lines, conflict
points), and lane changes (MOBIL: Kesting, Treiber and Helbing 2007).

Occupancy (``occupancy``) lists, per lane, the arc positions (m) of the cars on it and of cars that physically
reach into it: a car within ``MERGE_M`` of the end of a lane that merges with this one (placed at the same
distance from the shared end, so whoever is nearer the merge leads: a zipper), a car within ``FORK_M`` of the
start of a lane forking from the same predecessor, and a car still more than ``LC_BLOCK_M`` m into the lane it is
leaving. Conflict points (``Roads.conflicts``) are claimed before a car enters them (``obstacle_ahead``).

Units: metres along lanes, m/s, m/s², seconds.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np

from logpipe.synthetic.roads import Roads

if TYPE_CHECKING:
    from logpipe.synthetic.flow import Flow, Vehicle

LOOKAHEAD_M = 130.0
"""How far ahead (m) a driver looks for cars and controls: IDM's desired gap at 35 m/s is ~60 m."""
CONFLICT_M = 45.0
"""How far ahead (m) of a conflict point two drivers negotiate it."""
MERGE_M = 40.0
FORK_M = 15.0
LC_BLOCK_M = 0.85
"""A changing car blocks the lane it leaves while its centre is more than this (m) off the new centerline."""
CLEAR_M = 1.5
"""Margin (m) kept around a conflict point beyond half a car length."""

Occupancy = dict[int, list[tuple[float, int]]]


def occupancy(roads: Roads, cars: list[Vehicle]) -> Occupancy:
    """Lane -> sorted (arc, car index) of cars on it or reaching into it (module docstring)."""
    occ: Occupancy = {}
    for i, c in enumerate(cars):
        occ.setdefault(c.lane, []).append((c.s, i))
        to_end = roads.lens[c.lane] - c.s
        if to_end < MERGE_M:
            for nxt in roads.succ[c.lane]:
                for p in roads.pred[nxt]:
                    if p != c.lane:
                        occ.setdefault(p, []).append((roads.lens[p] - to_end, i))
        if c.s < FORK_M:
            for q in roads.pred[c.lane]:
                for sib in roads.succ[q]:
                    if sib != c.lane:
                        occ.setdefault(sib, []).append((c.s, i))
        if c.lc_old >= 0 and abs(c.d) > LC_BLOCK_M:
            occ.setdefault(c.lc_old, []).append((c.s + c.lc_shift, i))
    for lst in occ.values():
        lst.sort()
    return occ


def first_gap(roads: Roads, cars: list[Vehicle], lane: int) -> tuple[float, float]:
    """(gap from the lane's start to the rear of its first car, that car's speed); (inf, 0) when empty."""
    best, v = math.inf, 0.0
    for c in cars:
        if c.lane == lane and c.s - c.length / 2 < best:
            best, v = c.s - c.length / 2, c.v
    return best, v


def _car_ahead(occ: Occupancy, cars: list[Vehicle], lane: int, after: float, me: int) -> tuple[float, int]:
    """(arc, index) of the first car on ``lane`` strictly ahead of arc ``after`` other than ``me``."""
    for s_j, j in occ.get(lane, ()):
        if s_j > after and j != me:
            return s_j, j
    return math.inf, -1


def obstacle_ahead(flow: Flow, occ: Occupancy, i: int, t_s: float) -> tuple[float, float]:
    """(bumper gap in m, its speed) to the nearest thing vehicle ``i`` must keep a gap to along its lanes.

    Conflict points are claimed, all those within ``CONFLICT_M`` on the car's path at once or none (no car
    holds one while waiting for another, so no circular wait); a car stops short of the first point it could
    not claim, and claims nothing while a light or stop line comes first, or while the car it follows stands
    within a car length past the last point (it would block the crossing lane).
    """
    roads, cars = flow.roads, flow.cars
    car = cars[i]
    gap, v_lead = math.inf, 0.0
    offset = -car.s  # arc of the current lane's start relative to the car
    ctrl = math.inf
    zone = car.length / 2 + CLEAR_M
    path: list[tuple[float, tuple[int, int, int], int, float, float]] = []
    for lane in [car.lane, *car.plan]:
        if offset > LOOKAHEAD_M:
            break
        for s_c, other, s_o, s_c1, s_o1 in roads.conflicts[lane]:
            d = offset + s_c
            if -zone - (s_c1 - s_c) < d < CONFLICT_M:
                path.append((d, _key(lane, s_c, other, s_o), other, s_o, s_o1))
        s_j, j = _car_ahead(occ, cars, lane, car.s if offset < 0 else -math.inf, i)
        if j >= 0:
            g = offset + s_j - (car.length + cars[j].length) / 2
            if g < gap:
                gap, v_lead = g, cars[j].v
        if ctrl == math.inf:
            ctrl = _control_gap(flow, car, lane, offset + roads.lens[lane], t_s)
        if j >= 0:
            break
        offset += roads.lens[lane]
    if car.lc_old >= 0 and abs(car.d) > LC_BLOCK_M:  # half still in the lane it leaves: mind that lane's car too
        s_j, j = _car_ahead(occ, cars, car.lc_old, car.s + car.lc_shift, i)
        if j >= 0 and s_j - car.s - car.lc_shift - (car.length + cars[j].length) / 2 < gap:
            gap, v_lead = s_j - car.s - car.lc_shift - (car.length + cars[j].length) / 2, cars[j].v
    why = "car" if math.isfinite(gap) else "free"
    if ctrl < gap:
        gap, v_lead, why = ctrl, 0.0, "control"
    g_claim = _claim(flow, occ, car, path, zone, ctrl, gap + car.length if v_lead < 2.0 else math.inf)
    if g_claim < gap:
        gap, v_lead, why = g_claim, 0.0, "yield"
    car.held, car.why = why in ("control", "yield"), why
    return gap, v_lead


def _key(lane: int, s: float, other: int, s_other: float) -> tuple[int, int, int]:
    """One conflict point, the same from both lanes: (lower lane, higher lane, decimetre on the lower)."""
    return (lane, other, round(s * 10)) if lane < other else (other, lane, round(s_other * 10))


def _claim(flow: Flow, occ: Occupancy, car: Vehicle, path: list[tuple[float, tuple[int, int, int], int, float, float]],
           zone: float, ctrl: float, blocked_at: float) -> float:
    """Keep the claims on ``path`` still ahead, try to claim the rest (all or none; see ``obstacle_ahead``),
    and return the gap (m) to the stop short of the first point not held (inf when all are)."""
    owner = flow.owner
    ahead = {p[1] for p in path}
    for k in car.claims - ahead:
        if owner.get(k) == car.vid:
            del owner[k]
    car.claims &= ahead
    need = [p for p in path if p[1] not in car.claims]
    if not need:
        return math.inf
    first = need[0][0]
    stop = first - zone
    if ctrl < first or first > blocked_at - zone:
        return stop if stop > -0.5 else math.inf
    free = all(owner.get(k, car.vid) == car.vid and not _occupied(flow, occ, other, s0, s1)
               for _, k, other, s0, s1 in need)
    if not free:
        return stop if stop > -0.5 else math.inf
    for _, k, _, _, _ in need:
        owner[k] = car.vid
        car.claims.add(k)
    return math.inf


def _occupied(flow: Flow, occ: Occupancy, lane: int, s0: float, s1: float) -> bool:
    """A car on ``lane`` covers part of its arcs ``s0``..``s1`` (within half its length plus ``CLEAR_M``)."""
    for s_j, j in occ.get(lane, ()):
        margin = flow.cars[j].length / 2 + CLEAR_M
        if s0 - margin < s_j < s1 + margin:
            return True
    return False


def _control_gap(flow: Flow, car: Vehicle, lane: int, end: float, t_s: float) -> float:
    """Gap (m) to the stop line at a lane end ``end`` m ahead: a red light the car can still stop for, or a
    stop line it has not yet stopped at (a full stop, then a random wait, then go). inf when none applies."""
    roads, cfg = flow.roads, flow.cfg
    to_line = end - car.length / 2 - 0.5
    if to_line > LOOKAHEAD_M:
        return math.inf
    signal = roads.signals.get(lane)
    if signal is not None and signal.is_red(t_s):
        can_stop = to_line > 0 and car.v**2 / (2 * to_line) < cfg.b_max * 0.6
        return to_line if can_stop else math.inf
    if lane in roads.stops and car.stopped_at != lane:
        if to_line < 3.0 and car.v < 0.3 and car.lane == lane:
            car.wait += 0.1
            if car.wait >= 1.0 + 2.0 * ((car.vid * 7919) % 100) / 100.0:
                car.stopped_at, car.wait = lane, 0.0
                return math.inf
        return to_line if to_line > -1.0 else math.inf
    return math.inf


def lane_change(flow: Flow, occ: Occupancy, i: int) -> None:
    """MOBIL: move to a same-direction neighbour when it is safe for the new follower (it brakes less than
    ``b_safe``) and the gain (own plus ``politeness`` x the followers') beats ``lc_threshold``; a lane that ends
    with no successor while its neighbour goes on adds a bias that grows towards its end (a forced merge)."""
    roads, cars, cfg = flow.roads, flow.cars, flow.cfg
    car = cars[i]
    lane = car.lane
    ends = not car.plan and not roads.succ[lane]
    if car.lc_dur > 0 or car.v < (1.0 if ends else 3.0) or car.disturb > 0 or flow.t - car.last_lc < 80 \
            or car.claims or roads.conflicts[lane] or not _straight_ahead(flow, car):
        return  # not inside a junction (its conflicts are negotiated per lane), nor into a bend
    to_end = roads.lens[lane] - car.s
    best, best_gain, forced = -1, cfg.lc_threshold, False
    a_now = car.a_want
    for nb in (int(roads.left[lane]), int(roads.right[lane])):
        if nb < 0 or not flow.inside[nb] or roads.conflicts[nb] or flow.vcurve[nb] < 15.0:
            continue
        s_nb = roads.project(nb, _position(roads, car))
        lead_s, lead, fol_s, fol = _around(roads, occ, nb, s_nb, i)
        g_lead = lead_s - s_nb - (car.length + cars[lead].length) / 2 if lead >= 0 else math.inf
        g_fol = s_nb - fol_s - (car.length + cars[fol].length) / 2 if fol >= 0 else math.inf
        if g_lead < 2.0 or g_fol < 2.0:
            continue
        a_me = flow.idm(car, g_lead, cars[lead].v if lead >= 0 else car.v)
        gain = a_me - a_now
        if fol >= 0:
            a_fol = flow.idm(cars[fol], g_fol, car.v)
            if a_fol < -cfg.b_safe:
                continue
            gain += cfg.politeness * (a_fol - cars[fol].a)
        nb_ends = not roads.succ[nb]
        must = ends and not nb_ends and to_end < 250.0
        if must:
            gain += 1.0 + 200.0 / max(to_end, 5.0)
        elif nb_ends and not ends:
            continue  # never move into a lane that is about to end
        if gain > best_gain:
            best, best_gain, forced = nb, gain, must
    if best >= 0:
        _start_change(flow, car, best, forced)


def _straight_ahead(flow: Flow, car: Vehicle) -> bool:
    """The lanes the car covers during a lane change (5 s at its speed, plus 10 m) are nearly straight (their
    bends allow 15 m/s): an offset from a tight bend's centerline would sweep sideways faster than the car."""
    reach, ahead = car.v * 5.0 + 10.0, -car.s
    for lane in [car.lane, *car.plan]:
        if ahead > reach:
            break
        if flow.vcurve[lane] < 15.0:
            return False
        ahead += flow.roads.lens[lane]
    return True


def _car_behind(occ: Occupancy, lane: int, before: float, me: int) -> tuple[float, int]:
    """(arc, index) of the last car on ``lane`` behind arc ``before`` other than ``me``."""
    found = (-math.inf, -1)
    for s_j, j in occ.get(lane, ()):
        if s_j >= before:
            break
        if j != me:
            found = (s_j, j)
    return found


def _around(roads: Roads, occ: Occupancy, lane: int, s: float, me: int) -> tuple[float, int, float, int]:
    """(arc, index) of the cars ahead and behind arc ``s`` of ``lane``, looking one lane on into its successors
    and back into its predecessors (arcs then count from ``lane``'s start)."""
    lead_s, lead = _first_after(occ, lane, s, me)
    if lead < 0:
        for nxt in roads.succ[lane]:
            s_j, j = _first_after(occ, nxt, -math.inf, me)
            if j >= 0 and roads.lens[lane] + s_j < lead_s:
                lead_s, lead = roads.lens[lane] + s_j, j
    fol_s, fol = _car_behind(occ, lane, s, me)
    if fol < 0:
        for prv in roads.pred[lane]:
            s_j, j = _car_behind(occ, prv, math.inf, me)
            if j >= 0 and s_j - roads.lens[prv] > fol_s:
                fol_s, fol = s_j - roads.lens[prv], j
    return lead_s, lead, fol_s, fol


def _first_after(occ: Occupancy, lane: int, after: float, me: int) -> tuple[float, int]:
    for s_j, j in occ.get(lane, ()):
        if s_j > after and j != me:
            return s_j, j
    return math.inf, -1


def _position(roads: Roads, car: Vehicle) -> np.ndarray:
    here, h = roads.at(np.array([car.lane]), np.array([car.s]))
    out: np.ndarray = here[0] + car.d * np.array([-math.sin(h[0]), math.cos(h[0])])
    return out


def _start_change(flow: Flow, car: Vehicle, nb: int, forced: bool) -> None:
    """Switch the car to lane ``nb`` at once; its lateral offset then decays to 0 over 2-5 s (``Flow.lateral``)."""
    roads = flow.roads
    pos = _position(roads, car)
    s_nb = roads.project(nb, pos)
    there, h2 = roads.at(np.array([nb]), np.array([s_nb]))
    rel = pos - there[0]
    d_new = float(-math.sin(h2[0]) * rel[0] + math.cos(h2[0]) * rel[1])
    car.lc_shift = car.s - s_nb  # arc on the old lane minus arc on the new: parallel lanes keep it
    car.lc_old, car.lane, car.s = car.lane, nb, s_nb
    car.d, car.lc_from, car.lc_t = d_new, d_new, 0.0
    car.lc_dur = float(flow.rng.uniform(*flow.cfg.lc_duration))
    car.last_lc = flow.t
    car.plan = []
    flow.extend_plan(car)
    flow.events.append((flow.t + 1, car.vid, "forced_lane_change" if forced else "lane_change"))
