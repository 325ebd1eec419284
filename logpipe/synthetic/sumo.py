"""SYNTHETIC highway-speed traffic from the established simulator, SUMO (``eclipse-sumo`` + ``libsumo``, the
``[sumo]`` extra), on the same real lane graphs as our own generator (issue 62, item 4): the SUMO arm of the
own-generator-versus-SUMO comparison. Nothing written here is recorded data.

Per location (``USA_Lanker``, ``USA_Peach``, ``USA_AV2``, ``USA_US101``: the maps ``pretrain.load_locations``
builds), each map becomes a SUMO network once (``logpipe.synthetic.sumo_net``). Scene ``n`` of location ``l``
draws from ``default_rng([seed, l, n])`` (SUMO's ``--seed`` too): cars enter every lane without a predecessor
(Poisson arrivals) and fill every lane at the start, drive a random walk over the edges and leave where it ends;
desired speeds 25-40 m/s (the highway regime), IDM car following, LC2013 lane changing with a 3 s lateral move.
libsumo steps at 10 Hz; after ``WARMUP_S`` every car's centre, heading, speed and acceleration is recorded every
0.1 s for ``scene_s`` seconds; overlapping cars are dropped (``scenes.remove_overlaps``) and the scene is written
with our own CommonRoad writer (``scenes.write_commonroad``).

Output (``--out``): ``commonroad/<location>/synthetic_sumo_<real id>_<n>.xml.gz`` (benchmark id
``synthetic_<real id>_sumo_<n>``: ingest reads the location and marks the log synthetic), ``nets/<map>/`` (the
SUMO network), ``stats/<location>/<n>.json`` per scene (resume) and ``generation.json``.

CLI: ``python -m logpipe.synthetic.sumo --shared ../shared/data --out DIR --locations ... --windows N --seed S``.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import math
import sys
import tempfile
import time
from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
from lxml import etree

from logpipe.synthetic import scenes
from logpipe.synthetic.flow import DT_S, FlowConfig, Tracks
from logpipe.synthetic.pretrain import (
    HIGHWAY_DEMAND,
    HIGHWAY_DESIRED,
    NOISE,
    SHARES,
    Location,
    cpu_seconds,
    load_locations,
    resumable_scene,
)
from logpipe.synthetic.sumo_net import SumoNet, convert

DESIRED = HIGHWAY_DESIRED
"""Range of every car's desired speed, m/s: our generator's highway regime (the speeds the real data lacks)."""
DEMAND = HIGHWAY_DEMAND
"""Arrivals per second per lane of an entry edge, drawn once per scene: our generator's highway regime."""
FILL_PER_100M = 1.0
"""Cars per 100 m of lane placed at the start (``FlowConfig.fill``), so the warm-up need not wait for cars to cross
the map."""
WARMUP_S = 10.0
HEADWAY = FlowConfig.headway
MAX_ROUTE_EDGES = 60
LC_SPEED_GAIN = 1.0
"""LC2013's eagerness to change lanes for speed (SUMO's default; 5 and 20 gave 0-3 more changes on 4 scenes)."""
STRAIGHT_RAD = 0.15
"""A route continues onto a successor with weight exp(-|turn| / this): mostly straight on, as through traffic on
a fast road does (turning into a cross street at 30 m/s is rare), yet every turn is taken now and then."""
Sizes = dict[str, tuple[float, float, bool]]
"""SUMO vehicle id -> (length m, width m, is a truck)."""
SPEED_BINS = 46
"""1 m/s bins of the speed histogram (0-45 m/s; a car's top speed is its desired speed, <= 40)."""


@dataclass
class NetGraph:
    """What the route draw needs of a SUMO network: edges, their successors, lengths and lane counts."""

    edges: list[str]
    succ: dict[str, list[str]]
    length: dict[str, float]
    lanes: dict[str, int]
    entries: list[str]
    weights: dict[str, np.ndarray]


