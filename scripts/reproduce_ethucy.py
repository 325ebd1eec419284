"""Reproduce the paper's Table 1 (ETH/UCY leave-one-scene-out) with logpipe's stages.

For each scene S of eth, hotel, univ, zara1, zara2: the dataset (``logpipe ingest`` of the Social-GAN folder
layout) gives ``S/train``, ``S/val`` and ``S/test`` by log membership. The non-learned methods are run on
``S/test``: constant velocity (K=1), the paper's Linear and KF rows (K=1), and a constant-velocity sampler
(K=20) whose heading/speed noise is chosen on ``S/val`` (never on test). Learned methods (the paper's
network, LSTM, Noise-LSTM) are run when their checkpoint folder exists and listed as skipped otherwise.
Everything is scored with ``logpipe.stages.score`` under two explicit protocols (Social-GAN's literal
loader, windows with >= 2 pedestrians; and every window with >= 1), and ``docs/results/ethucy.md`` gets the
table with the paper's numbers beside it.

Usage::

    python -m scripts.reproduce_ethucy [--data ../shared/data/ethucy] [--work out/reproduce/ethucy]
        [--results docs/results] [--checkpoint zhu2020=model/checkpoints/ethucy/{scene}] ...
        [--seeds-dir out/checkpoints]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from logpipe.dataset.reader import Dataset
from logpipe.stages.score import score
from logpipe.stages.train import scene_samples
from scripts.ethucy_checks import (
    MOTION_METHODS,
    motion_breakdown,
    paired_differences,
    rate_shifted_dataset,
    val_forecasts,
)
from scripts.ethucy_report import ABLATION, SCENES, render
from scripts.forecasts import read_forecasts, write_classical, write_learned
from scripts.locations import REPO, SEEDS_DIR, checkpoint_paths, ensure_dataset, find_checkpoint
from scripts.seeds import seed_run, stale_seeds, training_seeds
from scripts.tables import AS_TRAINED, PAPER
from scripts.validation import (
    K_BEST,
    chosen_on,
    chosen_sampler,
    grid_row,
    predicted_best_of_k,
    shifted_best_of_k,
    tune_sampler,
)

LEARNED = {  # method -> (default checkpoint template, K): the lead trains these with `logpipe train`
    PAPER: ("model/checkpoints/ethucy/{scene}/paper", K_BEST),
    "zhu2020": ("model/checkpoints/ethucy/{scene}", K_BEST),
    "noise_lstm": ("model/checkpoints/ethucy/{scene}/noise_lstm", K_BEST),
    "lstm": ("model/checkpoints/ethucy/{scene}/lstm", 1),
    ABLATION: ("model/checkpoints/ethucy/{scene}/no_position", K_BEST),
}


def validation_summary(results: dict[str, Any], scene: str) -> dict[str, Any]:
    """What was measured on ``scene/val``: per K=20 method its chosen setting, best-of-20 ADE/FDE there and on the
    speed- and frame-rate-shifted val (the inference-settings grid of the learned methods too)."""
    smp = results["sampler"][scene]
    c = smp["choice"]
    at = next(g for g in smp["grid"] if g[0] == c["heading_std_rad"] and g[1] == c["speed_std_frac"])
    out: dict[str, Any] = {"cv_sampler": {"ade_fde": list(at[2:]), "speed_shift_ade_fde": list(smp["speed_shift_val"]),
                                          "rate_shift_ade_fde": list(smp["rate_shift_val"])}}
    for method, n in results["noise"].get(scene, {}).items():
        chosen = grid_row(n["grid"], n["constant_velocity_modes"], n["noise_scale"])
        out[method] = {"noise_scale": n["noise_scale"], "constant_velocity_modes": n["constant_velocity_modes"],
                       "trained_constant_velocity_modes": n["trained_constant_velocity_modes"],
                       "context_max_neighbours": n.get("context_max_neighbours"),
                       "ade_fde": list(chosen[2:]), "speed_shift_ade_fde": list(n["speed_shift_val"]),
                       "rate_shift_ade_fde": list(n["rate_shift_val"]), "inference_grid": n["grid"]}
    return out


def main(argv: Sequence[str] | None = None) -> int:
    """Run the ETH/UCY reproduction; returns the process exit code."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--data", type=Path, default=REPO.parent / "shared" / "data" / "ethucy")
    ap.add_argument("--work", type=Path, default=REPO / "out" / "reproduce" / "ethucy")
    ap.add_argument("--results", type=Path, default=REPO / "docs" / "results")
    ap.add_argument("--checkpoint", action="append", default=[], metavar="METHOD=TEMPLATE",
                    help="checkpoint folder per method, {scene} is replaced (defaults: "
                         + ", ".join(f"{m}={t}" for m, (t, _) in LEARNED.items()) + ")")
    ap.add_argument("--scenes", nargs="+", default=list(SCENES), choices=SCENES)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--seeds-dir", type=Path, default=SEEDS_DIR,
                    help="the extra training seeds' checkpoints, seedN/ethucy/... (`make train-ethucy SEED=N`), for "
                         "the across-seeds table (default: out/checkpoints)")
    ap.add_argument("--no-store-settings", dest="store_settings", action="store_false",
                    help="do not record the inference settings chosen on validation in the checkpoints' meta.json "
                         "(where they become `logpipe predict`'s defaults)")
    args = ap.parse_args(argv)
    t0 = time.perf_counter()
    templates = checkpoint_paths(ap, args.checkpoint, {m: t for m, (t, _) in LEARNED.items()})
    ds = ensure_dataset(args.data, args.work / "dataset", "ethucy")
    rate_ds = rate_shifted_dataset(args.data, args.work / "rate_shift")
    results: dict[str, Any] = {"scenes": {}, "skipped": [], "sampler": {}, "noise": {}, "val": {}, "seeds": {},
                               "motion": {}, "paired": {}, "stale_seeds": stale_seeds(ds.kind, args.seeds_dir)}
    for scene in args.scenes:
        ts = time.perf_counter()
        run_scene(scene, ds, rate_ds, templates, args, results)
        print(f"{scene}: {time.perf_counter() - ts:.1f} s", file=sys.stderr)
    seconds = time.perf_counter() - t0
    args.results.mkdir(parents=True, exist_ok=True)
    summary = {s: {p: {m: e["overall"] for m, e in r[p]["methods"].items()} for p in ("min2", "min1")}
               | {"sampler": results["sampler"][s]["choice"], "seconds": r["seconds"], "val": results["val"][s],
                  "seeds": {str(n): v for n, v in results["seeds"][s].items()}, "motion": results["motion"][s],
                  "paired": results["paired"][s]}
               for s, r in results["scenes"].items()}
    stale = {str(n): v for n, v in results["stale_seeds"].items()}
    (args.results / "ethucy.json").write_text(json.dumps({"scenes": summary, "skipped": results["skipped"],
                                                          "stale_seeds": stale, "seconds": round(seconds, 1)},
                                                         indent=1, sort_keys=True))
    out_md = args.results / "ethucy.md"
    out_md.write_text(render(results, args, seconds))
    print(f"wrote {out_md} in {seconds:.1f} s", file=sys.stderr)
    return 0


