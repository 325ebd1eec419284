"""How much data the residual driving model would need on its worst held-out location (issue 57's learning curve).

The leave-one-location-out run (``scripts.driving_lolo``) finds the full model at 1.57× the best kinematic baseline
on US-101, the only freeway, when no freeway is in training. Two curves, both scored on the same fixed half of
US-101's recording clusters (by hash), against Kalman and constant velocity on the same targets:

* **same road:** the other five locations' training data plus a growing number of US-101's other clusters;
* **more of other roads:** a growing share of the other five locations' training clusters, no US-101 at all.

Each point trains the full model with the shipped recipe (``configs/driving_residual.toml``); the point with all
other-road data and no US-101 is the LOLO fold's own checkpoint (reused, not retrained). Validation (the epoch
choice) is always the other locations' validation clusters.

    python -m scripts.driving_curve [--points same:2 same:4 ...]   # after scripts.driving_lolo

Writes ``docs/results/driving_curve.json`` and ``.md``; checkpoints stay in ``out/driving_lolo/curve/``.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import sys
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from logpipe.model.kinematic import best_baseline
from logpipe.model.residual.checkpoint import load_residual
from logpipe.model.residual.config import ResidualConfig, load_residual_config
from logpipe.model.residual.fit import fit_residual, forecast
from scripts.driving_lolo import CONFIG, K, errors, targets
from scripts.driving_targets import Targets
from scripts.locations import REPO

HELD = "USA_US101"
DEFAULT_POINTS = ("same:0", "same:2", "same:4", "same:all", "other:0.25", "other:0.5")


def _rank(cluster: str) -> float:
    return int(hashlib.sha256(f"curve:{cluster}".encode()).hexdigest()[:12], 16) / 16**12


def held_clusters(real: Targets) -> tuple[list[str], list[str]]:
    """US-101's clusters outside validation, split by hash: (the fixed test half, the addable rest in hash order)."""
    val = real.validation()
    ranked = sorted({str(c) for c in real.cluster[(real.location == HELD) & ~val]}, key=_rank)
    half = len(ranked) // 2
    return ranked[:half], ranked[half:]


def training_rows(real: Targets, point: str, addable: list[str]) -> np.ndarray:
    """Training targets of a curve point (``same:N``/``same:all`` or ``other:F``)."""
    val = real.validation()
    kind, amount = point.split(":")
    other = (real.location != HELD) & ~val
    if kind == "same":
        added = addable if amount == "all" else addable[: int(amount)]
        return np.flatnonzero(other | np.isin(real.cluster, added))
    share = float(amount)
    kept = [c for c in {str(c) for c in real.cluster[other]} if _rank(c) < share]
    return np.flatnonzero(other & np.isin(real.cluster, kept))


def point_model(config: ResidualConfig, real: Targets, rows: np.ndarray, out: Path, lolo: Path,
                point: str) -> tuple[Path, dict[str, Any]]:
    """A point's best checkpoint and cost: the LOLO fold's for ``same:0``, a finished run's, or trained now."""
    if point == "same:0":
        return lolo / HELD / "full" / "real" / "best", json.loads((lolo / HELD / "full" / "cost.json").read_text())
    done = out / "cost.json"
    if done.is_file():
        return out / "real" / "best", dict(json.loads(done.read_text()))
    val_rows = np.flatnonzero((real.location != HELD) & real.validation())
    started = time.perf_counter()
    fit = fit_residual(real.inputs.take(rows), real.window[rows], real.inputs.take(val_rows), config, out / "real",
                       dataset_kind="real", manifest_hash="")
    seconds = time.perf_counter() - started
    cost = {"seconds": round(seconds, 1), "core_hours": round(seconds * config.num_threads / 3600, 3),
            "best_epoch": fit.best_epoch, "train_targets": len(rows), "val_targets": len(val_rows)}
    done.write_text(json.dumps(cost) + "\n")
    return fit.best_checkpoint, cost


