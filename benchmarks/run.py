"""``make bench``: run every benchmark module and write one JSON file with their figures.

Each ``benchmarks/bench_*.py`` exposes ``run(quick: bool) -> dict`` that measures its own baseline in the
same process/run and reports medians and ratios (the machine is shared and noisy).
"""

from __future__ import annotations

import argparse
import importlib
import json
import os
import platform
import sys
import time
from pathlib import Path
from typing import Any

BENCHMARKS = ["bench_mcap_writers", "bench_mcap_channels", "bench_ingest", "bench_rosbag", "bench_raster",
              "bench_model", "bench_train", "bench_predict", "bench_social"]


def render_targets(results: dict[str, Any], command: str) -> str:
    """The targets of a run as Markdown: each figure beside the figure required and, where the run measured one,
    this machine's floor for it and the share of that floor reached."""
    lines = [
        "# make bench: the issue-35 targets on this machine", "",
        f"Produced by `python -m benchmarks.run {command}` (started {results['started']}, Python "
        f"{results['python']}, {results['machine']}; {machine_line()}). Each figure and its reference come from the "
        "same run; the machine is shared, so compare figures of one run only. Floor: the same outputs written alone "
        "(nothing encoded); for the networks, torch's own recurrent cells (LSTMCell, GRUCell) stepping exactly the "
        "rows the network's recurrences step, nothing else (the full model: the backbone alone plus those cells "
        "plus its environment gathers and W_v projection replayed alone), in the target's unit; share: measured / "
        "floor. For a short run (one small split), the floor plus the run's fixed cost (the same run selecting no "
        "sample) and, with MCAP, reading the original logs it copies.", "",
        "| target | measured | required | met | this machine's floor | share of the floor "
        "| with the run's fixed cost (and reads) | share of that |",
        "|---|---|---|---|---|---|---|---|"]
    for t in results["targets"]:
        floor = (f"{t['floor']:,}", f"{t['share_of_floor']:.2f}") if "floor" in t else ("—", "—")
        bound = (f"{t['bound_with_fixed_cost']:,}", f"{t['share_of_bound']:.2f}") if "bound_with_fixed_cost" in t \
            else ("—", "—")
        lines.append(f"| {t['target']} | {t['measured']:,} | {t['required']:,} | {'yes' if t['met'] else 'no'} | "
                     f"{floor[0]} | {floor[1]} | {bound[0]} | {bound[1]} |")
    return "\n".join([*lines, ""])


def machine_line() -> str:
    """Cores, load average and the vector features the kernels use (torch's own detection), read now."""
    import torch

    from logpipe.model.zhu2020.backbone import native_bf16

    return (f"{os.cpu_count()} cores, 1-min load average {os.getloadavg()[0]:.1f} at the end, torch CPU capability "
            f"{torch.backends.cpu.get_cpu_capability()}, native bf16: {'yes' if native_bf16() else 'no'}")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--out", type=Path, default=Path("out/bench.json"))
    parser.add_argument("--quick", action="store_true", help="small corpora, one repeat (smoke run)")
    parser.add_argument("--only", nargs="*", help="benchmark module names to run")
    parser.add_argument("--markdown", type=Path, help="also write the targets as a Markdown table here")
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
    if args.markdown is not None:
        args.markdown.write_text(render_targets(results, " ".join(sys.argv[1:])))
    print(json.dumps(results, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