def run_scene(scene: str, ds: Dataset, rate_ds: Dataset, templates: dict[str, str], args: argparse.Namespace,
              results: dict[str, Any]) -> None:
    """One leave-one-out fold: tune on ``scene/val``, predict and score ``scene/test`` (both window protocols), the
    checks, diagnoses and extra seeds; everything lands in ``results`` under ``scene``."""
    ts = time.perf_counter()
    pred_len = ds.protocol.pred_len
    detail = args.results / "ethucy"
    val = scene_samples(ds, f"{scene}/val")
    test = scene_samples(ds, f"{scene}/test")
    train = scene_samples(ds, f"{scene}/train")  # for the neighbour cap only
    choice, grid = tune_sampler(val, pred_len, K_BEST, args.seed)
    rate_val = scene_samples(rate_ds, f"{scene}/val")
    sampler = chosen_sampler(choice, pred_len)
    results["sampler"][scene] = {"choice": choice, "val_agents": int(sum(s.target_mask.sum() for s in val)),
                                 "grid": grid,
                                 "speed_shift_val": shifted_best_of_k(sampler, val, pred_len, K_BEST, args.seed),
                                 "rate_shift_val": predicted_best_of_k(sampler, rate_val, pred_len, K_BEST,
                                                                       args.seed),
                                 "rate_shift_agents": int(sum(s.target_mask.sum() for s in rate_val))}
    pdir = args.work / "predictions" / scene
    sampler_id = (f"cv_sampler heading_std_rad={choice['heading_std_rad']} "
                  f"speed_std_frac={choice['speed_std_frac']} (chosen on {scene}/val)")
    files = write_classical(test, pred_len, args.seed, choice, K_BEST, sampler_id, pdir)
    for method, (_, k) in LEARNED.items():
        ckpt = find_checkpoint(templates[method], scene)
        if ckpt is None:
            results["skipped"].append({"scene": scene, "method": method,
                                       "reason": f"no checkpoint at {templates[method].format(scene=scene)}"})
            continue
        written, noise = write_learned(ckpt, ds.kind, val, test, k, args.seed, pred_len, pdir, method,
                                       AS_TRAINED if method == "zhu2020" else None, speed_shift=True,
                                       rate_val=rate_val, train=train, as_specified=method == PAPER,
                                       store_as=chosen_on(f"{scene}/val", k, args.seed, "make reproduce-ethucy",
                                                         f"{scene}/train")
                                       if args.store_settings and method != PAPER else None)
        files += written
        if noise is not None:
            results["noise"].setdefault(scene, {})[method] = noise
    results["val"][scene] = validation_summary(results, scene)
    literal = score(files, ds.root, detail / scene, split=f"{scene}/test", min_agents=2, plots=True,
                    title=f"ETH/UCY {scene} (leave-one-out test), Social-GAN literal windows (>= 2 peds)")
    test_forecasts = read_forecasts(files, test, MOTION_METHODS)
    results["motion"][scene] = {
        "val": motion_breakdown(val, val_forecasts(sampler, templates, results["noise"].get(scene, {}), scene,
                                                   ds.kind, val, args.seed), pred_len, 2),
        "test": motion_breakdown(test, test_forecasts, pred_len, 2)}
    results["paired"][scene] = paired_differences(test, test_forecasts, pred_len, 2)
    every = score(files, ds.root, detail / scene / "min1", split=f"{scene}/test", min_agents=1, plots=False,
                  title=f"ETH/UCY {scene} (leave-one-out test), every window (>= 1 ped)")
    results["seeds"][scene] = {seed: seed_run(seed, templates, LEARNED, scene, ds, val, test, f"{scene}/test", 2,
                                              args.work / "seeds" / f"seed{seed}" / scene, train, args.seeds_dir)
                               for seed in training_seeds(ds.kind, args.seeds_dir)}
    results["scenes"][scene] = {"min2": literal, "min1": every, "seconds": round(time.perf_counter() - ts, 2)}


if __name__ == "__main__":
    sys.exit(main())
