"""SYNTHETIC traffic on real Argoverse 1 lane graphs, written as Argoverse 1 forecasting CSVs.

Purpose: data on which the map decides the future (issue 33, item 2), so that the environment net (EN) can be
shown to read the lane raster. Vehicles drive along real AV1 city lane centerlines, pick a successor at random at
every fork, follow a speed profile limited by curvature and acceleration bounds, and keep a car-following gap
(IDM) to the vehicle ahead on their own route. One vehicle per window is the AV (ego) with its own route; one
other is the AGENT. Nothing here is recorded data: files and log ids start with ``synthetic_``.

Frames and units: positions are metres in the AV1 city frame of the map (the same frame as the real CSVs),
speeds m/s, accelerations m/s², time steps 0.1 s (10 Hz), CSV timestamps decimal seconds on an invented clock.

The lane graph and its held-out test region are ``logpipe.synthetic.lanes``; the vehicles and one simulated
window are ``logpipe.synthetic.driving``. This module lays the windows out per city and split and writes them.

CLI: ``python -m logpipe.synthetic.traffic --maps DIR --out DIR --windows N --seed S``.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from logpipe.maps.argoverse1 import city_from_name, sniff_npz
from logpipe.synthetic.driving import SimConfig, SimWindow, simulate_window
from logpipe.synthetic.lanes import LINK_MAX_TURN_DEG, HoldOut, LaneGraph
from logpipe.types import NDArrayBool

AV_TRACK_ID = "00000000-0000-0000-0000-000000000000"
"""The AV's track id in every AV1 CSV."""
CSV_HEADER = "TIMESTAMP,TRACK_ID,OBJECT_TYPE,X,Y,CITY_NAME"


def window_csv(window: SimWindow, city: str, t0_ns: int, dt_ns: int = 100_000_000) -> str:
    """The window as AV1 forecasting CSV text (rows by timestamp, then AV, AGENT, OTHERS)."""
    n, steps = window.positions.shape[:2]
    ids = [AV_TRACK_ID] + [f"00000000-0000-0000-0000-{i:012d}" for i in range(1, n)]
    kinds = ["AV"] + ["AGENT" if i == window.agent else "OTHERS" for i in range(1, n)]
    lines = [CSV_HEADER]
    for k in range(steps):
        ns = t0_ns + k * dt_ns
        stamp = f"{ns // 1_000_000_000}.{ns % 1_000_000_000:09d}"
        for i in range(n):
            x, y = window.positions[i, k]
            lines.append(f"{stamp},{ids[i]},{kinds[i]},{x:.4f},{y:.4f},{city}")
    return "\n".join(lines) + "\n"


@dataclass
class CityPlan:
    """A city's graph, held-out box and lane masks."""

    graph: LaneGraph
    holdout: HoldOut
    train: NDArrayBool
    test: NDArrayBool


def city_maps(maps: Path) -> dict[str, Path]:
    """City -> pickle-free centerline ``.npz`` under ``maps`` (shortest name wins; pickles are never opened)."""
    found: dict[str, Path] = {}
    for p in sorted(maps.rglob("*.npz"), key=lambda q: (len(q.name), str(q))):
        city = city_from_name(p)
        if city and city not in found and sniff_npz(p):
            found[city] = p
    return found


def plan_city(path: Path, holdout_fraction: float, holdout_margin: float) -> CityPlan:
    """Load a city's lane graph and split its lanes into training and held-out ones."""
    graph = LaneGraph.from_path(path)
    box = HoldOut.for_graph(graph, holdout_fraction, holdout_margin)
    train, test = box.lane_masks(graph)
    return CityPlan(graph, box, train, test)


