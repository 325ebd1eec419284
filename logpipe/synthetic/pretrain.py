"""SYNTHETIC pre-training traffic on every real lane graph held (issue 57, item 2): AV1 MIA and PIT, the AV2 log
maps, and the NGSIM US-101, Lankershim and Peachtree lanelet networks. Nothing written here is recorded data.

Each location gets a share of windows (``SHARES``, 20 observed + 30 future steps at 10 Hz). CommonRoad locations
get ``scene_s``-long scenes (60 s: 56 windows a file at ingest's one-a-second protocol), cycling over the
location's real map files; AV1 cities get 60 s scenes on 250 m boxes, cut into one CSV per window every
``AV1_STRIDE`` steps. Scene ``n`` of location ``l`` draws everything from ``default_rng([seed, l, n])``.

Output (``--out``): ``commonroad/<location>/synthetic_<real id>_<n>.xml.gz``,
``av1/<city>/synthetic_<city>_<n>_<w>.csv``, ``generation.json`` (counts, behaviour events, speed histograms,
physical extremes, timings) and a README.

CLI: ``python -m logpipe.synthetic.pretrain --shared ../shared/data --out DIR [--scale F] [--seed S]``.
"""

from __future__ import annotations

import argparse
import json
import resource
import sys
import time
from collections import Counter
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from logpipe.synthetic import scenes
from logpipe.synthetic.flow import EVENTS, FlowConfig, Tracks, simulate
from logpipe.synthetic.roads import LaneExtras, Roads, build_roads

SHARES: dict[str, int] = {"USA_US101": 55_000, "USA_Lanker": 45_000, "USA_Peach": 35_000, "USA_AV2": 45_000,
                          "MIA": 15_000, "PIT": 15_000}
"""Windows per location (210,000). CommonRoad ones are counted as ingest cuts them (a window a second)."""
AV1_STRIDE = 20
"""Steps between the starts of two AV1 windows cut from one scene (2 s; the AV and AGENT are drawn anew)."""
NOISE: dict[str, float] = {"USA_US101": 0.1, "USA_Lanker": 0.1, "USA_Peach": 0.1, "USA_AV2": 0.03,
                           "MIA": 0.05, "PIT": 0.05}
"""White position noise (m) added to written positions, per location: video tracking (NGSIM) is noisier than
lidar tracking (AV2); AV1's is between. Ground-truth states (statistics) are noiseless."""
DEMAND: dict[str, tuple[float, float]] = {"USA_US101": (0.06, 0.4), "MIA": (0.01, 0.08), "PIT": (0.01, 0.08)}
"""Arrivals per second per entry lane where the default (``FlowConfig.demand``) does not fit: the freeway runs
from free flow to congested; an AV1 box has many entry lanes (every lane crossing its edge)."""
WARMUP = 80
FAST_SHARE = 0.3
"""Share of scenes driven well above their lanes' limits (up to ``FlowConfig.v_cap``, bends still slowing cars):
only US-101's maps have a highway limit, so without these a model held out from US-101 would pre-train on no
highway speeds at all (issue 57: standstill to 35 m/s on every lane graph)."""
FAST_FACTOR = (1.6, 2.6)
"""Range of the factor a fast scene's desired speeds are multiplied by (a 35 mph arterial becomes 56-91 mph)."""


HIGHWAY_A_LAT = 3.0
"""Lateral acceleration (m/s²) the highway regime's drivers accept in bends."""
HIGHWAY_CURVE_SPAN_M = 60.0
"""The highway regime reads bends over this arc (m): NGSIM lanelets bend in kinks, and a lane's sharpest bend caps
all of it."""
HIGHWAY_DESIRED = (25.0, 40.0)
"""The highway regime's desired speeds, m/s: the speeds no real training location shows."""
HIGHWAY_DEMAND = (0.03, 0.12)
"""The highway regime's arrivals per second per entry lane, light enough to flow freely."""