def read_graph(net: SumoNet) -> NetGraph:
    """The non-internal edges of ``net`` and their links (``sumolib``)."""
    import sumolib  # the optional [sumo] extra: imported where used

    sn = sumolib.net.readNet(str(net.path))
    edges = sorted(e.getID() for e in sn.getEdges())
    succ = {e: sorted(o.getID() for o in sn.getEdge(e).getOutgoing()) for e in edges}
    has_pred = {o for outs in succ.values() for o in outs}

    def heading(e: str, end: bool) -> float:
        pts = sn.getEdge(e).getShape()
        (x0, y0), (x1, y1) = (pts[-2], pts[-1]) if end else (pts[0], pts[1])
        return math.atan2(y1 - y0, x1 - x0)

    weights = {}
    for e, outs in succ.items():
        turn = np.array([abs(math.remainder(heading(o, False) - heading(e, True), 2 * math.pi)) for o in outs])
        w = np.exp(-turn / STRAIGHT_RAD)
        weights[e] = w / w.sum() if len(w) else w
    return NetGraph(edges, succ, {e: sn.getEdge(e).getLength() for e in edges},
                    {e: sn.getEdge(e).getLaneNumber() for e in edges}, [e for e in edges if e not in has_pred],
                    weights)


def _walk(graph: NetGraph, first: str, rng: np.random.Generator) -> list[str]:
    route = [first]
    while len(route) < MAX_ROUTE_EDGES and graph.succ[route[-1]]:
        outs = graph.succ[route[-1]]
        route.append(outs[int(rng.choice(len(outs), p=graph.weights[route[-1]]))])
    return route


def route_xml(graph: NetGraph, rng: np.random.Generator, horizon_s: float) -> tuple[str, Sizes]:
    """The scene's cars as a SUMO route file (sorted by departure) and their sizes: id -> (length, width, truck)."""
    cfg = FlowConfig()
    starts: list[tuple[float, str, str]] = []  # (depart s, edge, departPos)
    for edge in graph.edges:
        for _ in range(int(rng.poisson(graph.length[edge] * graph.lanes[edge] * FILL_PER_100M / 100))):
            starts.append((0.0, edge, "random_free"))
    rate = rng.uniform(*DEMAND)
    for edge in graph.entries:
        t = float(rng.exponential(1 / (rate * graph.lanes[edge])))
        while t < horizon_s:
            starts.append((round(t, 1), edge, "base"))
            t += float(rng.exponential(1 / (rate * graph.lanes[edge])))
    starts.sort(key=lambda s: s[0])
    rows, sizes = ['<routes>'], {}
    for i, (depart, edge, pos) in enumerate(starts):
        truck = bool(rng.random() < cfg.truck_share)
        (l_lo, l_hi), (w_lo, w_hi) = cfg.truck if truck else cfg.car
        length, width = float(rng.uniform(l_lo, l_hi)), float(rng.uniform(w_lo, w_hi))
        sizes[f"v{i}"] = (length, width, truck)
        desired = float(rng.uniform(*DESIRED))
        rows.append(f'<vType id="t{i}" length="{length:.3f}" width="{width:.3f}" minGap="{cfg.gap_min}" '
                    f'accel="{cfg.a_max}" decel="{cfg.b_comfort}" emergencyDecel="{cfg.b_max}" '
                    f'tau="{rng.uniform(*HEADWAY):.3f}" maxSpeed="{desired:.3f}" carFollowModel="IDM" '
                    f'laneChangeModel="LC2013" lcStrategic="1" lcSpeedGain="{LC_SPEED_GAIN}" impatience="0.5"/>')
        rows.append(f'<vehicle id="v{i}" type="t{i}" depart="{depart:.1f}" departLane="best" '
                    f'departPos="{pos}" departSpeed="{"max" if pos == "random_free" else "desired"}" speedFactor="1">'
                    f'<route edges="{" ".join(_walk(graph, edge, rng))}"/></vehicle>')
    rows.append("</routes>")
    return "\n".join(rows) + "\n", sizes


