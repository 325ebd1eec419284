"""The driving model on the real logs we hold: the full method and the Table 4 variants (v1-v4), several seeds.

Data: the 69 Argoverse 1 sequences (every vehicle observed for all 50 frames but the AV is a target; the AV's past
is the EMF input, its future the ETF input) and the AV2 sensor logs and scenario cut into sliding windows of the
same 20 + 30 steps (stride 10), each with ego-centred, heading-rotated 224 x 224 lane rasters over 100 m from its
real map. Split by log with each dataset's id hash: trained on ``hash/train``, early-stopped on ``hash/val``,
scored on ``hash/test``, which nothing is tuned on (the CV sampler's two noise parameters are chosen on
``hash/train``). A pipeline check on a few hundred windows, not a reproduction of the paper's Table 3 or 4::

    python -m scripts.reproduce_driving [--seeds 0 1 2] [--no-train]

Trainings are resumable (``logpipe train --resume``): a run stopped half-way continues where it stopped. Writes
``docs/results/argoverse_logs.json`` and ``.md``; ``scripts.reproduce_argoverse`` shows the table in ``argoverse.md``.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from logpipe.api import ingest, rasterise, train
from logpipe.dataset.reader import Dataset
from logpipe.errors import DatasetError
from logpipe.model.kinematic.constant_velocity import ConstantVelocity
from logpipe.model.kinematic.kalman import KalmanCV
from logpipe.model.predictor import Predictor
from logpipe.model.zhu2020.predictor import NetPredictor
from logpipe.raster.runs import find_raster_run
from logpipe.scoring import metrics
from logpipe.stages.train import scene_samples
from logpipe.types import NDArrayFloat, SceneSample
from scripts.locations import REPO
from scripts.tables import machine_note
from scripts.validation import chosen_sampler, truth_of, tune_sampler

K = 6
VARIANTS = ("full", "v4", "v3", "v2", "v1", "baseline")
CONFIG = REPO / "configs" / "argoverse_logs.toml"
T_95 = {2: 12.706, 3: 4.303, 4: 3.182, 5: 2.776}  # two-sided 95 % Student t quantiles by sample count
PAPER_TABLE4 = {"baseline": "1.48/3.17", "v1": "1.32/2.70", "v2": "1.24/2.56", "v3": "1.22/2.51",
                "v4": "1.19/2.47", "full": "1.18/2.45"}  # Zhu et al. Table 4, Argoverse val, K unstated
LABELS = {"full": "The paper's method, full (PF+TF+EMF+ETF+EF)", "v4": "v4 (PF+TF+EMF+ETF, no EN)",
          "v3": "v3 (PF+TF+EMF)", "v2": "v2 (PF+TF)", "v1": "v1 (PF)",
          "baseline": "Noise-LSTM (Table 4's Baseline: no AIN feature, no EN)"}


def build_datasets(av1: Path, av2: Path, av1_maps: Path, work: Path) -> list[Dataset]:
    """Ingest and rasterise both sources (both steps skip finished work)."""
    ingest([av1], out=work / "av1", protocol="argoverse", targets="fully_observed_no_ego", mcap=False, workers=1)
    ingest([av2], out=work / "av2", protocol="argoverse2", obs=20, pred=30, window="sliding", stride=10,
           targets="fully_observed_no_ego", target_types="vehicle,bus_truck", mcap=False, workers=1)
    for name, maps in (("av1", av1_maps), ("av2", av2)):
        rasterise(work / name, maps=[maps], rotate=True, workers=1)
    return [Dataset.open(work / "av1"), Dataset.open(work / "av2")]


def split_samples(datasets: Sequence[Dataset], split: str) -> list[SceneSample]:
    """The samples of ``split`` in every dataset that has logs in it, with their rasters."""
    out: list[SceneSample] = []
    for ds in datasets:
        rasters = find_raster_run(ds.root, None, None)
        try:
            out += scene_samples(ds, split, rasters=rasters)
        except DatasetError:  # no log in the split: a hash split of AV2's five logs can be empty (hash/val is)
            continue
    return out


def train_runs(datasets: Sequence[Dataset], runs: Path, seeds: Sequence[int]) -> None:
    """Train (or resume) every variant and seed that has no summary yet."""
    for seed in seeds:
        for variant in VARIANTS:
            run = runs / variant / f"seed{seed}"
            summary = run.with_suffix(".json")
            if not summary.exists():
                result = train([ds.root for ds in datasets], out=run, train_split="hash/train", val_split="hash/val",
                               config=CONFIG, preset=variant, seed=seed, resume=(run / "last" / "meta.json").exists())
                tmp = summary.with_suffix(".json.tmp")
                tmp.write_text(json.dumps(result, indent=1, sort_keys=True))
                tmp.replace(summary)


def run_minutes(runs: Path, seeds: Sequence[int]) -> dict[str, float]:
    """Training minutes of each finished run (all its sessions, when it was resumed)."""
    minutes: dict[str, float] = {}
    for seed in seeds:
        for variant in VARIANTS:
            summary = runs / variant / f"seed{seed}.json"
            if summary.exists():
                done = json.loads(summary.read_text())
                minutes[f"{variant}/seed{seed}"] = done.get("seconds_total", done.get("seconds", math.nan)) / 60
    return minutes


def scores(pred: NDArrayFloat, truth: NDArrayFloat, window: np.ndarray) -> dict[str, Any]:
    """K = 1 and K = 6 scores of (N, K, T, 2) forecasts: per agent, joint per window, Argoverse; per-agent arrays
    of the K = 6 per-agent minADE / minFDE kept for intervals."""
    err = metrics.displacement_errors(pred, truth)
    out: dict[str, Any] = {}
    for k in (1, K):
        e = metrics.top_k(err, k)
        agent, joint, argo = (metrics.best_of_k_per_agent(e), metrics.best_of_k_joint(e, window),
                              metrics.argoverse(e))
        out[f"k{k}"] = {"ade": float(agent.ade.mean()), "fde": float(agent.fde.mean()),
                        "ade_joint": float(joint.ade.mean()), "fde_joint": float(joint.fde.mean()),
                        "argo_ade": float(argo.ade.mean()), "argo_fde": float(argo.fde.mean()),
                        "miss_rate": float(metrics.miss(argo.fde).mean())}
        if k == K:
            out["agent_ade"], out["agent_fde"] = agent.ade, agent.fde
    return out


def forecast(predictor: Predictor, samples: Sequence[SceneSample], k: int, seed: int, ok: np.ndarray) -> NDArrayFloat:
    """(N, K, T, 2) forecasts of the scored targets (deterministic methods repeated to K)."""
    pred = np.concatenate(predictor.predict(samples, k, seed))[ok]
    return np.repeat(pred, K, axis=1) if pred.shape[1] == 1 else pred


def interval(values: Sequence[float]) -> tuple[float, float]:
    """Mean and the half-width of its 95 % Student t interval over training seeds (NaN for one seed)."""
    v = np.asarray(values, dtype=np.float64)
    if len(v) < 2:
        return float(v.mean()), math.nan
    return float(v.mean()), float(T_95.get(len(v), 1.96) * v.std(ddof=1) / math.sqrt(len(v)))


def window_interval(per_agent: NDArrayFloat, window: np.ndarray) -> tuple[float, float]:
    """95 % percentile bootstrap of the mean over whole test windows (test sampling only)."""
    d = metrics.paired_difference_interval(per_agent, window)
    return d.low, d.high


def main(argv: Sequence[str] | None = None) -> int:
    """Train what is missing, score every run on hash/test and write the results files; returns the exit code."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    shared = REPO.parent / "shared" / "data"
    ap.add_argument("--av1", type=Path, default=shared / "argoverse1" / "data")
    ap.add_argument("--av1-maps", type=Path, default=shared / "argoverse1" / "maps")
    ap.add_argument("--av2", type=Path, default=shared / "av2")
    ap.add_argument("--work", type=Path, default=REPO / "out" / "driving")
    ap.add_argument("--runs", type=Path, default=REPO / "out" / "runs" / "driving")
    ap.add_argument("--results", type=Path, default=REPO / "docs" / "results")
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    ap.add_argument("--no-train", dest="train", action="store_false", help="score finished runs only")
    ap.add_argument("--seed", type=int, default=0, help="noise seed of the forecasts")
    args = ap.parse_args(argv)
    t0 = time.perf_counter()
    datasets = build_datasets(args.av1, args.av2, args.av1_maps, args.work)
    if args.train:
        train_runs(datasets, args.runs, args.seeds)
    minutes = run_minutes(args.runs, args.seeds)
    test, tune = split_samples(datasets, "hash/test"), split_samples(datasets, "hash/train")
    pred_len = datasets[0].protocol.pred_len
    truth_all = truth_of(test, pred_len)
    ok = np.all(np.isfinite(truth_all), axis=(1, 2))
    truth = truth_all[ok]
    window = np.repeat(np.arange(len(test)), [int(s.target_mask.sum()) for s in test])[ok]
    sampler, _ = tune_sampler(tune, pred_len, K, args.seed)
    baselines: dict[str, Predictor] = {
        "cv": ConstantVelocity(pred_len=pred_len), "kalman": KalmanCV(pred_len=pred_len),
        "cv_sampler": chosen_sampler(sampler, pred_len)}
    methods: dict[str, Any] = {}
    for name, predictor in baselines.items():
        s = scores(forecast(predictor, test, K if name == "cv_sampler" else 1, args.seed, ok), truth, window)
        lo, hi = window_interval(s.pop("agent_fde"), window)
        s.pop("agent_ade")
        methods[name] = {"seeds": [], "k1": s["k1"], f"k{K}": s[f"k{K}"], "fde6_window_interval": [lo, hi]}
    for variant in VARIANTS:
        per_seed, fde_agents, used = [], [], []
        for seed in args.seeds:
            best = args.runs / variant / f"seed{seed}" / "best"
            if not (args.runs / variant / f"seed{seed}.json").exists():  # finished runs only
                continue
            used.append(seed)
            net = NetPredictor.from_checkpoint(best, expect_kind=datasets[0].kind)
            s = scores(forecast(net, test, K, args.seed, ok), truth, window)
            fde_agents.append(s.pop("agent_fde"))
            s.pop("agent_ade")
            per_seed.append(s)
        if not per_seed:
            continue
        entry: dict[str, Any] = {"seeds": used}
        for k in ("k1", f"k{K}"):
            entry[k] = {m: interval([s[k][m] for s in per_seed]) for m in per_seed[0][k]}
        entry["fde6_window_interval"] = list(window_interval(np.mean(fde_agents, axis=0), window))
        methods[variant] = entry
    counts = {"test_windows": len(test), "test_targets": int(ok.sum()),
              "windows": {ds.kind: {sp: len(split_samples([ds], sp)) for sp in ("hash/train", "hash/val", "hash/test")}
                          for ds in datasets}}
    seconds = time.perf_counter() - t0
    result = {"methods": methods, "counts": counts, "sampler": sampler, "k": K, "seeds": args.seeds,
              "train_minutes": minutes, "seconds": round(seconds, 1)}
    args.results.mkdir(parents=True, exist_ok=True)
    (args.results / "argoverse_logs.json").write_text(json.dumps(result, indent=1, sort_keys=True))
    (args.results / "argoverse_logs.md").write_text(render(result, seconds))
    print(f"wrote {args.results / 'argoverse_logs.md'} in {seconds:.1f} s", file=sys.stderr)
    return 0


