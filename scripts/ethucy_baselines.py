"""Every kinematic baseline on an ETH/UCY scene's test windows, with its settings chosen on that scene's training
windows: the row the shipped social checkpoints (``model/checkpoints/ethucy/<scene>/social_*``) stand beside.

Windows: the Social-GAN split files (8 observed + 12 predicted steps at 2.5 Hz), samples with at least 2 targets (the
published test sizes' convention, ``logpipe score --min-agents 2``). K = 1: CV, least-squares CV, the Kalman filter
and the adaptive prior, each over its grid, and the best of them (``model.kinematic.best_baseline``, chosen on
``<scene>/train``). K = 20: the CV sampler with plain CV as mode 0, its noise chosen on ``<scene>/train`` by
minFDE@20 (``model.residual.compare``'s grid, its heading noise widened to 1.28 rad), best-of-20 per agent and
joint (one sample index for every agent of a window, Social-GAN's evaluation)::

    python -m scripts.ethucy_baselines [--scene zara1]

Writes ``docs/results/ethucy_baselines.json`` and ``.md``.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

import numpy as np

from logpipe.model.kinematic import best_baseline
from logpipe.model.residual.compare import SAMPLER_HEADINGS, choose_sampler_noise, cv_sampler
from logpipe.stages.train import scene_samples
from logpipe.types import NDArrayFloat
from scripts.locations import REPO, ensure_dataset

K = 20
MIN_AGENTS = 2
HEADINGS = (*SAMPLER_HEADINGS, 0.64, 1.28)
"""The CV sampler's heading noise candidates, rad: the driving grid, widened for walkers (who turn far more)."""


def windows(ds: Any, split: str) -> tuple[NDArrayFloat, NDArrayFloat, np.ndarray]:
    """(observed (N, T_obs, 2), future (N, T_pred, 2), window number (N,)) of every target of ``split``'s samples
    with at least ``MIN_AGENTS`` targets."""
    obs, fut, win = [], [], []
    for n, s in enumerate(scene_samples(ds, split)):
        mask = np.asarray(s.target_mask, bool)
        if mask.sum() < MIN_AGENTS:
            continue
        obs.append(s.positions[mask, :s.obs_len])
        fut.append(s.positions[mask, s.obs_len:])
        win.append(np.full(int(mask.sum()), n))
    return np.concatenate(obs), np.concatenate(fut), np.concatenate(win)


def ade_fde(forecasts: NDArrayFloat, future: NDArrayFloat, window: np.ndarray) -> dict[str, list[float]]:
    """(N, K, T, 2) forecasts: mode 0's ADE/FDE, best-of-K per agent and joint (by window), metres."""
    dist = np.linalg.norm(forecasts - future[:, None], axis=-1)  # (N, K, T)
    ade, fde = dist.mean(axis=2), dist[:, :, -1]
    per_agent = np.argmin(fde, axis=1)
    rows = np.arange(len(fde))
    joint = np.empty(len(fde), int)
    for w in np.unique(window):
        m = window == w
        joint[m] = int(np.argmin(ade[m].sum(axis=0)))
    return {"k1": [float(ade[:, 0].mean()), float(fde[:, 0].mean())],
            "per_agent": [float(ade[rows, per_agent].mean()), float(fde[rows, per_agent].mean())],
            "joint": [float(ade[rows, joint].mean()), float(fde[rows, joint].mean())]}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--shared", type=Path, default=REPO.parent / "shared" / "data")
    ap.add_argument("--work", type=Path, default=REPO / "out" / "ethucy")
    ap.add_argument("--scene", default="zara1")
    ap.add_argument("--out", type=Path, default=REPO / "docs" / "results" / "ethucy_baselines.json")
    args = ap.parse_args(argv)
    ds = ensure_dataset(args.shared / "ethucy", args.work)
    train_obs, train_fut, _ = windows(ds, f"{args.scene}/train")
    obs, fut, win = windows(ds, f"{args.scene}/test")
    pred_len = fut.shape[1]
    per_method = best_baseline.choose_per_method(train_obs, train_fut)
    best = best_baseline.choose(per_method)
    rows = {name: ade_fde(best_baseline.forecast(rec, obs, pred_len)[:, None], fut, win)["k1"]
            for name, rec in per_method.items()}
    rows["best kinematic baseline"] = ade_fde(best_baseline.forecast(best, obs, pred_len)[:, None], fut, win)["k1"]
    noise = choose_sampler_noise(train_obs, train_fut, K, headings=HEADINGS)
    sampler = ade_fde(cv_sampler(obs, pred_len, K, noise["heading_std_rad"], noise["speed_std_frac"], 0), fut, win)
    result = {"scene": args.scene, "test_agents": len(obs), "train_agents": len(train_obs), "k1": rows,
              "chosen": {name: best_baseline.label(rec) for name, rec in per_method.items()},
              "best": best_baseline.label(best),
              "cv_sampler": noise | sampler}
    args.out.write_text(json.dumps(result, indent=1) + "\n")
    args.out.with_suffix(".md").write_text(markdown(result))
    return 0


def markdown(r: dict[str, Any]) -> str:
    """``docs/results/ethucy_baselines.md``."""
    intro = __doc__.split("\n\n")
    lines = [f"# Kinematic baselines on ETH/UCY {r['scene'].upper()} (test)\n", intro[0].replace("\n", " ") + "\n",
             intro[1].replace("\n", " ").replace("::", ".") + "\n",
             f"{r['test_agents']:,} test agents; settings chosen on {r['train_agents']:,} training agents. ADE/FDE in "
             "metres.\n", "| method (K = 1) | settings chosen on train | ADE/FDE |", "|---|---|---|"]
    for name, (ade, fde) in r["k1"].items():
        lines.append(f"| {name} | {r['chosen'].get(name, r['best'])} | {ade:.2f}/{fde:.2f} |")
    s = r["cv_sampler"]
    lines += ["", f"CV sampler, mode 0 = CV, noise {s['heading_std_rad']} rad and {s['speed_std_frac']} of speed "
              + ("(on its grid's edge)" if s["on_grid_edge"] else "(an interior point of its grid)") + ":", "",
              "| CV sampler | ADE/FDE |", "|---|---|"]
    lines += [f"| {rule} | {s[key][0]:.2f}/{s[key][1]:.2f} |" for rule, key in
              (("K = 1 (mode 0, plain CV)", "k1"), ("best-of-20 per agent", "per_agent"),
               ("best-of-20 joint", "joint"))]
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    raise SystemExit(main())