def sumo_argv(net: SumoNet, routes: Path, seed: int, end_s: float) -> list[str]:
    """libsumo's command line: 10 Hz, seeded, continuous lane changes, a car stuck 20 s removed (never teleported:
    a jump would corrupt its track), no console chatter."""
    return ["sumo", "-n", str(net.path), "-r", str(routes), "--step-length", str(DT_S), "--seed", str(seed),
            "--begin", "0", "--end", f"{end_s:.1f}", "--lanechange.duration", "3", "--time-to-teleport", "20",
            "--time-to-teleport.remove", "true", "--ignore-junction-blocker", "5",
            "--max-depart-delay", "3", "--ignore-route-errors", "true", "--collision.action", "warn",
            "--no-step-log", "true", "--no-warnings", "true", "--xml-validation", "never"]


def _libsumo() -> Any:
    """The optional ``[sumo]`` extra's libsumo, imported where used. Its import prints a warning to stdout when
    pyarrow's version differs from the Arrow it was built with (1.28.0: Arrow 23; ours: 26); it does not use Arrow
    for anything here, and the line would land in the CLI's output, so it is swallowed."""
    with contextlib.redirect_stdout(io.StringIO()):
        import libsumo

    return libsumo


def simulate(net: SumoNet, graph: NetGraph, rng: np.random.Generator, steps: int) -> Tracks:
    """One scene on ``net``: ``steps`` recorded steps after ``WARMUP_S`` (module docstring)."""
    libsumo = _libsumo()

    warm = round(WARMUP_S / DT_S)
    routes, sizes = route_xml(graph, rng, (warm + steps) * DT_S)
    wanted = (libsumo.constants.VAR_POSITION, libsumo.constants.VAR_ANGLE, libsumo.constants.VAR_SPEED,
              libsumo.constants.VAR_ACCELERATION)
    rows: list[tuple[int, int, float, float, float, float, float]] = []
    with tempfile.TemporaryDirectory(prefix="logpipe-sumo-") as tmp:
        path, changes = Path(tmp) / "scene.rou.xml", Path(tmp) / "lanechanges.xml"
        path.write_text(routes)
        argv = sumo_argv(net, path, int(rng.integers(2**31 - 1)), (warm + steps + 1) * DT_S)
        libsumo.start([*argv, "--lanechange-output", str(changes)])
        try:
            for k in range(warm + steps):
                libsumo.simulationStep()
                for vid in libsumo.simulation.getDepartedIDList():
                    libsumo.vehicle.subscribe(vid, wanted)
                if k < warm:
                    continue
                for vid, got in libsumo.vehicle.getAllSubscriptionResults().items():
                    (x, y), angle, speed, accel = (got[w] for w in wanted)
                    heading = math.radians(90.0 - angle)  # SUMO: degrees clockwise from north
                    half = sizes[vid][0] / 2  # SUMO's position is the front bumper; ours the centre
                    rows.append((k - warm, int(vid[1:]), x - half * math.cos(heading), y - half * math.sin(heading),
                                 math.remainder(heading, 2 * math.pi), speed, accel))
        finally:
            libsumo.close()
        events = lane_changes(changes, warm, steps)
    return _tracks(rows, sizes, events, steps)


def lane_changes(path: Path, warm: int, steps: int) -> list[tuple[int, int, str]]:
    """(recorded step, car, ``lane_change``) of every lane change in SUMO's ``--lanechange-output`` within the
    recording (SUMO's own log: a change that spans an edge boundary is one there, not a change of edge)."""
    found = []
    for el in etree.parse(str(path)).getroot().iter("change"):
        k = round(float(el.get("time") or 0.0) / DT_S) - 1 - warm  # the step after which SUMO's clock shows it
        if 0 <= k < steps:
            found.append((k, int(str(el.get("id"))[1:]), "lane_change"))
    return found


def _tracks(rows: list[tuple[int, int, float, float, float, float, float]], sizes: Sizes,
            events: list[tuple[int, int, str]], steps: int) -> Tracks:
    arr = np.array(rows, dtype=np.float64).reshape(-1, 7)
    return Tracks(step=arr[:, 0].astype(np.int64), vid=arr[:, 1].astype(np.int64), xy=arr[:, 2:4].copy(),
                  heading=arr[:, 4].copy(), speed=arr[:, 5].copy(), accel=arr[:, 6].copy(),
                  sizes={int(v[1:]): s for v, s in sizes.items()}, events=events, steps=steps)


