"""Leave-one-location-out evaluation of the residual driving model (issue 57, item 5).

For each of the six real locations (``scripts.driving_targets.LOCATIONS``): train on the other five (their
training clusters; ``VAL_SHARE`` of each location's recording clusters validate, choosing the epoch), optionally
pre-trained first on SYNTHETIC traffic of the other five locations' maps, then test on the held-out location. The
full model and the same without the environment net (EN) are trained alike. Beside them, on the same targets:
constant velocity (the last displacement), constant velocity fitted by least squares over the last n steps and a
constant-velocity Kalman filter (n and the filter's noise chosen on the training locations), the CV sampler (its
noise chosen on the training locations by minFDE@6) and the adaptive prior alone. K = 1 (mode 0: the mean head)
and K = 6 per agent (minFDE@6 over mode 0 and the 5 best-scored heads); 95 % bootstrap intervals over recording
clusters, resampled within each location::

    python -m scripts.driving_lolo [--synthetic DS ...] [--locations AV2 ...] [--epochs N]

Writes ``docs/results/driving_lolo.json`` and ``.md``; the fold checkpoints stay in ``out/driving_lolo/`` (not
shipped), and a fold whose training finished (its ``cost.json``) is reused by the next run, so an interrupted run
resumes and a rerun only evaluates.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from logpipe.model.kinematic.adaptive_prior import AdaptiveConstantVelocity
from logpipe.model.kinematic.constant_velocity import ConstantVelocity, ConstantVelocitySampler, LinearFit
from logpipe.model.kinematic.kalman import KalmanCV
from logpipe.model.residual.checkpoint import load_residual
from logpipe.model.residual.config import ResidualConfig, load_residual_config
from logpipe.model.residual.fit import fit_residual, forecast
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
LS_WINDOWS = (2, 3, 4, 5, 6, 8, 10, 12, 15)
KALMAN_GRID = tuple((q, r) for q in (0.003, 0.01, 0.03, 0.1, 0.3) for r in (0.01, 0.03, 0.1, 0.3, 1.0))
SAMPLER_GRID = tuple((h, s) for h in (0.02, 0.05, 0.1, 0.2, 0.3) for s in (0.05, 0.1, 0.2, 0.3, 0.5))
BOOTSTRAP = 2000


def _stack(forecasts: Sequence[NDArrayFloat]) -> NDArrayFloat:
    return np.concatenate(list(forecasts))


def classical_forecasts(targets: Targets, pred_len: int) -> dict[str, NDArrayFloat]:
    """Every classical candidate's (N, K, T, 2) forecasts of the targets (grids included; chosen per fold)."""
    samples = targets.samples
    out = {"cv": _stack(ConstantVelocity(pred_len=pred_len).predict(samples, 1, 0)),
           "adaptive_cv": _stack(AdaptiveConstantVelocity(pred_len=pred_len).predict(samples, 1, 0))}
    for n in LS_WINDOWS:
        out[f"ls:{n}"] = _stack(LinearFit(pred_len=pred_len, history=n).predict(samples, 1, 0))
    for q, r in KALMAN_GRID:
        out[f"kalman:{q}:{r}"] = _stack(KalmanCV(pred_len=pred_len, accel_std=q, meas_std=r).predict(samples, 1, 0))
    for h, s in SAMPLER_GRID:
        out[f"sampler:{h}:{s}"] = _stack(ConstantVelocitySampler(pred_len=pred_len, heading_std_rad=h,
                                                                 speed_std_frac=s).predict(samples, K, 0))
    return out


def errors(forecasts: NDArrayFloat, future: NDArrayFloat) -> dict[str, NDArrayFloat]:
    """Per target: K = 1 ADE/FDE (mode 0) and per-agent minADE/minFDE over the modes, metres."""
    dist = np.linalg.norm(forecasts - future[:, None], axis=-1)  # (N, K, T)
    return {"ade": dist[:, 0].mean(axis=1), "fde": dist[:, 0, -1], "min_ade": dist.mean(axis=2).min(axis=1),
            "min_fde": dist[:, :, -1].min(axis=1)}