@dataclass(frozen=True)
class Regime:
    """How fast a set drives. The default is issue 57's mix: ``FAST_SHARE`` of its scenes multiply their drivers'
    desired speeds by ``FAST_FACTOR`` (they still slow to 1.2 times the next lane's limit, so arterials stay below
    ~23 m/s). With ``desired`` (issue 62, item 4: ``HIGHWAY``) every driver wants a speed drawn from that range
    (m/s) whatever the lane's limit, and lights and stop lines are off: free-flow traffic at speeds no real training
    location shows, on their real lane graphs (bends, merges and crossing conflicts still slow it); ``demand``
    (arrivals per second per entry lane) replaces the location's own, light enough to flow freely."""

    fast_share: float = FAST_SHARE
    v_cap: float = FlowConfig.v_cap
    desired: tuple[float, float] | None = None
    demand: tuple[float, float] | None = None

    def scene(self, roads: Roads, cfg: FlowConfig, rng: np.random.Generator) -> tuple[Roads, FlowConfig]:
        """One scene's lanes and driver model."""
        cfg = replace(cfg, v_cap=self.v_cap, demand=self.demand or cfg.demand)
        if self.desired is not None:
            lo, hi = self.desired
            flat = replace(roads, limits=np.full(len(roads), hi), signals={}, stops=set())
            return flat, replace(cfg, speed_factor=(lo / hi, 1.0), a_lat=HIGHWAY_A_LAT,
                                 curve_baseline_m=HIGHWAY_CURVE_SPAN_M, enter_free=True)
        if rng.random() < self.fast_share:
            factor = rng.uniform(*FAST_FACTOR)
            cfg = replace(cfg, speed_factor=(cfg.speed_factor[0] * factor, cfg.speed_factor[1] * factor))
        return roads, cfg


HIGHWAY = Regime(v_cap=HIGHWAY_DESIRED[1], desired=HIGHWAY_DESIRED, demand=HIGHWAY_DEMAND)


@dataclass
class Location:
    """One location's maps (sources or the AV1 city store) and roads, built once."""

    name: str
    kind: str  # "commonroad" | "av1"
    sources: list[scenes.LaneletSource] = field(default_factory=list)
    roads: list[Roads] = field(default_factory=list)


def load_locations(shared: Path, names: Sequence[str], seed: int) -> list[Location]:
    """The real maps of each named location under ``shared`` (the project's ``../shared/data``)."""
    out = []
    for name in names:
        rng = np.random.default_rng([seed, list(SHARES).index(name), 1_000_000])
        loc = Location(name, "av1" if name in ("MIA", "PIT") else "commonroad")
        if loc.kind == "av1":
            path = next(shared.glob(f"argoverse1/maps/**/{name}_lane_centerlines.npz"))
            loc.roads.append(build_roads(scenes.load_av1(path), LaneExtras(), scenes.CITY_LIMIT, rng, name))
        else:
            if name == "USA_AV2":
                files = sorted(shared.glob("av2/**/log_map_archive_*.json"))
                loc.sources = [scenes.av2_source(p) for p in files]
            else:
                loc.sources = [scenes.ngsim_source(p) for p in sorted(shared.glob(f"commonroad/ngsim/{name}/*.xml"))]
            loc.roads = [build_roads(s.store, s.extras, s.default_limit, rng, s.real_id) for s in loc.sources]
        out.append(loc)
    return out


