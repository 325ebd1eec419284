"""What the scripts measure on validation: best-of-K errors of forecasts against the true futures, the choice of
the constant-velocity sampler's noise and of a learned method's inference settings (noise scale, constant-velocity
modes, neighbour cap) on a validation split, and the speed-shift check. Positions and errors in metres."""

from __future__ import annotations

import dataclasses
import itertools
from collections.abc import Sequence
from typing import Any

import numpy as np

from logpipe.model.kinematic.constant_velocity import ConstantVelocitySampler
from logpipe.model.predictor import Predictor
from logpipe.model.zhu2020.batching import neighbour_counts
from logpipe.model.zhu2020.predictor import NetPredictor
from logpipe.scoring import metrics
from logpipe.types import NDArrayFloat, SceneSample

K_BEST = 20
"""K of the pedestrian tables' best-of-K rows (the Social-GAN rows the paper compares with)."""
HEADING_GRID = (0.02, 0.05, 0.1, 0.15, 0.2, 0.25, 0.3, 0.4, 0.5, 0.7)
"""Sampler heading noise std candidates, radians."""

SPEED_GRID = (0.0, 0.1, 0.2, 0.3, 0.4, 0.6, 0.8)
"""Sampler relative speed noise std candidates."""

NOISE_SCALE_GRID = (0.5, 0.75, 1.0, 1.5, 2.0, 2.5, 3.0)
"""Candidates for the std of a learned method's noise z at inference (1 = eq. 21, what training drew)."""

CV_MODES_GRID = (0, 1)
"""Candidates for how many of a learned method's K modes are held to constant velocity at inference."""

NEIGHBOUR_CAP_PERCENTILE = 99
"""A fold's neighbour cap (``ModelConfig.context_max_neighbours``, for the methods with interaction features) is this
percentile of its training targets' neighbour counts within the context radius: at test each target sees at most as
many neighbours as all but 1 % of the training targets did. Fixed before any test was read; see ``neighbour_cap``."""

SPEED_SHIFT = 2.4
"""Factor of the speed-shift check: ``S/val`` with every position scaled by it, the same motion this many times
faster. biwi_eth's median one-step displacement (1.01 m, measured on ``biwi_eth_train.txt``) is about 2.4 times the
other scenes' (0.21-0.58 m): the leave-one-out ETH fold tests at speeds its training never saw. Provenance: every row
of ``biwi_eth_train.txt`` lies in ETH's test recording, so this factor is test information; a choice it decides is
recorded as such (``configs/ethucy.toml``, ``speed_unit_m``)."""


def truth_of(samples: Sequence[SceneSample], pred_len: int) -> NDArrayFloat:
    """(N, T, 2) true futures of every target of ``samples``, in ``Predictor`` row order."""
    rows = [s.positions[s.target_mask, s.obs_len : s.obs_len + pred_len] for s in samples]
    return np.concatenate(rows) if rows else np.zeros((0, pred_len, 2))


def best_of_k(pred: NDArrayFloat, truth: NDArrayFloat) -> tuple[float, float]:
    """Mean per-agent best-of-K ADE and FDE of (N, K, T, 2) forecasts over the agents with a full future."""
    ok = np.all(np.isfinite(truth), axis=(1, 2))
    best = metrics.best_of_k_per_agent(metrics.displacement_errors(pred[ok], truth[ok]))
    return float(best.ade.mean()), float(best.fde.mean())


def chosen_sampler(choice: dict[str, float], pred_len: int) -> ConstantVelocitySampler:
    """The CV sampler at a ``tune_sampler`` choice (its heading and speed noise)."""
    return ConstantVelocitySampler(pred_len=pred_len, heading_std_rad=choice["heading_std_rad"],
                                   speed_std_frac=choice["speed_std_frac"])


def tune_sampler(val: Sequence[SceneSample], pred_len: int, k: int, seed: int) -> tuple[dict[str, float], list[Any]]:
    """Pick the sampler's (heading_std_rad, speed_std_frac) with the lowest per-agent best-of-k ADE (+FDE as a
    tie-break) on ``val``. Returns the choice and every grid point's (heading, speed, ade, fde)."""
    truth = truth_of(val, pred_len)
    ok = np.all(np.isfinite(truth), axis=(1, 2))
    grid = []
    for h, sp in itertools.product(HEADING_GRID, SPEED_GRID):
        sampler = ConstantVelocitySampler(pred_len=pred_len, heading_std_rad=h, speed_std_frac=sp)
        pred = np.concatenate(sampler.predict(val, k, seed))
        err = metrics.displacement_errors(pred[ok], truth[ok])
        best = metrics.best_of_k_per_agent(err)
        grid.append((h, sp, float(best.ade.mean()), float(best.fde.mean())))
    h, sp, _, _ = min(grid, key=lambda g: (g[2], g[3]))
    return {"heading_std_rad": h, "speed_std_frac": sp}, grid


