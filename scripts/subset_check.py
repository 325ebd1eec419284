"""Validation-only check: does choosing K diverse forecasts out of many separate the methods on ETH/UCY?

Under per-agent best-of-K, a method whose K samples cover more of the plausible futures wins. A common trick
draws M > K samples and keeps K representatives (here: k-means with K centres on the whole M trajectories of each
agent, seeded by farthest-point picks). This check applies the same reduction to every stochastic method of
``make reproduce-ethucy`` (the CV sampler at its setting chosen on ``S/val``, Noise-LSTM and ours at their noise
scale chosen there) and reports the per-agent best-of-K ADE/FDE on ``S/val`` with and without it. Test data is
never read: this is a question about the methods, not a setting for the results table.

Usage::

    python -m scripts.subset_check [--scenes eth zara2] [--draws 100] [--out docs/results/ethucy_subset_check.json]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from logpipe.model.predictor import Predictor
from logpipe.model.zhu2020.predictor import NetPredictor
from logpipe.stages.train import scene_samples
from logpipe.types import NDArrayFloat, NDArrayInt, SceneSample
from scripts.ethucy_report import SCENES
from scripts.locations import REPO, ensure_dataset, find_checkpoint
from scripts.reproduce_ethucy import LEARNED
from scripts.validation import K_BEST, best_of_k, chosen_sampler, truth_of, tune_inference, tune_sampler, tuned


def farthest_points(x: NDArrayFloat, k: int) -> NDArrayInt:
    """(N, k) indices into the M candidates of each row of ``x`` (N, M, D): the candidate nearest the row's mean,
    then repeatedly the one farthest from those already picked (squared Euclidean distance)."""
    rows = np.arange(x.shape[0])
    pick = [np.argmin(((x - x.mean(axis=1, keepdims=True)) ** 2).sum(-1), axis=1)]
    dist = ((x - x[rows, pick[0]][:, None]) ** 2).sum(-1)
    for _ in range(k - 1):
        pick.append(np.argmax(dist, axis=1))
        dist = np.minimum(dist, ((x - x[rows, pick[-1]][:, None]) ** 2).sum(-1))
    return np.stack(pick, axis=1)


def kmeans_centres(x: NDArrayFloat, k: int, iterations: int = 10) -> NDArrayFloat:
    """(N, k, D) k-means centres of each row's M points in ``x`` (N, M, D), batched over rows (Lloyd's
    iterations from farthest-point seeds; an emptied cluster keeps its previous centre)."""
    centres = np.take_along_axis(x, farthest_points(x, k)[..., None], axis=1)
    for _ in range(iterations):
        nearest = ((x[:, :, None] - centres[:, None]) ** 2).sum(-1).argmin(-1)  # (N, M)
        member = np.eye(k)[nearest]  # (N, M, k)
        count = member.sum(axis=1)
        mean = np.einsum("nmk,nmd->nkd", member, x) / np.maximum(count, 1)[..., None]
        centres = np.where(count[..., None] > 0, mean, centres)
    return centres


def reduced(pred: NDArrayFloat, k: int) -> NDArrayFloat:
    """(N, k, T, 2) k-means representatives of (N, M, T, 2) forecasts (whole trajectories as points)."""
    n, m, t, _ = pred.shape
    return kmeans_centres(pred.reshape(n, m, t * 2), k).reshape(n, k, t, 2)


def compare(predictor: Predictor, samples: Sequence[SceneSample], pred_len: int, draws: int,
            seed: int) -> dict[str, list[float]]:
    """Best-of-K ADE/FDE of the first K of ``draws`` samples against the K k-means representatives of all."""
    truth = truth_of(samples, pred_len)
    pred = np.concatenate(predictor.predict(samples, draws, seed))
    ok = np.all(np.isfinite(truth), axis=(1, 2)) & np.all(np.isfinite(pred), axis=(1, 2, 3))
    return {"first_k": list(best_of_k(pred[ok, :K_BEST], truth[ok])),
            "kmeans_of_draws": list(best_of_k(reduced(pred[ok], K_BEST), truth[ok]))}


def main(argv: Sequence[str] | None = None) -> int:
    """Run the check; returns the process exit code."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", type=Path, default=REPO.parent / "shared" / "data" / "ethucy")
    ap.add_argument("--work", type=Path, default=REPO / "out" / "reproduce" / "ethucy")
    ap.add_argument("--scenes", nargs="+", default=list(SCENES), choices=SCENES)
    ap.add_argument("--draws", type=int, default=100, help="samples drawn before reducing to K=20")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", type=Path, default=REPO / "docs" / "results" / "ethucy_subset_check.json")
    args = ap.parse_args(argv)
    t0 = time.perf_counter()
    ds = ensure_dataset(args.data, args.work / "dataset", "ethucy")
    pred_len = ds.protocol.pred_len
    result: dict[str, dict[str, object]] = {}
    for scene in args.scenes:
        val = scene_samples(ds, f"{scene}/val")
        choice, _ = tune_sampler(val, pred_len, K_BEST, args.seed)
        methods: dict[str, object] = {
            "cv_sampler": {"setting": choice, **compare(chosen_sampler(choice, pred_len), val,
                                                        pred_len, args.draws, args.seed)}}
        for method in ("noise_lstm", "zhu2020"):
            ckpt = find_checkpoint(LEARNED[method][0], scene)
            if ckpt is None:
                continue
            net = NetPredictor.from_checkpoint(ckpt, expect_kind=ds.kind)
            setting, _ = tune_inference(net, val, pred_len, K_BEST, args.seed)
            methods[method] = {"setting": setting,
                               **compare(tuned(net, setting), val, pred_len, args.draws, args.seed)}
        result[scene] = methods
        print(f"{scene}: {json.dumps(methods)}", file=sys.stderr)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({"split": "S/val", "k": K_BEST, "draws": args.draws, "seed": args.seed,
                                    "protocol": "per-agent best-of-K ADE/FDE (m), every window",
                                    "seconds": round(time.perf_counter() - t0, 1), "scenes": result},
                                   indent=1, sort_keys=True))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