def run_scene(loc: Location, n: int, rng: np.random.Generator, steps: int, out: Path, regime: Regime = Regime()
              ) -> tuple[Tracks, int, int]:
    """Simulate and write scene ``n`` of ``loc``: (recorded tracks, files written, cars dropped for overlap)."""
    k = n % len(loc.roads)
    roads, cfg = regime.scene(loc.roads[k], FlowConfig(demand=DEMAND.get(loc.name, FlowConfig.demand)), rng)
    if loc.kind == "av1":
        region = scenes.av1_region_of(roads, rng)
        tracks = simulate(roads, replace(cfg, fill=0.8), rng, steps, WARMUP, region)
        tracks, dropped = scenes.remove_overlaps(tracks)
        folder = out / "av1" / loc.name
        folder.mkdir(parents=True, exist_ok=True)
        t0 = 500_000_000.0 + n * 1000.0  # an invented clock, clear of AV1's real times (~3.2e8 s)
        files = scenes.av1_windows(tracks, loc.name, f"synthetic_{loc.name}_{n:06d}", folder, rng, AV1_STRIDE,
                                   NOISE[loc.name], t0)
        return tracks, files, dropped
    src = loc.sources[k]
    tracks = simulate(roads, cfg, rng, steps, WARMUP)
    tracks, dropped = scenes.remove_overlaps(tracks)
    path = out / "commonroad" / loc.name / f"synthetic_{src.real_id}_{n}.xml.gz"
    scenes.write_commonroad(path, src, n, tracks, NOISE[loc.name], rng)
    return tracks, 1, dropped


