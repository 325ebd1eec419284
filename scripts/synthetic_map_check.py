"""Does the environment net read the map? The full model against the same model without EN (Table 4's v4) on
SYNTHETIC traffic simulated on the real Argoverse 1 lane graphs (``logpipe.synthetic.traffic``), scored on the
held-out region of each city that no training window touches.

    python -m scripts.synthetic_map_check --full RUN_OR_CKPT --no-en RUN_OR_CKPT --test out/syn20k_test

Protocol: 20 observed + 30 predicted steps at 10 Hz; every fully observed vehicle but the AV is a target (the AV's
past and future are the EMF and ETF inputs); K = 6, Argoverse convention (among the K modes the one with the lowest
FDE, its ADE and FDE; miss = that FDE > 2 m), per agent. The gain is 1 - minFDE(full) / minFDE(no EN) with a 95 %
percentile bootstrap over whole windows (targets of one window resample together).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from logpipe.dataset.reader import Dataset
from logpipe.raster.runs import find_raster_run
from logpipe.scoring import metrics
from logpipe.stages.train import scene_samples
from logpipe.types import NDArrayFloat, NDArrayInt, SceneSample
from scripts.locations import REPO, find_checkpoint
from scripts.tables import machine_note
from scripts.validation import truth_of

K = 6
TARGET_GAIN = 0.15
"""Issue 33's bar: the full model's minFDE@6 at least 15 % below the model without EN, on all held-out targets."""
TURN_DEG = 20.0
"""A target 'turns' when its true heading changes by more than this over the predicted 3 s."""


def _per_agent(pred: NDArrayFloat, truth: NDArrayFloat) -> metrics.AgentScores:
    return metrics.argoverse(metrics.displacement_errors(pred[:, :K], truth))


def _turning(samples: Sequence[SceneSample], truth: NDArrayFloat) -> np.ndarray:
    """Targets whose future heading turns by more than ``TURN_DEG``: where a lane, not momentum, decides."""
    obs = np.concatenate([s.positions[s.target_mask, s.obs_len - 2 : s.obs_len] for s in samples])
    start = np.arctan2(*(obs[:, 1] - obs[:, 0])[:, ::-1].T)
    end = np.arctan2(*(truth[:, -1] - truth[:, -3])[:, ::-1].T)
    turn = np.degrees(np.abs((end - start + np.pi) % (2 * np.pi) - np.pi))
    return np.asarray(turn > TURN_DEG)


def _inside_raster(samples: Sequence[SceneSample], margin_px: float = 20.0) -> np.ndarray:
    """Targets whose whole true path lies on their window's raster (the figure shows the lanes under it)."""
    inside = []
    for s in samples:
        affine = np.asarray(s.world_to_raster)
        size = s.raster.shape[-1] if s.raster is not None else 0
        for row in np.flatnonzero(s.target_mask):
            px = s.positions[row] @ affine[:, :2].T + affine[:, 2]
            inside.append(bool(np.all((px > margin_px) & (px < size - margin_px))))
    return np.asarray(inside)


def gain_interval(full: NDArrayFloat, base: NDArrayFloat, cluster: NDArrayInt, resamples: int = 2000,
                  seed: int = 0) -> dict[str, float]:
    """1 - mean(full) / mean(base) over agents, and its 95 % percentile bootstrap over whole clusters."""
    _, label = np.unique(cluster, return_inverse=True)
    n = int(label.max()) + 1
    f = np.bincount(label, weights=full, minlength=n)
    b = np.bincount(label, weights=base, minlength=n)
    picks = np.random.default_rng(seed).integers(0, n, size=(resamples, n))
    gains = 1.0 - f[picks].sum(axis=1) / b[picks].sum(axis=1)
    low, high = np.percentile(gains, [2.5, 97.5])
    return {"gain": float(1.0 - full.sum() / base.sum()), "low": float(low), "high": float(high),
            "agents": len(full), "windows": n}