def markdown(results: dict[str, Any]) -> str:
    """The curve as a table beside its protocol."""
    base = results["baselines"]
    lines = [
        "# The residual driving model's learning curve on US-101 (issue 57)", "",
        "Produced by `python -m scripts.driving_curve` (after `python -m scripts.driving_lolo`). Test: a fixed half "
        f"of US-101's recording clusters by hash ({results['test_targets']} targets, clusters "
        f"{', '.join(results['test_clusters'])}), never trained on. Each row trains the full residual model "
        "(`configs/driving_residual.toml`) on the data named; the epoch is chosen on the other five locations' "
        "validation clusters. K = 1 FDE at 3 s in metres; ratios to the best kinematic baseline "
        f"(`model.kinematic.best_baseline`, chosen on the other locations: {base['best_choice']}).", "",
        f"Baselines on these targets: constant velocity {base['cv']:.2f}, the best kinematic {base['best']:.2f}.", "",
        "| training data | train targets | US-101 targets in training | K=1 FDE | × best baseline | × CV | minFDE@6 "
        "| core-hours |",
        "|---|---|---|---|---|---|---|---|",
    ]
    best = base["best"]
    for point in results["points"]:
        r = results["points"][point]
        lines.append(f"| {r['label']} | {r['cost']['train_targets']} | {r['us101_train_targets']} | "
                     f"{r['fde']:.2f} | {r['fde'] / best:.3f} | {r['fde'] / base['cv']:.3f} | {r['min_fde']:.2f} | "
                     f"{r['cost']['core_hours']:.2f} |")
    return "\n".join(lines) + "\n"


def _label(point: str, addable: list[str]) -> str:
    kind, amount = point.split(":")
    if kind == "same":
        n = len(addable) if amount == "all" else int(amount)
        return f"other five locations + {n} of {len(addable)} further US-101 clusters"
    return f"{float(amount):.0%} of the other five locations' training clusters, no US-101"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--shared", type=Path, default=REPO.parent / "shared" / "data")
    ap.add_argument("--work", type=Path, default=REPO / "out" / "driving_lolo")
    ap.add_argument("--config", type=Path, default=CONFIG)
    ap.add_argument("--points", nargs="*", default=list(DEFAULT_POINTS))
    ap.add_argument("--out", type=Path, default=REPO / "docs" / "results" / "driving_curve.json")
    ap.add_argument("--train-only", action="store_true", help="train the points' models, write no results")
    args = ap.parse_args(argv)
    config = load_residual_config(args.config)
    real = targets(args, config)
    test_clusters, addable = held_clusters(real)
    test = np.flatnonzero(np.isin(real.cluster, test_clusters))
    train_locs = np.flatnonzero(real.location != HELD)
    observed, pred_len = real.inputs.observed, config.pred_len
    choice = best_baseline.choose(best_baseline.choose_per_method(observed[train_locs], real.future[train_locs]))
    cv_fde = errors(best_baseline.forecast({"method": "cv"}, observed[test], pred_len)[:, None], real.future[test])
    best_fde = errors(best_baseline.forecast(choice, observed[test], pred_len)[:, None], real.future[test])
    results: dict[str, Any] = {
        "protocol": "K=1 FDE at 3 s (mean head) and per-agent minFDE@6; 20 + 30 steps at 10 Hz; real targets only",
        "held_location": HELD, "test_clusters": test_clusters, "addable_clusters": addable,
        "test_targets": len(test), "baselines": {"cv": float(cv_fde["fde"].mean()),
                                                 "best": float(best_fde["fde"].mean()),
                                                 "best_choice": best_baseline.label(choice)}, "points": {}}
    for point in args.points:
        rows = training_rows(real, point, addable)
        best, cost = point_model(replace(config, environment=True), real, rows, args.work / "curve" / point,
                                 args.work, point)
        print(point, cost, file=sys.stderr)
        if args.train_only:
            continue
        net, _ = load_residual(best)
        err = errors(forecast(net, real.inputs.take(test), K), real.future[test])
        results["points"][point] = {"label": _label(point, addable), "cost": cost, "fde": float(err["fde"].mean()),
                                    "min_fde": float(err["min_fde"].mean()),
                                    "us101_train_targets": int((real.location[rows] == HELD).sum())}
    if not args.train_only:
        args.out.write_text(json.dumps(results, indent=1) + "\n")
        args.out.with_suffix(".md").write_text(markdown(results))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
