"""Leave-one-location-out evaluation of the residual driving model (issue 57, item 5; honest baselines, issue 62).

For each of the six real locations (``scripts.driving_targets.LOCATIONS``): train on the other five (their
training clusters; ``VAL_SHARE`` of each location's recording clusters validate, choosing the epoch), then test on
the held-out location. The full model and the same without the environment net (EN) are trained alike. Beside
them, on the same targets, every kinematic baseline with its settings chosen on the training locations
(``model.kinematic.best_baseline``: CV, least-squares CV, Kalman and the adaptive prior, whose constants are chosen
here too; the model's own prior keeps the constants frozen since issue 57) and the best of them (chosen there);
the CV sampler with plain CV as mode 0 and its noise chosen there by minFDE@6 on a grid with room on both sides
(``model.residual.compare``); and the model as ``logpipe predict`` runs it by default (``auto``): on a road it never
trained on, mode 0 is the best kinematic baseline of its own training targets and its modes follow. K = 1 (mode
0) and K = 6 per agent (minFDE@6); 95 % bootstrap intervals over recording clusters, resampled within each
location::

    python -m scripts.driving_lolo [--locations AV2 ...] [--epochs N]

Writes ``docs/results/driving_lolo.json`` (then ``python -m scripts.driving_report``); the fold checkpoints stay in
``out/driving_lolo/`` (not shipped), and a fold whose training finished (its ``cost.json``) is reused by the next
run, so an interrupted run resumes and a rerun only evaluates.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from logpipe.model.kinematic import best_baseline
from logpipe.model.kinematic.adaptive_prior import adaptive_fit
from logpipe.model.residual.checkpoint import load_residual
from logpipe.model.residual.compare import cv_sampler, tune_sampler
from logpipe.model.residual.config import ResidualConfig, load_residual_config
from logpipe.model.residual.fit import fit_residual, ranked_forecasts
from logpipe.model.residual.inputs import concat
from logpipe.model.residual.modes import model_modes
from logpipe.model.residual.ood import fallback_forecasts, tune_baselines
from logpipe.types import NDArrayFloat
from scripts.driving_targets import (
    LOCATIONS,
    Targets,
    build_datasets,
    config_key,
    load_targets,
    real_targets,
    save_targets,
)
from scripts.locations import REPO

K = 6
CONFIG = REPO / "configs" / "driving_residual.toml"
BOOTSTRAP = 2000


def errors(forecasts: NDArrayFloat, future: NDArrayFloat) -> dict[str, NDArrayFloat]:
    """Per target: K = 1 ADE/FDE (mode 0) and per-agent minADE/minFDE over the modes, metres."""
    dist = np.linalg.norm(forecasts - future[:, None], axis=-1)  # (N, K, T)
    return {"ade": dist[:, 0].mean(axis=1), "fde": dist[:, 0, -1], "min_ade": dist.mean(axis=2).min(axis=1),
            "min_fde": dist[:, :, -1].min(axis=1)}


def kinematic_rows(targets: Targets, held: str, pred_len: int) -> tuple[dict[str, NDArrayFloat], dict[str, Any]]:
    """Per baseline (N, K, T, 2) forecasts of every target (settings chosen on the locations other than ``held``)
    and the choices."""
    train_locs = np.flatnonzero(targets.location != held)
    observed = targets.inputs.observed
    per_method = best_baseline.choose_per_method(observed[train_locs], targets.future[train_locs])
    best = best_baseline.choose(per_method)
    out = {name: best_baseline.forecast(record, observed, pred_len)[:, None] for name, record in per_method.items()}
    out["best_kinematic"] = best_baseline.forecast(best, observed, pred_len)[:, None]
    out["model_prior"] = adaptive_fit(observed).forecast(pred_len)[:, None]
    sampler = tune_sampler(targets.inputs.take(train_locs))
    out["cv_sampler"] = cv_sampler(observed, pred_len, K, sampler["heading_std_rad"], sampler["speed_std_frac"], 0)
    return out, {"baselines": per_method, "best_kinematic": best, "cv_sampler": sampler}


def as_shipped(targets: Targets, held: str, ranked: NDArrayFloat, rows: np.ndarray
               ) -> tuple[NDArrayFloat, dict[str, Any]]:
    """``logpipe predict``'s default (``auto``) on ``rows``, a road the model never trained on, given its ranked
    forecasts of them (``fit.ranked_forecasts``): mode 0 the best kinematic baseline of the fold model's own
    training targets (as ``fit_residual`` records it), then its mode heads around it."""
    train_rows = np.flatnonzero((targets.location != held) & ~targets.validation())
    ood = tune_baselines(targets.inputs.take(train_rows))
    return fallback_forecasts(ood, targets.inputs.observed[rows], ranked, K), ood["fallback_k1"]


def train_variant(config: ResidualConfig, real: Targets, synthetic: Targets | None, held: str, out: Path,
                  mixed: bool = False) -> tuple[Path, dict[str, Any]]:
    """One fold's model: trained on the other locations' training clusters, validated on their validation
    clusters; with ``synthetic`` traffic (of locations other than ``held``), pre-trained on it first, or with
    ``mixed`` trained on both at once. Returns the best checkpoint and its cost."""
    val = real.validation()
    train_rows = np.flatnonzero((real.location != held) & ~val)
    val_rows = np.flatnonzero((real.location != held) & val)
    started = time.perf_counter()
    init = None
    cost: dict[str, Any] = {}
    train, windows = real.inputs.take(train_rows), real.window[train_rows]
    if synthetic is not None:
        keep = np.flatnonzero(synthetic.location != held)
        cost["pretrain_targets" if not mixed else "mixed_targets"] = len(keep)
        if mixed:
            train = concat([train, synthetic.inputs.take(keep)])
            windows = np.concatenate([windows, synthetic.window[keep]])
        else:
            pre = fit_residual(synthetic.inputs.take(keep), synthetic.window[keep], real.inputs.take(val_rows),
                               config, out / "pretrain", dataset_kind="synthetic", manifest_hash="")
            init = pre.best_checkpoint
    fine = fit_residual(train, windows, real.inputs.take(val_rows), config, out / "real", dataset_kind="real",
                        manifest_hash="", init_from=init)
    seconds = time.perf_counter() - started
    cost |= {"seconds": round(seconds, 1), "core_hours": round(seconds * config.num_threads / 3600, 3),
             "best_epoch": fine.best_epoch, "train_targets": len(train_rows), "val_targets": len(val_rows)}
    return fine.best_checkpoint, cost


def fold_model(config: ResidualConfig, real: Targets, held: str, out: Path) -> tuple[Path, dict[str, Any]]:
    """A fold's best checkpoint and training cost: the finished one in ``out`` (its ``cost.json`` is written only
    after training ended, so an interrupted fold trains again), else trained now."""
    done = out / "cost.json"
    if done.is_file():
        return out / "real" / "best", dict(json.loads(done.read_text()))
    best, cost = train_variant(config, real, None, held, out)
    done.write_text(json.dumps(cost) + "\n")
    return best, cost


def bootstrap(values: dict[str, NDArrayFloat], location: np.ndarray, cluster: np.ndarray, rows: np.ndarray,
              seed: int = 0) -> dict[str, list[float]]:
    """95 % intervals of each value's mean over ``rows``, resampling clusters within each location."""
    rng = np.random.default_rng(seed)
    groups = [[rows[cluster[rows] == c] for c in np.unique(cluster[rows[location[rows] == loc]])]
              for loc in np.unique(location[rows])]
    means: dict[str, list[float]] = {k: [] for k in values}
    for _ in range(BOOTSTRAP):
        picked = np.concatenate([g[i] for gs in groups for i in rng.integers(0, len(gs), len(gs)) for g in [gs]])
        for k, v in values.items():
            means[k].append(float(v[picked].mean()))
    return {k: [float(np.percentile(m, 2.5)), float(np.percentile(m, 97.5))] for k, m in means.items()}