def windows_of(loc: Location, tracks: Tracks, files: int) -> int:
    """Windows a scene gives: AV1 files, or CommonRoad's one a second over the steps some car is seen whole."""
    if loc.kind == "av1":
        return files
    return max((tracks.steps - 50) // 10 + 1, 0)


def generate(shared: Path, out: Path, *, seed: int = 0, scale: float = 1.0, scene_s: float = 60.0,
             locations: Sequence[str] | None = None, progress: bool = True, regime: Regime = Regime()
             ) -> dict[str, object]:
    """Write the set (module docstring) and return the summary written to ``out/generation.json``.

    Locations take turns (the one furthest from its share goes next), so a run cut short still covers all of
    them; each scene's statistics go to ``out/stats/<location>/<n>.json`` after its files, and a scene that has
    them is not simulated again: re-running the same command resumes.
    """
    names = [n for n in SHARES if n in set(locations or SHARES)]
    t_load = time.process_time()
    locs = load_locations(shared, names, seed)
    load_s = time.process_time() - t_load
    steps = round(scene_s * 10)
    stats = {loc.name: SceneStats() for loc in locs}
    done = dict.fromkeys(stats, 0)
    targets = {name: round(SHARES[name] * scale) for name in stats}
    t_all = time.perf_counter()
    while True:
        todo = [loc for loc in locs if stats[loc.name].windows < targets[loc.name]]
        if not todo:
            break
        loc = min(todo, key=lambda x: stats[x.name].windows / max(targets[x.name], 1))
        n = done[loc.name]
        stats[loc.name].merge(scene_stats(loc, n, seed, steps, out, regime))
        done[loc.name] += 1
        if progress and sum(done.values()) % 20 == 0:
            total = sum(x.windows for x in stats.values())
            print(f"{total:,}/{sum(targets.values()):,} windows, {sum(done.values())} scenes, "
                  f"{time.perf_counter() - t_all:.0f} s", file=sys.stderr, flush=True)
    summary: dict[str, object] = {
        "synthetic": True, "seed": seed, "scale": scale, "scene_steps": steps, "map_load_cpu_s": round(load_s, 1),
        "wall_s": round(time.perf_counter() - t_all, 1),
        "locations": {name: {**st.summary(), "scenes": done[name], "noise_sd_m": NOISE[name],
                             "maps": [r.name for r in loc.roads]}
                      for (name, st), loc in zip(stats.items(), locs, strict=True)},
        "flow": asdict(FlowConfig(v_cap=regime.v_cap)), "regime": asdict(regime),
    }
    summary["windows"] = sum(st.windows for st in stats.values())
    summary["scene_cpu_s"] = round(sum(st.cpu_s for st in stats.values()), 1)
    out.mkdir(parents=True, exist_ok=True)
    (out / "generation.json").write_text(json.dumps(summary, indent=1) + "\n")
    (out / "README.md").write_text(README.format(seed=seed, windows=summary["windows"]))
    return summary


def scene_stats(loc: Location, n: int, seed: int, steps: int, out: Path, regime: Regime = Regime()
                ) -> dict[str, Any]:
    """Scene ``n`` of ``loc``: its statistics from ``out/stats`` when a previous run finished it, else simulated,
    written and recorded there."""
    def simulate_scene() -> dict[str, Any]:
        t0 = time.process_time()
        rng = np.random.default_rng([seed, list(SHARES).index(loc.name), n])
        tracks, files, dropped = run_scene(loc, n, rng, steps, out, regime)
        one = SceneStats()
        one.add(tracks, files, dropped, windows_of(loc, tracks, files))
        one.cpu_s = time.process_time() - t0
        record = {k: getattr(one, k) for k in ("windows", "files", "cars", "car_steps", "dropped", "accel_min",
                                               "accel_max", "jerk_max", "speed_max", "cpu_s")}
        record.update(events=dict(one.events), speed_hist=one.speed_hist.tolist())
        return record

    return resumable_scene(out / "stats" / loc.name / f"{n:06d}.json", simulate_scene)


def cpu_seconds() -> float:
    """CPU seconds of this process and its finished children (SUMO's netconvert): what a set cost to make."""
    kids = resource.getrusage(resource.RUSAGE_CHILDREN)
    return time.process_time() + kids.ru_utime + kids.ru_stime


def resumable_scene(path: Path, simulate_scene: Callable[[], dict[str, Any]]) -> dict[str, Any]:
    """A scene's statistics record at ``path`` when a previous run finished the scene, else ``simulate_scene()``
    (which writes the scene's files), recorded there afterwards: a scene with a record is complete."""
    if path.exists():
        found: dict[str, Any] = json.loads(path.read_text())
        return found
    record = simulate_scene()
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp")
    tmp.write_text(json.dumps(record))
    tmp.replace(path)
    return record


SPEED_BINS = 41
"""Speed histogram bins, 1 m/s each; the last one counts everything from 40 m/s up."""


@dataclass
class SceneStats:
    """Running statistics of one location's scenes (ground-truth states, before tracking noise)."""

    windows: int = 0
    files: int = 0
    cars: int = 0
    car_steps: int = 0
    dropped: int = 0
    events: Counter[str] = field(default_factory=Counter)
    speed_hist: np.ndarray = field(default_factory=lambda: np.zeros(SPEED_BINS, dtype=np.int64))
    accel_min: float = 0.0
    accel_max: float = 0.0
    jerk_max: float = 0.0
    speed_max: float = 0.0
    cpu_s: float = 0.0

    def add(self, tracks: Tracks, files: int, dropped: int, windows: int) -> None:
        """Add one scene."""
        self.windows += windows
        self.files += files
        self.dropped += dropped
        self.cars += len(np.unique(tracks.vid))
        self.car_steps += len(tracks.vid)
        self.events.update(e[2] for e in tracks.events)
        self.speed_hist += np.histogram(np.minimum(tracks.speed, SPEED_BINS - 0.5), bins=np.arange(SPEED_BINS + 1))[0]
        if len(tracks.speed):
            self.speed_max = max(self.speed_max, float(tracks.speed.max()))
            self.accel_min = min(self.accel_min, float(tracks.accel.min()))
            self.accel_max = max(self.accel_max, float(tracks.accel.max()))
            self.jerk_max = max(self.jerk_max, float(np.abs(car_jerks(tracks)).max(initial=0.0)))

    def merge(self, other: dict[str, Any]) -> None:
        """Add another scene's record (``scene_stats``)."""
        for key in ("windows", "files", "cars", "car_steps", "dropped", "cpu_s"):
            setattr(self, key, getattr(self, key) + other[key])
        self.events.update(other["events"])
        hist = np.asarray(other["speed_hist"], dtype=np.int64)  # records of before issue 62 have 36 bins
        self.speed_hist[: len(hist)] += hist
        self.accel_min = min(self.accel_min, float(other["accel_min"]))
        self.accel_max = max(self.accel_max, float(other["accel_max"]))
        self.jerk_max = max(self.jerk_max, float(other["jerk_max"]))
        self.speed_max = max(self.speed_max, float(other["speed_max"]))

    def summary(self) -> dict[str, object]:
        """JSON-ready figures."""
        return {"windows": self.windows, "files": self.files, "cars": self.cars, "car_steps": self.car_steps,
                "cars_dropped_for_overlap": self.dropped, "events": {k: self.events.get(k, 0) for k in EVENTS},
                "speed_hist_1ms": self.speed_hist.tolist(), "speed_max": round(self.speed_max, 2),
                "accel_min": round(self.accel_min, 2), "accel_max": round(self.accel_max, 2),
                "jerk_max": round(self.jerk_max, 1), "cpu_s": round(self.cpu_s, 1)}


def car_jerks(tracks: Tracks) -> np.ndarray:
    """Jerk (m/s³) between consecutive steps of the same car."""
    order = np.lexsort((tracks.step, tracks.vid))
    a, v = tracks.accel[order], tracks.vid[order]
    same = v[1:] == v[:-1]
    out: np.ndarray = (np.diff(a) / 0.1)[same]
    return out


README = """# SYNTHETIC traffic for pre-training — not recorded data

Every vehicle in this folder was **simulated** by `logpipe.synthetic.pretrain` (seed {seed}); none was observed.
Only the lane graphs are real: the NGSIM CommonRoad lanelet networks (`../shared/data/commonroad`), the AV2 log
maps (`../shared/data/av2`) and the AV1 city centerlines (`../shared/data/argoverse1/maps`); see their SOURCE.md
files for provenance and licences. {windows:,} windows of 20 + 30 steps at 10 Hz.

- `commonroad/<location>/synthetic_<real benchmark id>_<n>.xml.gz`: CommonRoad 2020a, the real lanelet network
  copied (AV2 lane segments converted to lanelets), `source="SYNTHETIC traffic (logpipe.synthetic)"`; ingest marks
  each log `synthetic` with its real location (`location/USA_US101`, ...).
- `av1/<city>/synthetic_<city>_<scene>_<window>.csv`: Argoverse 1 forecasting CSVs, CITY_NAME the real city.
- `generation.json`: counts, behaviour events, speed histograms, physical extremes, timings.

What the simulator does and does not model: docs/synthetic.md.
"""


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m logpipe.synthetic.pretrain --shared DIR --out DIR [--scale F] [--seed S]``."""
    ap = argparse.ArgumentParser(prog="python -m logpipe.synthetic.pretrain", description=__doc__.split("\n\n")[0])
    ap.add_argument("--shared", type=Path, required=True, help="the shared data folder (../shared/data)")
    ap.add_argument("--out", type=Path, required=True, help="output folder")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--scale", type=float, default=1.0, help="multiply every location's share of windows")
    ap.add_argument("--scene-seconds", type=float, default=60.0, help="length of one scene, s")
    ap.add_argument("--locations", nargs="*", default=None, help=f"subset of {', '.join(SHARES)}")
    ap.add_argument("--highway", action="store_true",
                    help="every scene fast, up to 40 m/s (issue 62: speeds no real training location shows)")
    args = ap.parse_args(argv)
    summary = generate(args.shared, args.out, seed=args.seed, scale=args.scale, scene_s=args.scene_seconds,
                       locations=args.locations, regime=HIGHWAY if args.highway else Regime())
    print(json.dumps({"windows": summary["windows"], "scene_cpu_s": summary["scene_cpu_s"]}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