def tune_inference(net: NetPredictor, val: Sequence[SceneSample], pred_len: int, k: int,
                   seed: int) -> tuple[dict[str, Any], list[tuple[int, float, float, float]]]:
    """Pick a learned method's inference settings, noise scale and constant-velocity modes, with the lowest
    per-agent best-of-k ADE (+FDE as a tie-break) on ``val``, the sampler's criterion. Returns the choice
    ({"noise_scale", "constant_velocity_modes"}) and every candidate's (modes, scale, ade, fde)."""
    truth = truth_of(val, pred_len)
    grid = []
    for held in CV_MODES_GRID:
        for scale in NOISE_SCALE_GRID:
            forecasts = tuned(net, {"noise_scale": scale, "constant_velocity_modes": held}).predict(val, k, seed)
            grid.append((held, scale, *best_of_k(np.concatenate(forecasts), truth)))
    held, scale, _, _ = min(grid, key=lambda g: (g[2], g[3]))
    return {"noise_scale": scale, "constant_velocity_modes": held}, grid


def tuned(net: NetPredictor, choice: dict[str, Any]) -> NetPredictor:
    """``net`` at the inference settings ``tune_inference`` chose; a neighbour cap the choice does not name stays
    ``net``'s."""
    return (net.with_noise_scale(choice["noise_scale"]).with_constant_velocity_modes(choice["constant_velocity_modes"])
            .with_context_max_neighbours(choice.get("context_max_neighbours", net.context_max_neighbours)))


def neighbour_cap(train: Sequence[SceneSample], radius_m: float, percentile: float = NEIGHBOUR_CAP_PERCENTILE) -> int:
    """``percentile`` of the neighbour counts within ``radius_m`` of the targets of ``train`` (an observed count)."""
    counts = np.concatenate([neighbour_counts(s, radius_m) for s in train])
    return int(np.percentile(counts, percentile, method="higher"))


def grid_row(grid: Sequence[Sequence[float]], held: int, scale: float) -> Sequence[float]:
    """The (modes, scale, ade, fde) row of ``tune_inference``'s grid at these settings."""
    return next(g for g in grid if g[0] == held and g[1] == scale)


def chosen_on(val_split: str, k: int, seed: int, command: str, cap_split: str | None = None) -> str:
    """How ``tune_inference`` (and ``neighbour_cap`` on ``cap_split``) chose a checkpoint's inference settings, as
    stored in its ``meta.json``."""
    cap = (f"; neighbour cap (methods that pool neighbours): {NEIGHBOUR_CAP_PERCENTILE}th percentile of "
           f"{cap_split} neighbour counts" if cap_split else "")
    return (f"{val_split}, per-agent best-of-{k} ADE (FDE breaks ties) over constant-velocity modes "
            f"{list(CV_MODES_GRID)} x noise scale {list(NOISE_SCALE_GRID)}, seed {seed}{cap} ({command})")


def speed_shifted(samples: Sequence[SceneSample], factor: float = SPEED_SHIFT) -> list[SceneSample]:
    """``samples`` with every position scaled by ``factor`` about the world origin; a raster keeps its pixels
    under the same agents (the map grows with the scene)."""
    shrink = np.diag([1.0 / factor, 1.0 / factor, 1.0])
    return [dataclasses.replace(s, positions=s.positions * factor,
                                world_to_raster=None if s.world_to_raster is None else s.world_to_raster @ shrink)
            for s in samples]


def predicted_best_of_k(predictor: Predictor, samples: Sequence[SceneSample], pred_len: int, k: int,
                        seed: int) -> tuple[float, float]:
    """Per-agent best-of-k ADE/FDE of ``predictor`` on ``samples``."""
    return best_of_k(np.concatenate(predictor.predict(samples, k, seed)), truth_of(samples, pred_len))


def shifted_best_of_k(predictor: Predictor, val: Sequence[SceneSample], pred_len: int, k: int,
                      seed: int) -> tuple[float, float]:
    """Per-agent best-of-k ADE/FDE of ``predictor`` on the speed-shifted ``val`` (the speed-shift check)."""
    return predicted_best_of_k(predictor, speed_shifted(val), pred_len, k, seed)