def targets(args: argparse.Namespace, config: ResidualConfig) -> Targets:
    """The real targets (with crops), cached in ``--work`` by the input settings."""
    cache = args.work / f"targets-{config_key(config)}.npz"
    if cache.is_file():
        return load_targets(cache)[0]
    real = real_targets(build_datasets(args.shared, args.work / "data"), replace(config, environment=True))
    save_targets(real, {}, cache)
    return real


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--shared", type=Path, default=REPO.parent / "shared" / "data")
    ap.add_argument("--work", type=Path, default=REPO / "out" / "driving_lolo")
    ap.add_argument("--config", type=Path, default=CONFIG)
    ap.add_argument("--locations", nargs="*", default=list(LOCATIONS))
    ap.add_argument("--epochs", type=int, default=None)
    ap.add_argument("--out", type=Path, default=REPO / "docs" / "results" / "driving_lolo.json")
    args = ap.parse_args(argv)
    started = time.perf_counter()
    config = load_residual_config(args.config, {"epochs": args.epochs} if args.epochs else None)
    real = targets(args, config)
    print(f"{len(real.inputs)} real targets", file=sys.stderr)
    results: dict[str, Any] = {"config": config.to_dict(), "folds": {}, "targets": len(real.inputs)}
    per_target: dict[str, NDArrayFloat] = {}

    def record(label: str, forecasts: NDArrayFloat, rows: np.ndarray) -> None:
        for key, v in errors(forecasts, real.future[rows]).items():
            per_target.setdefault(f"{label}.{key}", np.full(len(real.inputs), np.nan))[rows] = v

    for held in args.locations:
        test = np.flatnonzero(real.location == held)
        fold: dict[str, Any] = {"targets": len(test), "turning": int(real.turning[test].sum())}
        kinematic, fold["chosen_on_training_locations"] = kinematic_rows(real, held, config.pred_len)
        for label, forecasts in kinematic.items():
            record(label, forecasts[test], test)
        for variant, en in (("full", True), ("no_en", False)):
            cfg = replace(config, environment=en)
            inputs = real if en else replace(real, inputs=replace(real.inputs, crops=None))
            best, cost = fold_model(cfg, inputs, held, args.work / held / variant)
            net, _ = load_residual(best)
            ranked = ranked_forecasts(net, inputs.inputs.take(test))
            record(variant, model_modes(ranked, K), test)
            shipped, fallback = as_shipped(real, held, ranked, test)
            record(f"{variant}_auto", shipped, test)
            fold[variant] = cost | {"fallback_k1": fallback}
            print(held, variant, cost, file=sys.stderr)
        results["folds"][held] = fold
    # Millimetres: the bootstrap needs every target's error, not its float64 noise (a third of the bytes).
    results["per_target"] = {k: np.round(v, 3).tolist() for k, v in per_target.items()}
    results["location"] = real.location.tolist()
    results["cluster"] = real.cluster.tolist()
    results["turning"] = real.turning.tolist()
    results["seconds"] = round(time.perf_counter() - started, 1)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(results) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