@dataclass
class SumoLocation:
    """A location's maps (``pretrain.Location``) with their SUMO networks and route graphs."""

    loc: Location
    nets: list[SumoNet]
    graphs: list[NetGraph]


def load(shared: Path, out: Path, names: Sequence[str], seed: int) -> list[SumoLocation]:
    """The named locations' real maps, each converted to a SUMO network under ``out/nets`` once."""
    found = []
    for loc in load_locations(shared, names, seed):
        if not loc.sources:
            raise ValueError(f"{shared}: no lane graphs of {loc.name} (commonroad/ngsim/{loc.name}/*.xml, "
                             "av2/**/log_map_archive_*.json)")
        nets = [convert(roads, out / "nets" / src.real_id) for src, roads in zip(loc.sources, loc.roads, strict=True)]
        found.append(SumoLocation(loc, nets, [read_graph(n) for n in nets]))
    return found


def scene_record(where: SumoLocation, n: int, seed: int, steps: int, out: Path) -> dict[str, Any]:
    """Scene ``n``'s statistics from ``out/stats`` when a previous run finished it, else simulated, written and
    recorded there (after its file: a scene with stats is complete)."""
    return resumable_scene(out / "stats" / where.loc.name / f"{n:06d}.json",
                           lambda: _scene(where, n, seed, steps, out))