def _cell(block: Any, a: str, f: str) -> str:
    """``ADE/FDE``, with the seed interval's half-widths when the block holds (mean, half-width) pairs."""
    if isinstance(block[a], (list, tuple)):
        (am, ah), (fm, fh) = block[a], block[f]
        return f"{am:.2f}/{fm:.2f}" + ("" if math.isnan(ah) else f" ±{ah:.2f}/{fh:.2f}")
    return f"{block[a]:.2f}/{block[f]:.2f}"


def _rate(block: Any) -> str:
    v = block["miss_rate"]
    return f"{v[0]:.2f}" if isinstance(v, (list, tuple)) else f"{v:.2f}"


def table_lines(result: dict[str, Any]) -> list[str]:
    """The results table (also shown in ``argoverse.md``)."""
    rows = [(LABELS[v], v) for v in VARIANTS] + [
        ("Baseline: constant velocity (K=1)", "cv"), ("Baseline: Kalman CV (K=1)", "kalman"),
        ("Baseline (ours): CV sampler (6 draws, noise chosen on hash/train)", "cv_sampler")]
    lines = ["| method | seeds | K=1 ADE/FDE | K=6 per agent minADE/minFDE | 95 % over test windows (minFDE@6) | "
             "K=6 joint minADE/minFDE | K=6 Argoverse minADE/minFDE | MR@6 | paper Table 4 |",
             "|---|---|---|---|---|---|---|---|---|"]
    for label, name in rows:
        m = result["methods"].get(name)
        if m is None:
            lines.append(f"| {label} | | not run | | | | | | {PAPER_TABLE4.get(name, '')} |")
            continue
        k1, k6 = m["k1"], m[f"k{K}"]
        lo, hi = m["fde6_window_interval"]
        seeds = ", ".join(map(str, m["seeds"])) or "—"
        lines.append(f"| {label} | {seeds} | {_cell(k1, 'ade', 'fde')} | {_cell(k6, 'ade', 'fde')} | "
                     f"[{lo:.2f}, {hi:.2f}] | "
                     f"{_cell(k6, 'ade_joint', 'fde_joint')} | {_cell(k6, 'argo_ade', 'argo_fde')} | {_rate(k6)} | "
                     f"{PAPER_TABLE4.get(name, '')} |")
    return lines


