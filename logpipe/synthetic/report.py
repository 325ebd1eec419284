"""Statistics of a pre-training set (``logpipe.synthetic.pretrain``) from its per-scene records
(``OUT/stats/<location>/<n>.json``), finished or not: windows, cars, speed histograms and behaviour events per
location, as JSON and as the Markdown tables of docs/synthetic.md.

CLI: ``python -m logpipe.synthetic.report OUT`` (prints Markdown; writes ``OUT/summary.json``).
"""

from __future__ import annotations

import argparse
import json
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from logpipe.synthetic.flow import EVENTS
from logpipe.synthetic.pretrain import SHARES, SceneStats

SPEED_BINS = ((0, 1), (1, 5), (5, 10), (10, 15), (15, 20), (20, 25), (25, 30), (30, 35), (35, 41))
"""Speed bins of the tables, m/s (the histograms are kept at 1 m/s; the last bin counts 40 m/s and up)."""


def summarise(out: Path) -> dict[str, Any]:
    """Per-location and total figures of the scenes recorded under ``out/stats``."""
    locations: dict[str, Any] = {}
    for name in SHARES:
        files = sorted((out / "stats" / name).glob("*.json"))
        if not files:
            continue
        stats = SceneStats()
        for f in files:
            stats.merge(json.loads(f.read_text()))
        locations[name] = {**stats.summary(), "scenes": len(files), "share": SHARES[name]}
    return {"synthetic": True, "locations": locations,
            "windows": sum(v["windows"] for v in locations.values()),
            "scene_cpu_s": round(sum(v["cpu_s"] for v in locations.values()), 1)}


def markdown(summary: dict[str, Any]) -> str:
    """The two tables: sizes and speeds by location; behaviour events by location."""
    locs = summary["locations"]
    head = "| location | scenes | windows | cars | car-steps | " + " | ".join(
        f"{lo}-{hi} m/s" if hi < 41 else f"{lo}+ m/s" for lo, hi in SPEED_BINS) + " | max m/s | cars dropped |"
    lines = [head, "|" + "---|" * (head.count("|") - 1)]
    for name, v in locs.items():
        hist = v["speed_hist_1ms"]
        total = max(sum(hist), 1)
        shares = [f"{100 * sum(hist[lo:hi]) / total:.1f} %" for lo, hi in SPEED_BINS]
        lines.append(f"| {name} | {v['scenes']:,} | {v['windows']:,} | {v['cars']:,} | {v['car_steps']:,} | "
                     + " | ".join(shares) + f" | {v['speed_max']} | {v['cars_dropped_for_overlap']} |")
    lines += ["", "| location | " + " | ".join(EVENTS) + " |", "|---|" + "---|" * len(EVENTS)]
    for name, v in locs.items():
        lines.append(f"| {name} | " + " | ".join(f"{v['events'][k]:,}" for k in EVENTS) + " |")
    lines += ["", f"Total: {summary['windows']:,} windows; scene CPU time {summary['scene_cpu_s'] / 3600:.2f} h."]
    return "\n".join(lines) + "\n"


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m logpipe.synthetic.report OUT``."""
    ap = argparse.ArgumentParser(prog="python -m logpipe.synthetic.report", description=__doc__.split("\n\n")[0])
    ap.add_argument("out", type=Path, help="the pretrain output folder (with stats/)")
    args = ap.parse_args(argv)
    summary = summarise(args.out)
    (args.out / "summary.json").write_text(json.dumps(summary, indent=1) + "\n")
    print(markdown(summary), end="")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