def _scene(where: SumoLocation, n: int, seed: int, steps: int, out: Path) -> dict[str, Any]:
    """Simulate scene ``n`` of ``where``, write its file and return its statistics record."""
    loc = where.loc
    t0 = time.process_time()
    rng = np.random.default_rng([seed, list(SHARES).index(loc.name), n])
    k = n % len(loc.sources)
    tracks = simulate(where.nets[k], where.graphs[k], rng, steps)
    tracks, dropped = scenes.remove_overlaps(tracks)
    src = loc.sources[k]
    name = out / "commonroad" / loc.name / f"synthetic_sumo_{src.real_id}_{n}.xml.gz"
    # the benchmark id must differ from our own generator's scene n, and still start "synthetic_<real id>"
    scenes.write_commonroad(name, replace(src, real_id=f"{src.real_id}_sumo"), n, tracks, NOISE[loc.name], rng)
    speed = tracks.speed
    record = {"map": src.real_id, "windows": max((tracks.steps - 50) // 10 + 1, 0), "files": 1,
              "cars": len(np.unique(tracks.vid)), "car_steps": len(speed), "dropped": dropped,
              "lane_changes": len(tracks.events),
              "speed_hist": np.histogram(np.minimum(speed, SPEED_BINS - 0.5), bins=np.arange(SPEED_BINS + 1))[0]
              .tolist(),
              "speed_max": float(speed.max(initial=0.0)), "accel_min": float(tracks.accel.min(initial=0.0)),
              "accel_max": float(tracks.accel.max(initial=0.0)), "cpu_s": time.process_time() - t0}
    return record


def generate(shared: Path, out: Path, *, windows: int, seed: int = 0, scene_s: float = 60.0,
             locations: Sequence[str] = ("USA_Lanker", "USA_Peach", "USA_AV2"), progress: bool = True,
             ) -> dict[str, Any]:
    """Write ``windows`` windows (split over ``locations`` by their ``pretrain.SHARES``) and return the summary
    written to ``out/generation.json``. Locations take turns (the one furthest from its target next); re-running
    the same command resumes."""
    t_cpu, t_wall = cpu_seconds(), time.perf_counter()
    names = [n for n in SHARES if n in set(locations)]
    where = load(shared, out, names, seed)
    load_cpu = cpu_seconds() - t_cpu
    steps = round(scene_s / DT_S)
    total_share = sum(SHARES[n] for n in names)
    targets = {n: round(windows * SHARES[n] / total_share) for n in names}
    records: dict[str, list[dict[str, Any]]] = {n: [] for n in names}
    got = dict.fromkeys(names, 0)
    while todo := [w for w in where if got[w.loc.name] < targets[w.loc.name]]:
        w = min(todo, key=lambda x: got[x.loc.name] / max(targets[x.loc.name], 1))
        rec = scene_record(w, len(records[w.loc.name]), seed, steps, out)
        records[w.loc.name].append(rec)
        got[w.loc.name] += rec["windows"]
        if progress and sum(len(r) for r in records.values()) % 10 == 0:
            print(f"{sum(got.values()):,}/{sum(targets.values()):,} windows, "
                  f"{time.perf_counter() - t_wall:.0f} s", file=sys.stderr, flush=True)
    summary = _summary(records, names, where)
    summary.update(synthetic=True, simulator="SUMO (libsumo)", seed=seed, scene_steps=steps,
                   warmup_s=WARMUP_S, desired_speed_ms=list(DESIRED), map_load_and_netconvert_cpu_s=round(load_cpu, 1),
                   cpu_s_this_run=round(cpu_seconds() - t_cpu, 1),
                   wall_s_this_run=round(time.perf_counter() - t_wall, 1))
    out.mkdir(parents=True, exist_ok=True)
    tmp = out / "generation.json.tmp"
    tmp.write_text(json.dumps(summary, indent=1) + "\n")
    tmp.replace(out / "generation.json")
    return summary


def _summary(records: dict[str, list[dict[str, Any]]], names: Sequence[str], where: list[SumoLocation],
             ) -> dict[str, Any]:
    per: dict[str, Any] = {}
    for name, w in zip(names, where, strict=True):
        recs = records[name]
        hist = np.sum([r["speed_hist"] for r in recs], axis=0) if recs else np.zeros(SPEED_BINS, dtype=np.int64)
        per[name] = {key: sum(r[key] for r in recs) for key in ("windows", "files", "cars", "car_steps", "dropped",
                                                                  "lane_changes")}
        per[name].update(scenes=len(recs), speed_hist_1ms=hist.tolist(),
                         speed_max=round(max((r["speed_max"] for r in recs), default=0.0), 2),
                         accel_min=round(min((r["accel_min"] for r in recs), default=0.0), 2),
                         accel_max=round(max((r["accel_max"] for r in recs), default=0.0), 2),
                         scene_cpu_s=round(sum(r["cpu_s"] for r in recs), 1),
                         maps=[n.path.parent.name for n in w.nets],
                         lanes_left_out=sum(n.dropped_lanes for n in w.nets))
    hist = np.sum([p["speed_hist_1ms"] for p in per.values()], axis=0)
    moving = hist[1:].sum()
    return {"windows": sum(p["windows"] for p in per.values()),
            "scenes": sum(p["scenes"] for p in per.values()),
            "scene_cpu_s": round(sum(p["scene_cpu_s"] for p in per.values()), 1),
            "speed_hist_1ms": hist.tolist(),
            "share_car_steps_ge_25ms": round(float(hist[25:].sum() / max(hist.sum(), 1)), 4),
            "share_moving_car_steps_ge_25ms": round(float(hist[25:].sum() / max(moving, 1)), 4),
            "locations": per}


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m logpipe.synthetic.sumo --shared DIR --out DIR --windows N [--locations ...] [--seed S]``."""
    ap = argparse.ArgumentParser(prog="python -m logpipe.synthetic.sumo", description=__doc__.split("\n\n")[0])
    ap.add_argument("--shared", type=Path, required=True, help="the shared data folder (../shared/data)")
    ap.add_argument("--out", type=Path, required=True, help="output folder")
    ap.add_argument("--windows", type=int, required=True, help="windows to write (56 per 60 s scene)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--scene-seconds", type=float, default=60.0, help="length of one scene, s")
    ap.add_argument("--locations", nargs="+", default=["USA_Lanker", "USA_Peach", "USA_AV2"],
                    choices=["USA_US101", "USA_Lanker", "USA_Peach", "USA_AV2"])
    args = ap.parse_args(argv)
    try:
        summary = generate(args.shared, args.out, windows=args.windows, seed=args.seed,
                           scene_s=args.scene_seconds, locations=args.locations)
    except (OSError, RuntimeError, ValueError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(f"{summary['windows']:,} windows in {summary['scenes']} scenes, {summary['scene_cpu_s']} CPU s "
          f"({summary['share_car_steps_ge_25ms']:.1%} of car-steps >= 25 m/s) -> {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
