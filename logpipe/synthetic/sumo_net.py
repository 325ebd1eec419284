"""A real lane graph (``logpipe.synthetic.roads.Roads``) as a SUMO network, for the SUMO arm of the synthetic
traffic (``logpipe.synthetic.sumo``).

Plain-XML route (nodes, edges, connections) through ``netconvert`` from the ``eclipse-sumo`` wheel:

* junctions: lanelets inside an intersection (shorter than ``JUNCTION_LANE_M`` and crossing another lane) are not
  edges: their ends and those of the lanes they cross fall on one node, and netconvert's internal lanes replace
  them, so SUMO knows who crosses whom (a crossing mid-edge is invisible to it: cars would pass through each other).
* lanes: every other vehicle lane of ``Roads`` is one SUMO lane whose ``shape`` is the real centerline; same-direction
  neighbours (``Roads.left``/``right``) whose starts and ends lie within ``GROUP_END_M`` of each other become the
  lanes of one edge (rightmost = SUMO index 0), so SUMO can change lanes between them; anything else is a one-lane
  edge.
* nodes: an edge ends at the node where its lanes' successors' edges start (union of linked ends), placed at the
  mean of those ends; node type ``priority`` (no traffic lights, stop lines or all-way stops: a highway regime).
* connections: one per real lane-to-lane successor link (across a folded junction: to the edge lanes beyond it);
  netconvert adds no turnarounds.
* speeds: each lane's speed is ``V_TOP`` m/s, lowered in bends to ``sqrt(A_LAT / curvature)`` (SUMO does not slow
  cars in curved normal lanes by itself; our own generator does with the same lateral limit).

Coordinates stay in the map's own frame (``--offset.disable-normalization``).
"""

from __future__ import annotations

import hashlib
import subprocess
from dataclasses import dataclass
from pathlib import Path
from xml.sax.saxutils import quoteattr

import numpy as np

from logpipe.storage.io import atomic_open, atomic_path
from logpipe.synthetic.pretrain import HIGHWAY_A_LAT, HIGHWAY_CURVE_SPAN_M, HIGHWAY_DESIRED
from logpipe.synthetic.roads import Roads
from logpipe.types import NDArrayFloat

PLAIN = ("net.nod.xml", "net.edg.xml", "net.con.xml")
"""The plain-XML files netconvert reads (nodes, edges, connections)."""
NETCONVERT = ["--offset.disable-normalization", "true", "--no-turnarounds", "true", "--geometry.remove", "false",
              "--junctions.corner-detail", "5", "--default.junctions.radius", "1", "--geometry.avoid-overlap", "false",
              "--no-warnings", "true"]
"""netconvert's options: the map's own frame, no U-turns, the real shapes kept, small junctions."""
GROUP_END_M = 8.0
"""Neighbour lanes whose starts (and ends) lie within this distance (m) become lanes of one edge."""
V_TOP = HIGHWAY_DESIRED[1]
"""Speed of a straight lane, m/s: the top of the highway regime's desired speeds."""
A_LAT = HIGHWAY_A_LAT
"""Lateral acceleration a bend allows, m/s²: our generator's highway regime."""
CURVE_SPAN_M = HIGHWAY_CURVE_SPAN_M
"""Curvature is the heading change over this arc (m; a shorter lane: over all of it): a map's kinks between lanelet
pieces are not bends, as in our generator's highway regime."""
JUNCTIONS = True
"""Fold lanelets inside intersections into SUMO junctions (``junction_groups``)."""
JUNCTION_LANE_M = 40.0
"""Longest lanelet folded into a junction, m: a longer lane that crosses another stays an edge."""
NODE_TYPE = "priority"
MIN_LANE_SPEED = 8.0
"""No lane is slower than this, m/s (a hairpin in a map would otherwise stall every car)."""


@dataclass
class SumoNet:
    """A converted network: the ``.net.xml`` path and which ``Roads`` lanes became which edge."""

    path: Path
    edge_of_lane: dict[int, tuple[str, int]]
    dropped_lanes: int
    junction_lanes: int


def lane_points(roads: Roads, lane: int) -> NDArrayFloat:
    """(n, 2) resampled centerline of ``lane``, metres."""
    out: NDArrayFloat = roads.pts[roads.start[lane]:roads.start[lane] + roads.count[lane]]
    return out