def _plot(path: Path, sample: SceneSample, forecasts: dict[str, NDArrayFloat], target: int) -> None:
    """One window at a fork: the lane raster, the target's past, its true future and each model's K modes."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    raster, affine = sample.raster, np.asarray(sample.world_to_raster)
    assert raster is not None
    image = raster[:4].max(axis=0)  # drivable area and the centerline channels
    fig, axes = plt.subplots(1, len(forecasts), figsize=(5 * len(forecasts), 5))
    rows = np.flatnonzero(sample.target_mask)
    for ax, (name, pred) in zip(np.atleast_1d(axes), forecasts.items(), strict=True):
        ax.imshow(image, cmap="Greys", origin="upper")

        def px(xy: NDArrayFloat) -> NDArrayFloat:
            return np.asarray(xy @ affine[:, :2].T + affine[:, 2])

        agent = rows[target]
        past = px(sample.positions[agent, : sample.obs_len])
        future = px(sample.positions[agent, sample.obs_len :])
        for mode in pred:
            m = px(mode)
            ax.plot(m[:, 0], m[:, 1], "-", color="tab:orange", alpha=0.8, lw=1.5)
        ax.plot(past[:, 0], past[:, 1], "-", color="tab:blue", lw=2.5, label="observed 2 s")
        ax.plot(future[:, 0], future[:, 1], "--", color="tab:green", lw=2.5, label="true 3 s")
        ax.set_title(f"{name}: K={K} forecasts (orange)")
        ax.set_axis_off()
    np.atleast_1d(axes)[0].legend(loc="lower left", fontsize=8)
    fig.suptitle(f"SYNTHETIC traffic on the real {sample.sample_id.split('_')[1]} lane graph, held-out region, "
                 f"window {sample.sample_id}")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--full", type=Path, required=True, help="run folder or checkpoint of the full model")
    ap.add_argument("--no-en", type=Path, required=True, help="run folder or checkpoint of v4 (no EN)")
    ap.add_argument("--test", type=Path, default=REPO / "out" / "syn20k_test")
    ap.add_argument("--results", type=Path, default=REPO / "docs" / "results")
    ap.add_argument("--name", default="argoverse_synthetic")
    ap.add_argument("--limit", type=int, default=0, help="score only the first N test windows (a smoke run)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--note", default="", help="a line on how the checkpoints were trained")
    args = ap.parse_args(argv)
    t0 = time.perf_counter()
    from logpipe.model.zhu2020.meta import read_meta
    from logpipe.model.zhu2020.predictor import NetPredictor

    ds = Dataset.open(args.test)
    rasters = find_raster_run(ds.root, None, None)
    samples = scene_samples(ds, "all", rasters=rasters)
    if args.limit:
        samples = samples[: args.limit]
    pred_len = ds.protocol.pred_len
    truth = truth_of(samples, pred_len)
    cluster = np.concatenate([np.full(int(s.target_mask.sum()), i) for i, s in enumerate(samples)])
    forecasts: dict[str, NDArrayFloat] = {}
    checkpoints: dict[str, Any] = {}
    for name, path in (("full", args.full), ("no EN (v4)", args.no_en)):
        ckpt = find_checkpoint(str(path.resolve()), "")
        if ckpt is None:
            raise SystemExit(f"{path}: no checkpoint")
        meta = read_meta(ckpt)
        checkpoints[name] = {"path": str(ckpt), "step": meta.step, "val": meta.metrics,
                             "environment": meta.config.model.features.environment}
        net = NetPredictor.from_checkpoint(ckpt, expect_kind=ds.kind)
        forecasts[name] = np.concatenate(net.predict(samples, K, args.seed))
    scores = {name: _per_agent(pred, truth) for name, pred in forecasts.items()}
    turning = _turning(samples, truth)
    rows = {}
    groups = (("all targets", np.ones(len(truth), bool)), (f"turning > {TURN_DEG:g} deg", turning),
              (f"not turning (<= {TURN_DEG:g} deg)", ~turning))
    for group, mask in groups:
        rows[group] = {
            name: {"minADE": float(s.ade[mask].mean()), "minFDE": float(s.fde[mask].mean()),
                   "MR": float(metrics.miss(s.fde[mask]).mean()), "agents": int(mask.sum())}
            for name, s in scores.items()}
        rows[group]["gain"] = gain_interval(scores["full"].fde[mask], scores["no EN (v4)"].fde[mask],
                                            cluster[mask], seed=args.seed)
    # The window where EN helps most on a turning target inside its raster: the figure.
    diff = np.where(turning & _inside_raster(samples), scores["no EN (v4)"].fde - scores["full"].fde, -np.inf)
    best = int(np.argmax(diff))
    window = int(cluster[best])
    first = int(np.flatnonzero(cluster == window)[0])
    figure = args.results / args.name / "fork.png"
    figure.parent.mkdir(parents=True, exist_ok=True)
    _plot(figure, samples[window],
          {n: f[first : first + int(samples[window].target_mask.sum())][best - first] for n, f in forecasts.items()},
          best - first)
    seconds = time.perf_counter() - t0
    result = {"windows": len(samples), "targets": len(truth), "k": K, "rows": rows, "checkpoints": checkpoints,
              "seconds": round(seconds, 1), "note": args.note}
    (args.results / f"{args.name}.json").write_text(json.dumps(result, indent=1, sort_keys=True))
    (args.results / f"{args.name}.md").write_text(render(result, args, seconds))
    print(f"wrote {args.results / args.name}.md in {seconds:.1f} s", file=sys.stderr)
    return 0


def _dilution(rows: dict[str, Any]) -> str:
    """How much of the all-target gain the turning targets can carry: their share of v4's summed minFDE, and the
    all-target gain at their measured gain had the full model matched v4 on every other target."""
    turn = rows[f"turning > {TURN_DEG:g} deg"]
    total = rows["all targets"]["no EN (v4)"]
    base = turn["no EN (v4)"]["minFDE"] * turn["no EN (v4)"]["agents"]
    share = base / (total["minFDE"] * total["agents"])
    return (f"Where the gain can come from: turning targets carry {100 * share:.0f} % of v4's summed minFDE@6, so a "
            f"model that erased every turning error and changed nothing else would gain {100 * share:.0f} % on all "
            f"targets; at the turning gain measured here ({100 * turn['gain']['gain']:.1f} %), matching v4 on the "
            f"other targets would give {100 * share * turn['gain']['gain']:.1f} %.")


def render(result: dict[str, Any], args: argparse.Namespace, seconds: float) -> str:
    lines = [
        "# SYNTHETIC map check: does the environment net read the lanes?", "",
        "**All data here is SYNTHETIC**: traffic simulated by `logpipe.synthetic.traffic` on the real Argoverse 1 "
        "lane graphs (MIA, PIT); no real vehicle moved like this. It tests one thing: whether the full model uses "
        "the lane raster where the lane decides the future.", "",
        f"Produced by `python -m scripts.synthetic_map_check --full {args.full} --no-en {args.no_en} --test "
        f"{args.test}`. Test: {result['windows']} windows, {result['targets']} targets, all in the held-out region "
        "of each city (no training window within 75 m of it). Protocol: 20 observed + 30 predicted steps at 10 Hz; "
        "targets are every fully observed vehicle but the AV (its past and future are the EMF and ETF inputs); "
        f"K = {result['k']}, per agent, Argoverse convention (the mode with the lowest FDE, its ADE and FDE; "
        "miss: FDE > 2 m). Gain: 1 - minFDE(full) / minFDE(no EN), 95 % bootstrap over whole windows.", "",
        "| targets | method | minADE@6 | minFDE@6 | MR@6 | agents |", "|---|---|---|---|---|---|"]
    for group, row in result["rows"].items():
        for name in ("full", "no EN (v4)"):
            r = row[name]
            lines.append(f"| {group} | {name} | {r['minADE']:.2f} | {r['minFDE']:.2f} | {r['MR']:.3f} | "
                         f"{r['agents']} |")
    lines += ["", "| targets | minFDE@6 gain of EN | 95 % interval | windows |", "|---|---|---|---|"]
    for group, row in result["rows"].items():
        g = row["gain"]
        lines.append(f"| {group} | {100 * g['gain']:.1f} % | [{100 * g['low']:.1f}, {100 * g['high']:.1f}] % | "
                     f"{g['windows']} |")
    overall = result["rows"]["all targets"]["gain"]
    met = overall["low"] >= TARGET_GAIN
    lines += ["", f"**Target** (issue 33: the full model beats it by >= {100 * TARGET_GAIN:.0f} % minFDE@6 on the "
              f"held-out regions): {'met' if met else 'NOT met'} on all targets ({100 * overall['gain']:.1f} %, "
              f"interval [{100 * overall['low']:.1f}, {100 * overall['high']:.1f}] %). The turning rows are a "
              "diagnosis (threshold fixed before the run), not the target: they show where the raster is read. One "
              "training seed; the interval covers test sampling only."]
    lines += ["", _dilution(result["rows"])]
    lines += ["", "## Checkpoints", ""]
    for name, c in result["checkpoints"].items():
        lines.append(f"- {name}: `{c['path']}`, step {c['step']}, validation {c['val']}, EN "
                     f"{'on' if c['environment'] else 'off'}")
    if result["note"]:
        lines += ["", result["note"]]
    lines += ["", f"![a held-out window where EN helps most on a turning target]({args.name}/fork.png)", "",
              "## Time", "", machine_note(seconds), ""]
    return "\n".join(lines)


if __name__ == "__main__":
    sys.exit(main())
