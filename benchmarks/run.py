"""``make bench``: run every benchmark module and write one JSON file with their figures.

Each ``benchmarks/bench_*.py`` exposes ``run(quick: bool) -> dict`` that measures its own baseline in the
same process/run and reports medians and ratios (the machine is shared and noisy).
"""

from __future__ import annotations

import argparse
import importlib
import json
import platform
import sys
import time
from pathlib import Path

BENCHMARKS = ["bench_ingest", "bench_rosbag", "bench_raster", "bench_model", "bench_predict"]


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--out", type=Path, default=Path("out/bench.json"))
    parser.add_argument("--quick", action="store_true", help="small corpora, one repeat (smoke run)")
    parser.add_argument("--only", nargs="*", help="benchmark module names to run")
    args = parser.parse_args()
    results: dict[str, object] = {"python": sys.version.split()[0], "machine": platform.machine(),
                                  "started": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())}
    for name in args.only or BENCHMARKS:
        try:
            module = importlib.import_module(f"benchmarks.{name}")
        except ModuleNotFoundError:
            continue
        print(f"[bench] {name} ...", file=sys.stderr, flush=True)
        started = time.perf_counter()
        results[name] = module.run(quick=args.quick)
        print(f"[bench] {name} done in {time.perf_counter() - started:.1f} s", file=sys.stderr, flush=True)
    # Every target with what this run measured against it, in one list (each module keeps its own too).
    targets: list[dict[str, object]] = []
    for name, r in results.items():
        if isinstance(r, dict):
            targets += [dict(t, benchmark=name) for t in r.get("targets", [])]
    results["targets"] = targets
    for t in targets:
        floor = f"; {t['share_of_floor']} of this machine's floor {t['floor']}" if "floor" in t else ""
        print(f"[bench] {'met' if t['met'] else 'NOT met'}: {t['target']}: {t['measured']} (required "
              f"{t['required']}{floor})", file=sys.stderr)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(results, indent=2) + "\n")
    print(json.dumps(results, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