def lane_speed(roads: Roads, lane: int) -> float:
    """``V_TOP`` lowered to what the lane's sharpest bend (heading change over ``CURVE_SPAN_M``) allows at ``A_LAT``."""
    h = roads.heading[roads.start[lane]:roads.start[lane] + roads.count[lane]]
    span = min(max(round(CURVE_SPAN_M / max(float(roads.step[lane]), 1e-3)), 1), len(h) - 1)
    if span < 1:
        return V_TOP
    turn = np.abs((h[span:] - h[:-span] + np.pi) % (2 * np.pi) - np.pi)
    kappa = float(turn.max()) / (span * float(roads.step[lane]))
    return float(np.clip(np.sqrt(A_LAT / max(kappa, 1e-9)), MIN_LANE_SPEED, V_TOP))


def group_lanes(roads: Roads) -> list[list[int]]:
    """Lanes as edges: chains of same-direction neighbours, right to left, whose ends line up; else single."""
    def close(a: int, b: int) -> bool:
        pa, pb = lane_points(roads, a), lane_points(roads, b)
        return bool(np.hypot(*(pa[0] - pb[0])) < GROUP_END_M and np.hypot(*(pa[-1] - pb[-1])) < GROUP_END_M)

    def left_of(a: int) -> int:
        b = int(roads.left[a])
        return b if b >= 0 and int(roads.right[b]) == a and close(a, b) else -1

    has_right = {left_of(a) for a in range(len(roads))} - {-1}
    groups, seen = [], set()
    for a in range(len(roads)):
        if a in has_right or a in seen:
            continue
        chain = [a]
        while (b := left_of(chain[-1])) >= 0 and b not in seen and b not in chain:
            chain.append(b)
        seen.update(chain)
        groups.append(chain)
    groups += [[a] for a in range(len(roads)) if a not in seen]  # a neighbour cycle: no clear rightmost lane
    return groups


def _shape(pts: NDArrayFloat) -> str:
    return " ".join(f"{x:.3f},{y:.3f}" for x, y in pts)


def junction_groups(roads: Roads, groups: list[list[int]]) -> set[int]:
    """Groups that become part of a SUMO junction instead of an edge: short ones with a lane crossing another
    lane (``Roads.conflicts``), i.e. the lanelets inside an intersection."""
    return {g for g, members in enumerate(groups)
            if any(roads.conflicts[m] for m in members) and max(roads.lens[m] for m in members) < JUNCTION_LANE_M}


def _nodes(roads: Roads, groups: list[list[int]], inner: set[int]) -> tuple[list[int], NDArrayFloat]:
    """Union of edge ends: per end (2g = start of group g, 2g+1 its end) the node id, and node positions. An
    ``inner`` group's two ends and the ends of every lane it crosses fall on one node: SUMO then knows the
    crossing (as foe links inside that junction)."""
    group_of = {lane: g for g, members in enumerate(groups) for lane in members}
    parent = list(range(2 * len(groups)))

    def find(i: int) -> int:
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    for g, members in enumerate(groups):
        for lane in members:
            for s in roads.succ[lane]:
                parent[find(2 * g + 1)] = find(2 * group_of[s])
        if g in inner:
            parent[find(2 * g + 1)] = find(2 * g)
            for lane in members:
                for other in {c[1] for c in roads.conflicts[lane]}:
                    parent[find(2 * group_of[other])] = find(2 * g)
    ends = np.array([lane_points(roads, m[0])[k] for m in groups for k in (0, -1)])
    roots = [find(i) for i in range(len(parent))]
    ids = {r: k for k, r in enumerate(dict.fromkeys(roots))}
    node = [ids[r] for r in roots]
    pos = np.zeros((len(ids), 2))
    np.add.at(pos, node, ends)
    pos /= np.bincount(node, minlength=len(ids))[:, None]
    return node, pos