def choose(candidates: dict[str, dict[str, NDArrayFloat]], prefix: str, rows: np.ndarray, key: str) -> str:
    """The candidate of a family with the lowest mean ``key`` error over ``rows`` (the training locations)."""
    family = [name for name in candidates if name.startswith(prefix)]
    return min(family, key=lambda name: float(candidates[name][key][rows].mean()))


def train_variant(config: ResidualConfig, real: Targets, synthetic: Targets | None, held: str, out: Path,
                  ) -> tuple[Path, dict[str, Any]]:
    """One fold's model: pre-trained on synthetic traffic of the other locations (when given), then trained on the
    other locations' training clusters, validated on their validation clusters. Returns the best checkpoint and
    its cost."""
    val = real.validation()
    train_rows = np.flatnonzero((real.location != held) & ~val)
    val_rows = np.flatnonzero((real.location != held) & val)
    started = time.perf_counter()
    init = None
    cost: dict[str, Any] = {}
    if synthetic is not None:
        keep = np.flatnonzero(synthetic.location != held)
        pre = fit_residual(synthetic.inputs.take(keep), synthetic.window[keep], real.inputs.take(val_rows),
                           replace(config, epochs=config.epochs), out / "pretrain", dataset_kind="synthetic",
                           manifest_hash="")
        init = pre.best_checkpoint
        cost["pretrain_targets"] = len(keep)
    fine = fit_residual(real.inputs.take(train_rows), real.window[train_rows], real.inputs.take(val_rows), config,
                        out / "real", dataset_kind="real", manifest_hash="", init_from=init)
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


def targets_and_baselines(args: argparse.Namespace, config: ResidualConfig
                          ) -> tuple[Targets, dict[str, dict[str, NDArrayFloat]]]:
    """The real targets (with crops) and every classical candidate's errors on them, cached in ``--work``
    by the input settings (the data and the baselines do not change between runs)."""
    cache = args.work / f"targets-{config_key(config)}.npz"
    if cache.is_file():
        real, extra = load_targets(cache)
    else:
        datasets = build_datasets(args.shared, args.work / "data")
        real = real_targets(datasets, replace(config, environment=True))
        extra = {f"{name}|{key}": v for name, f in classical_forecasts(real, config.pred_len).items()
                 for key, v in errors(f, real.future).items()}
        save_targets(real, extra, cache)
    classical: dict[str, dict[str, NDArrayFloat]] = {}
    for key, values in extra.items():
        name, metric = key.split("|")
        classical.setdefault(name, {})[metric] = values
    return real, classical


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
    real, classical = targets_and_baselines(args, config)
    print(f"{len(real.inputs)} real targets", file=sys.stderr)
    results: dict[str, Any] = {"config": config.to_dict(), "folds": {}, "targets": len(real.inputs)}
    per_target: dict[str, NDArrayFloat] = {}
    for held in args.locations:
        test = np.flatnonzero(real.location == held)
        train_locs = np.flatnonzero(real.location != held)
        fold: dict[str, Any] = {"targets": len(test), "turning": int(real.turning[test].sum())}
        chosen = {"ls": choose(classical, "ls:", train_locs, "fde"), "kalman": choose(classical, "kalman:", train_locs,
                  "fde"), "sampler": choose(classical, "sampler:", train_locs, "min_fde")}
        fold["chosen_on_training_locations"] = chosen
        for label, name in (("cv", "cv"), ("adaptive_cv", "adaptive_cv"), ("ls_cv", chosen["ls"]),
                            ("kalman", chosen["kalman"]), ("cv_sampler", chosen["sampler"])):
            for key, v in classical[name].items():
                per_target.setdefault(f"{label}.{key}", np.full(len(real.inputs), np.nan))[test] = v[test]
        for variant, en in (("full", True), ("no_en", False)):
            cfg = replace(config, environment=en)
            inputs = real if en else replace(real, inputs=replace(real.inputs, crops=None))
            best, cost = fold_model(cfg, inputs, held, args.work / held / variant)
            net, _ = load_residual(best)
            world = forecast(net, inputs.inputs.take(test), K)
            for key, v in errors(world, real.future[test]).items():
                per_target.setdefault(f"{variant}.{key}", np.full(len(real.inputs), np.nan))[test] = v
            fold[variant] = cost
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