def generate(  # noqa: PLR0913  independent keyword knobs of the generator, all defaulted
    maps: Path, out: Path, windows: int, seed: int, *, test_fraction: float = 0.2,
    holdout_fraction: float = 0.15, holdout_margin: float = 75.0, cfg: SimConfig | None = None,
    cities: Sequence[str] | None = None, progress: bool = True,
) -> dict[str, object]:
    """Write ``windows`` SYNTHETIC windows as AV1 CSVs: ``out/train/`` and ``out/test/`` (held-out regions).

    Windows alternate over the cities; every ``1/test_fraction``-th round over the cities is drawn in the
    held-out boxes (test).
    Window ``k`` uses the generator ``default_rng([seed, k])``, so any window can be regenerated alone.

    Returns:
        The summary also written to ``out/generation.json`` (counts, boxes, speed in windows/s).
    """
    cfg = cfg or SimConfig()
    paths = city_maps(maps)
    if cities:
        paths = {c: paths[c] for c in cities if c in paths}
    if not paths:
        raise SystemExit(f"no AV1 lane-centerline .npz under {maps}")
    t_load = time.perf_counter()
    plans = {c: plan_city(p, holdout_fraction, holdout_margin) for c, p in sorted(paths.items())}
    load_s = time.perf_counter() - t_load
    (out / "train").mkdir(parents=True, exist_ok=True)
    (out / "test").mkdir(parents=True, exist_ok=True)
    names = sorted(plans)
    counts = {f"{c}/{split}": 0 for c in names for split in ("train", "test")}
    failed = 0
    every = max(round(1 / test_fraction), 1) if test_fraction > 0 else 0
    t_start = time.perf_counter()
    base_ns = 400_000_000 * 1_000_000_000  # an invented clock, well clear of the real AV1 times (~3.16e8 s)
    for k in range(windows):
        city = names[k % len(names)]
        plan = plans[city]
        # Count rounds over the cities, not windows, so every city gets its share of test windows.
        split = "test" if every and (k // len(names)) % every == every - 1 else "train"
        rng = np.random.default_rng([seed, k])
        win = simulate_window(plan.graph, plan.test if split == "test" else plan.train, rng, cfg)
        if win is None:
            failed += 1
            continue
        name = f"synthetic_{city}_{k:06d}"
        text = window_csv(win, city, base_ns + k * 10 * 1_000_000_000)
        (out / split / f"{name}.csv").write_text(text)
        counts[f"{city}/{split}"] += 1
        if progress and ((k + 1) % 100 == 0 or k + 1 == windows):
            rate = (k + 1) / max(time.perf_counter() - t_start, 1e-9)
            print(f"\r{k + 1}/{windows} windows  {rate:.1f} windows/s", end="", file=sys.stderr, flush=True)
    if progress:
        print(file=sys.stderr)
    elapsed = time.perf_counter() - t_start
    summary: dict[str, object] = {
        "synthetic": True,
        "seed": seed,
        "windows_requested": windows,
        "windows_written": sum(counts.values()),
        "windows_failed": failed,
        "counts": counts,
        "seconds": round(elapsed, 3),
        "map_load_seconds": round(load_s, 3),
        "windows_per_s": round(sum(counts.values()) / max(elapsed, 1e-9), 2),
        "test_fraction": test_fraction,
        "holdout": {c: asdict(p.holdout) for c, p in plans.items()},
        "lanes": {c: {"total": len(p.graph), "train": int(p.train.sum()), "test": int(p.test.sum()),
                      "forks": len(p.graph.forks), "derived_links": p.graph.derived_links}
                  for c, p in plans.items()},
        "maps": {c: str(p) for c, p in sorted(paths.items())},
        "sim": asdict(cfg),
    }
    (out / "generation.json").write_text(json.dumps(summary, indent=2) + "\n")
    (out / "README.md").write_text(_readme(summary, [str(p) for _, p in sorted(paths.items())]))
    return summary


def _readme(summary: dict[str, object], map_files: list[str]) -> str:
    return f"""# SYNTHETIC traffic on real Argoverse 1 lane graphs — not recorded data

Every file in this folder was **simulated** by `logpipe.synthetic.traffic` (seed {summary['seed']}); no vehicle
here was ever observed. Only the lane centerlines are real: the Argoverse 1 city lane centerlines
(`{'`, `'.join(map_files)}`, CC BY-NC-SA 4.0; see
`../shared/data/argoverse1/SOURCE.md`). Lane successor links were derived from geometry (end vertex = start vertex,
direction change < {LINK_MAX_TURN_DEG:.0f} deg), since the npz holds centerlines only.

Layout: `train/` and `test/` hold Argoverse 1 forecasting CSVs (`{CSV_HEADER}`), 50 steps at 10 Hz,
one AV (the ego, with its own route), one AGENT (a vehicle that meets a fork after step 20 when one does) and
OTHERS. File names and log ids start with `synthetic_`. `test/` windows use only lanes inside each city's held-out
box; `train/` windows only lanes at least the margin outside it (boxes in `generation.json`).

Model: lane following along successor lanes, a uniformly random successor at every fork, IDM car following on
shared lanes, speed limited by curvature (lateral acceleration) and acceleration bounds, a slow lateral wander of a
few decimetres. Not modelled: lane changes, traffic lights, right of way at intersections (paths that cross may
overlap), pedestrians, partial tracks.

Counts: {json.dumps(summary['counts'])}; {summary['windows_per_s']} windows/s.
"""


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m logpipe.synthetic.traffic --maps DIR --out DIR --windows N --seed S``."""
    ap = argparse.ArgumentParser(prog="python -m logpipe.synthetic.traffic", description=__doc__.split("\n\n")[0])
    ap.add_argument("--maps", type=Path, required=True, help="folder with {MIA,PIT}*_lane_centerlines*.npz")
    ap.add_argument("--out", type=Path, required=True, help="output folder (train/, test/, README.md)")
    ap.add_argument("--windows", type=int, default=1000, help="windows to simulate (train + test)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--test-fraction", type=float, default=0.2, help="share of windows drawn in the held-out boxes")
    ap.add_argument("--holdout-fraction", type=float, default=0.15, help="share of a city's lanes in its box")
    ap.add_argument("--holdout-margin", type=float, default=75.0, help="metres training lanes keep from the box")
    ap.add_argument("--cities", nargs="*", default=None, help="restrict to these cities (default: all found)")
    args = ap.parse_args(argv)
    summary = generate(args.maps, args.out, args.windows, args.seed, test_fraction=args.test_fraction,
                       holdout_fraction=args.holdout_fraction, holdout_margin=args.holdout_margin,
                       cities=args.cities)
    print(json.dumps({k: summary[k] for k in ("windows_written", "windows_failed", "counts", "windows_per_s")}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
