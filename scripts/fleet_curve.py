"""What a fleet gets from training on its own logs (issue 62's learning curve): for each of the six real locations,
held-out scores after the driving recipe trains on 1, 2 or 5 of that location's recordings.

The situation simulated is a fleet on roads the shipped model never saw: the "shipped" start is the leave-one-
location-out fold model of the location (``scripts.driving_lolo``: trained on the other five only). Each location's
recording clusters (logs that share tracks are one) are split by hash into a fixed test half and a pool; a point
takes the first N clusters of the pool and runs the recipe of ``logpipe train DATASET --out RUN`` without a config
(``model.residual.fleet``): validation chosen by ``logpipe.dataset.holdout`` on those logs alone (whole recordings
when there are enough, else the later part of each), fine-tuning from the start and training from scratch, the
better on validation kept. Argoverse 1's recordings are 5 s sequences with one window each, so its points take 5,
10 and all of its pool instead. Scored on the test half, beside constant velocity, the best kinematic baseline
chosen on the point's training targets (what the trained model falls back to), the start alone (zero-shot) and as
``logpipe predict`` runs it by default on an unseen road (physics at K = 1)::

    python -m scripts.fleet_curve          # after scripts.driving_lolo (its targets and fold models)

Writes ``docs/results/fleet_curve.json`` and ``.md``; checkpoints stay in ``out/driving_lolo/fleet/``.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc

from logpipe.dataset.holdout import choose_holdout
from logpipe.dataset.reader import Dataset
from logpipe.model.kinematic import best_baseline
from logpipe.model.residual.checkpoint import load_residual
from logpipe.model.residual.config import load_residual_config
from logpipe.model.residual.fit import fit_residual, forecast, ranked_forecasts
from logpipe.model.residual.modes import model_modes
from logpipe.model.residual.ood import fallback_forecasts
from logpipe.types import NDArrayFloat
from scripts.driving_lolo import CONFIG, K, errors, targets
from scripts.driving_targets import LOCATIONS, Targets
from scripts.locations import REPO

POINTS = (1, 2, 5)
AV1_POINTS = (5, 10, 0)
"""Argoverse 1's points, sequences (0: the whole pool)."""


def _rank(cluster: str) -> float:
    return int(hashlib.sha256(f"fleet:{cluster}".encode()).hexdigest()[:12], 16) / 16**12


def split_clusters(real: Targets, location: str) -> tuple[list[str], list[str]]:
    """A location's clusters by hash: (the fixed test half, the pool in hash order)."""
    ranked = sorted({str(c) for c in real.cluster[real.location == location]}, key=_rank)
    half = len(ranked) // 2
    return ranked[:half], ranked[half:]


def _dataset(location: str) -> str:
    return "av1" if location.startswith("AV1") else "av2" if location == "AV2" else "ngsim"


def recipe_rows(real: Targets, ds: Dataset, clusters: list[str]) -> tuple[np.ndarray, np.ndarray, str]:
    """Training and validation target rows of the clusters' logs as the recipe's holdout splits them, and how."""
    rows = np.flatnonzero(np.isin(real.cluster, clusters))
    logs = sorted({str(log) for log in real.log[rows]})
    samples = ds.samples().filter(pc.is_in(pc.field("log_id"), pa.array(logs)))
    holdout = choose_holdout([ds.logs().filter(pc.is_in(pc.field("log_id"), pa.array(logs)))], [samples])
    val_ids = set(holdout.val_ids[0])
    train_ids = set(holdout.train_ids[0])
    return (rows[np.isin(real.sample[rows], list(train_ids))], rows[np.isin(real.sample[rows], list(val_ids))],
            holdout.how)


def run_point(real: Targets, rows: tuple[np.ndarray, np.ndarray], start: Path, out: Path) -> dict[str, Any]:
    """The recipe's two candidates on ``rows`` (train, val); the one with the lower validation score kept."""
    done = out / "point.json"
    if done.is_file():
        return dict(json.loads(done.read_text()))
    config = load_residual_config(CONFIG)
    train, val = rows
    started = time.perf_counter()
    starts = (("scratch", None), ("finetune", start)) if len(val) else (("finetune", start),)
    fits = {name: fit_residual(real.inputs.take(train), real.window[train],
                               real.inputs.take(val) if len(val) else None, config, out / name, dataset_kind="real",
                               manifest_hash="", init_from=init)
            for name, init in starts}
    scores = {n: f.best_metrics["fde"] + f.best_metrics[f"min_fde_{config.modes + 1}"] for n, f in fits.items()
              if len(val)}
    chosen = min(scores, key=lambda n: scores[n]) if scores else "finetune"
    point = {"chosen": chosen, "validation_scores": scores, "best": str(fits[chosen].best_checkpoint),
             "seconds": round(time.perf_counter() - started, 1), "train_targets": len(train), "val_targets": len(val)}
    done.write_text(json.dumps(point) + "\n")
    return point


def _k1_source(real: Targets, net: Any, fallback: dict[str, Any], val: np.ndarray) -> str:
    """``model.residual.compare.k1_source`` on the point's validation targets: the model's mean head only where it
    beats the fallback there."""
    if not len(val):
        return "physics"
    truth, pred_len = real.future[val], real.future.shape[1]
    mine = _fde(forecast(net, real.inputs.take(val), K), truth)["fde"]
    theirs = _fde(best_baseline.forecast(fallback, real.inputs.observed[val], pred_len)[:, None], truth)["fde"]
    return "model" if mine < theirs else "physics"