def write_plain(roads: Roads, folder: Path) -> tuple[dict[int, tuple[str, int]], int, int]:
    """Write ``net.nod.xml``, ``net.edg.xml``, ``net.con.xml`` under ``folder``; returns lane -> (edge, index),
    the number of lanes left out (an edge whose both ends fell on one node: a loop netconvert refuses) and the
    number folded into junctions."""
    groups = group_lanes(roads)
    inner = junction_groups(roads, groups) if JUNCTIONS else set()
    node, pos = _nodes(roads, groups, inner)
    nodes = [f'<node id="n{k}" x="{x:.3f}" y="{y:.3f}" type="{NODE_TYPE}"/>' for k, (x, y) in enumerate(pos)]
    edges, edge_of = [], {}
    dropped = 0
    for g, members in enumerate(groups):
        if g in inner:
            continue
        if node[2 * g] == node[2 * g + 1]:
            dropped += len(members)
            continue
        lanes = []
        for i, lane in enumerate(members):
            edge_of[lane] = (f"e{g}", i)
            lanes.append(f'<lane index="{i}" shape="{_shape(lane_points(roads, lane))}" '
                         f'width="{float(roads.widths[lane]):.2f}" speed="{lane_speed(roads, lane):.2f}"/>')
        edges.append(f'<edge id="e{g}" from="n{node[2 * g]}" to="n{node[2 * g + 1]}" numLanes="{len(members)}" '
                     f'priority="1" name={quoteattr(roads.lane_ids[members[0]])} '
                     f'shape="{_shape(lane_points(roads, members[0]))}">' + "".join(lanes) + "</edge>")
    cons = [f'<connection from="{edge_of[a][0]}" to="{edge_of[s][0]}" fromLane="{edge_of[a][1]}" '
            f'toLane="{edge_of[s][1]}"/>'
            for a in sorted(edge_of) for s in through(roads, a, edge_of)]
    folder.mkdir(parents=True, exist_ok=True)
    for name, tag, rows in zip(PLAIN, ("nodes", "edges", "connections"), (nodes, edges, cons), strict=True):
        with atomic_open(folder / name, "w") as fh:
            fh.write(f"<{tag}>\n" + "\n".join(rows) + f"\n</{tag}>\n")
    return edge_of, dropped, sum(len(groups[g]) for g in inner)


def through(roads: Roads, lane: int, edge_of: dict[int, tuple[str, int]]) -> list[int]:
    """The edge lanes ``lane`` leads to: its successors, or past lanes folded into a junction, the first edge
    lanes beyond them (a few lanelets deep)."""
    found, todo, seen = [], [(s, 0) for s in roads.succ[lane]], set()
    while todo:
        s, depth = todo.pop()
        if s in edge_of:
            found.append(s)
        elif s not in seen and depth < 4:
            seen.add(s)
            todo += [(t, depth + 1) for t in roads.succ[s]]
    return sorted(set(found))


def netconvert_binary() -> Path:
    """The ``netconvert`` of the installed ``eclipse-sumo`` wheel."""
    import sumo  # the optional [sumo] extra: imported where used

    return Path(sumo.SUMO_HOME) / "bin" / "netconvert"


def convert(roads: Roads, folder: Path) -> SumoNet:
    """``roads`` as ``folder/net.net.xml`` (reused when built from the same plain files: once per map)."""
    net = folder / "net.net.xml"
    edge_of, dropped, folded = write_plain(roads, folder)
    key = hashlib.sha256(b"".join((folder / n).read_bytes() for n in PLAIN) + " ".join(NETCONVERT).encode()).hexdigest()
    stamp = folder / "net.sha256"  # the plain files and options the net was built from: a change rebuilds it
    if net.exists() and stamp.exists() and stamp.read_text() == key:
        return SumoNet(net, edge_of, dropped, folded)
    with atomic_path(net) as tmp:
        cmd = [str(netconvert_binary()), "--node-files", str(folder / PLAIN[0]),
               "--edge-files", str(folder / PLAIN[1]), "--connection-files", str(folder / PLAIN[2]),
               *NETCONVERT, "--output-file", str(tmp)]
        done = subprocess.run(cmd, capture_output=True, text=True, check=False)
        if done.returncode != 0:
            last = (done.stderr.strip().splitlines() or ["no message"])[-1]
            raise RuntimeError(f"{folder}: netconvert failed: {last}")
    with atomic_open(stamp, "w") as fh:
        fh.write(key)
    return SumoNet(net, edge_of, dropped, folded)
