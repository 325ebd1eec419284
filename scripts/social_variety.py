"""Whether a Social-GAN checkpoint's 20 samples differ (issue 63: 20VP-20 collapsed to one forecast): on evenly
spaced windows of a split, each window's 20 joint samples from the model's own predictor path, and per window

* ``spread_m``: the mean distance between two samples' final positions of the same agent (0: one forecast);
* ``best_gain``: joint best-of-20 ADE over the first sample's ADE (1: the other 19 add nothing);
* the decoder's initial state: the context's mean absolute value against the noise's (N(0, 1): 0.80).

Usage::

    python -m scripts.social_variety CHECKPOINT DATASET --split zara1/val [--windows 200] [--json]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

import numpy as np
import torch

from logpipe.dataset.reader import Dataset
from logpipe.model.social import split_samples
from logpipe.model.social_gan.fit import forecast
from logpipe.model.social_gan.predictor import load_generator
from logpipe.model.training.social_batch import evenly, stack, window_tracks


def variety(checkpoint: Path, dataset: Path, split: str, windows: int) -> dict[str, Any]:
    """The figures of the module docstring for ``checkpoint`` on ``windows`` windows of ``split``."""
    generator, meta = load_generator(checkpoint)
    samples, _ = split_samples([Dataset.open(dataset)], split)
    tracks = evenly(window_tracks(samples), windows)
    obs_len = meta.obs_len
    preds = forecast(generator, [t[:obs_len] for t in tracks], 20, list(range(len(tracks))))
    spread, gain = [], []
    for pred, track in zip(preds, tracks, strict=True):
        final = pred[:, -1]  # (K, N, 2)
        pairwise = np.linalg.norm(final[:, None] - final[None], axis=-1)  # (K, K, N)
        spread.append(float(pairwise.sum() / (20 * 19 * final.shape[1])))
        ade = np.linalg.norm(pred - track[obs_len:][None], axis=-1).mean(axis=(1, 2))  # (K,) per joint sample
        gain.append(float(ade.min() / ade[0]))
    batch = stack([t[:obs_len] for t in tracks])
    with torch.no_grad():
        context = generator.encode(batch.positions, batch.relative(), batch.pair_i, batch.pair_j)
    return {"checkpoint": str(checkpoint), "step": meta.step, "windows": len(tracks),
            "spread_m": round(float(np.mean(spread)), 3), "best_gain": round(float(np.mean(gain)), 3),
            "context_mean_abs": round(float(context.abs().mean()), 3),
            "context_dead_units": int((context.abs().amax(dim=0) == 0).sum()), "context_units": context.shape[1]}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("checkpoint", type=Path)
    parser.add_argument("dataset", type=Path)
    parser.add_argument("--split", required=True)
    parser.add_argument("--windows", type=int, default=200)
    args = parser.parse_args()
    torch.set_num_threads(1)
    print(json.dumps(variety(args.checkpoint, args.dataset, args.split, args.windows)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