def _fde(forecasts: NDArrayFloat, truth: NDArrayFloat) -> dict[str, float]:
    e = errors(forecasts, truth)
    return {"fde": float(e["fde"].mean()), "min_fde": float(e["min_fde"].mean())}


def location_curve(real: Targets, datasets: dict[str, Dataset], location: str, work: Path) -> dict[str, Any]:
    """Every point of one location, with the baselines and the start on its test half."""
    test_clusters, pool = split_clusters(real, location)
    test = np.flatnonzero(np.isin(real.cluster, test_clusters))
    truth, observed, pred_len = real.future[test], real.inputs.observed[test], real.future.shape[1]
    start = work / location / "full" / "real" / "best"
    zero = forecast(load_residual(start)[0], real.inputs.take(test), K)
    out: dict[str, Any] = {"test_clusters": len(test_clusters), "test_targets": len(test), "pool": len(pool),
                           "cv": _fde(best_baseline.forecast({"method": "cv"}, observed, pred_len)[:, None], truth),
                           "start": _fde(zero, truth), "points": {}}
    points = AV1_POINTS if location.startswith("AV1") else (*(n for n in POINTS if n < len(pool)), 0)
    for n in points:  # 0: the whole pool (a location with fewer than 5 pooled recordings ends there)
        clusters = pool[: n or len(pool)]
        train, val, how = recipe_rows(real, datasets[_dataset(location)], clusters)
        point = run_point(real, (train, val), start, work / "fleet" / location / str(n or "all"))
        net, meta = load_residual(Path(point["best"]))
        fallback = meta.ood["fallback_k1"]  # chosen on its training targets
        physics = best_baseline.forecast(fallback, observed, pred_len)[:, None]
        ranked = ranked_forecasts(net, real.inputs.take(test))
        world = model_modes(ranked, K)
        k1 = _k1_source(real, net, fallback, val)
        # predict's default with a physics K = 1: physics as mode 0, the model's modes around it
        shipped = fallback_forecasts(meta.ood, observed, ranked, K) if k1 == "physics" else world
        out["points"][str(n or len(pool))] = point | {
            "clusters": len(clusters), "validation": how, "model": _fde(world, truth), "k1_source": k1,
            "as_predict_runs_it": _fde(shipped, truth),
            "best_kinematic": _fde(physics, truth) | {"choice": best_baseline.label(fallback)}}
        print(location, n, out["points"][str(n or len(pool))]["model"], file=sys.stderr)
    return out


def markdown(results: dict[str, Any]) -> str:
    """The curve: per location and point, K = 1 FDE and minFDE@6 against CV and the best kinematic baseline."""
    lines = ["# Training on a fleet's own logs: the learning curve per location (issue 62)", "",
             __doc__.split("\n\n")[1].replace("\n", " "), "",
             "Produced by `python -m scripts.fleet_curve` after `python -m scripts.driving_lolo`. K = 1 FDE at 3 s "
             "(the mean head) and per-agent minFDE@6, metres, on each location's test half; x CV and x best: the "
             "trained model's K = 1 FDE over constant velocity's and over the best kinematic baseline's (chosen on the "
             "point's training targets) on the same targets.", "",
             "| location | recordings trained on | train / val targets | start kept | mean head K = 1 FDE | x CV | "
             "x best | K = 1 in predict (source) | x best | minFDE@6 | the start alone (never saw it): K = 1 / "
             "minFDE@6 | CV | best kinematic | seconds |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for location, r in results["locations"].items():
        for n, p in r["points"].items():
            fde = p["model"]["fde"]
            lines.append(
                f"| {location} | {n} of {r['pool']} ({r['test_targets']} test targets) | {p['train_targets']} / "
                f"{p['val_targets']} | {p['chosen']} | {fde:.2f} | {fde / r['cv']['fde']:.3f} | "
                f"{fde / p['best_kinematic']['fde']:.3f} | {p['as_predict_runs_it']['fde']:.2f} ({p['k1_source']}) | "
                f"{p['as_predict_runs_it']['fde'] / p['best_kinematic']['fde']:.3f} | "
                f"{p['as_predict_runs_it']['min_fde']:.2f} | {r['start']['fde']:.2f} / "
                f"{r['start']['min_fde']:.2f} | {r['cv']['fde']:.2f} | {p['best_kinematic']['fde']:.2f} "
                f"({p['best_kinematic']['choice']}) | {p['seconds']:.0f} |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--shared", type=Path, default=REPO.parent / "shared" / "data")
    ap.add_argument("--work", type=Path, default=REPO / "out" / "driving_lolo")
    ap.add_argument("--locations", nargs="*", default=list(LOCATIONS))
    ap.add_argument("--out", type=Path, default=REPO / "docs" / "results" / "fleet_curve.json")
    args = ap.parse_args(argv)
    config = load_residual_config(CONFIG)
    real = targets(args, config)
    datasets = {name: Dataset.open(args.work / "data" / name) for name in ("av1", "av2", "ngsim")}
    results = {"locations": {loc: location_curve(real, datasets, loc, args.work) for loc in args.locations}}
    args.out.write_text(json.dumps(results, indent=1) + "\n")
    args.out.with_suffix(".md").write_text(markdown(results))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