def render(result: dict[str, Any], seconds: float) -> str:
    """``docs/results/argoverse_logs.md``."""
    c = result["counts"]
    split_counts = "; ".join(f"{kind}: " + ", ".join(f"{n} {sp}" for sp, n in w.items())
                             for kind, w in c["windows"].items())
    lines = [
        "# The driving model on the real logs (pipeline check, not a reproduction of Table 3/4)", "",
        "Produced by `python -m scripts.reproduce_driving` (trains what is missing, resumably; config "
        "`configs/argoverse_logs.toml`). Data: the 69 Argoverse 1 sequences in `../shared/data/argoverse1/data` and "
        "the AV2 sensor logs and scenario in `../shared/data/av2/` cut into sliding windows of 20 observed + 30 "
        "predicted steps at 10 Hz (stride 10); ego-centred, heading-rotated 224 x 224 lane rasters over 100 m from "
        "each log's real map. Targets: every vehicle observed at all 50 steps but the AV, whose past is the EMF "
        "input and whose future the ETF input (as in the paper). Split by log (id hash) in each source: "
        f"{split_counts} windows. Scored on hash/test: {c['test_windows']} windows, {c['test_targets']} targets. "
        "Nothing is tuned on test.", "",
        f"Protocol: K = 1 and K = {K}, ADE/FDE in metres (mean / final Euclidean distance). Per agent: each target's "
        "best mode (the paper's Table 1 comparisons after Social-STGCNN); joint: one mode per window, the one with the "
        "lowest summed error over its targets (Social-GAN's evaluation, the rule of the Social-GAN rows the paper "
        "compares with); Argoverse: the lowest-FDE mode's ADE and FDE, miss when that FDE > 2 m. Learned rows: mean "
        "over the training seeds in the row's seeds column ± the half-width of the 95 % Student t interval over "
        "them (none shown for one seed); the bracket is a 95 % bootstrap over whole test windows of the "
        "seed-averaged per-agent minFDE@6 (test sampling only). The paper's Table 4 column is its printed Argoverse "
        "validation result (39,472 sequences, K unstated): a reference, not comparable with a few hundred windows.", "",
        *table_lines(result), "",
        "The learned rows are the paper's method as the paper specifies it (per-scene best-of-20 loss, eq. 23; plain "
        "displacement output; the ego-perspective frame of its Table 3), with a schedule cut to this data (800 steps "
        "of batch 8, learning rate halved every 200, early stopping on hash/val). The classical baselines are not in "
        "the paper's Table 4; the CV sampler is ours. With about 90 training windows a network of this size is not "
        "expected to beat constant velocity, and the rows with more inputs have more to overfit: read them as a check "
        "that the pipeline trains, predicts and scores every variant end to end, not as evidence about the method at "
        "the paper's scale.", "",
        f"CV sampler noise, chosen on hash/train: heading_std {result['sampler']['heading_std_rad']} rad, "
        f"speed_std {result['sampler']['speed_std_frac']}.", "", "## Time", "",
        machine_note(seconds) + (" Training minutes per run: " + ", ".join(
            f"{k} {v:.1f}" for k, v in sorted(result["train_minutes"].items())) + "."
            if result["train_minutes"] else ""), "",
    ]
    return "\n".join(lines)


if __name__ == "__main__":
    sys.exit(main())
