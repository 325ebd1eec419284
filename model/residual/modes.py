"""Which of the residual model's forecasts make its K modes.

The network gives a K = 1 forecast (the mean head, or physics where ``logpipe predict`` falls back) and six mode
heads with scores. Taking the K - 1 best-scored heads wastes modes when two heads (or a head and mode 0) end at
nearly the same point, so the heads are taken in score order, skipping any whose end lies within ``MODE_GAP_M`` of a
mode already taken; the skipped ones fill what is left, in score order (the endpoint suppression of MultiPath and
TNT, on six candidates).

Chosen on the validation targets of all six leave-one-location-out folds (their validation clusters, never the
held-out location), minFDE@6 in metres, gap grid 0 (plain score order) / 0.5 / 1 / 2 / 3 / 4 m:

- physics first (predict's fallback): 0.756 / 0.744 / **0.735** / 0.740 / 0.748 / 0.756, better at 1 m in every
  fold; turning targets 3.90 -> 3.84;
- mean head first: 0.774 / 0.751 / **0.745** / 0.768 (2 m; 3 and 4 m not run).
"""

from __future__ import annotations

import numpy as np

from logpipe.types import NDArrayFloat

MODE_GAP_M = 1.0
"""Metres between the ends of two modes below which the later-scored head gives way (chosen on validation)."""


def spread_modes(first: NDArrayFloat, heads: NDArrayFloat, num_modes: int, gap_m: float = MODE_GAP_M
                 ) -> NDArrayFloat:
    """(N, num_modes, T, 2): ``first`` (N, T, 2) as mode 0, then heads of ``heads`` (N, H, T, 2, best score first)
    whose end lies at least ``gap_m`` metres from every mode taken before, then the skipped heads in score order,
    then ``first`` again where more modes are asked for than there are forecasts. Same frame as the inputs."""
    n, num_heads = heads.shape[:2]
    taken_ends = np.full((n, num_modes, 2), np.nan)
    taken_ends[:, 0] = first[:, -1]
    keep = np.zeros((n, num_heads), bool)
    count = np.ones(n, int)
    for h in range(num_heads):
        gaps = np.linalg.norm(taken_ends - heads[:, h, None, -1], axis=-1)
        ok = (count < num_modes) & np.all(np.isnan(gaps) | (gaps >= gap_m), axis=1)
        taken_ends[ok, np.minimum(count[ok], num_modes - 1)] = heads[ok, h, -1]
        keep[:, h] = ok
        count += ok
    # Kept heads first, then the skipped ones, each group in score order (a stable sort on "skipped").
    order = np.argsort(~keep, axis=1, kind="stable")
    ranked = np.take_along_axis(heads, order[:, :, None, None], axis=1)
    picked = np.concatenate([first[:, None], ranked], axis=1)[:, :num_modes]
    if picked.shape[1] < num_modes:
        picked = np.concatenate([picked, np.repeat(first[:, None], num_modes - picked.shape[1], axis=1)], axis=1)
    return picked


def model_modes(ranked: NDArrayFloat, num_modes: int) -> NDArrayFloat:
    """(N, num_modes, T, 2): the model's own K modes from its ranked forecasts (N, 1 + heads, T, 2; the mean head
    first, then the heads by score, as ``fit.ranked_forecasts`` gives them): the mean head, then the heads spread."""
    return spread_modes(ranked[:, 0], ranked[:, 1:], num_modes)
