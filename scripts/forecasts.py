"""Predictions files of every method a results table compares: the non-learned baselines, a learned checkpoint at
the inference settings chosen on validation (and as trained), written as ``schemas/predictions.json`` tables that
``logpipe score`` reads; and those files read back as dense forecasts for the diagnoses."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from logpipe.model.checkpoint.format import InferenceSettings
from logpipe.model.kinematic.constant_velocity import ConstantVelocity, LinearFit
from logpipe.model.kinematic.kalman import KalmanCV
from logpipe.model.predictor import Predictor, inference_id
from logpipe.model.zhu2020.meta import amend_meta, read_meta
from logpipe.model.zhu2020.predictor import NetPredictor
from logpipe.prediction.runs import PredictionMeta
from logpipe.prediction.table import samples_table
from logpipe.scoring.method_forecasts import load_method
from logpipe.storage.io import write_parquet
from logpipe.types import NDArrayFloat, SceneSample
from scripts.validation import (
    chosen_sampler,
    neighbour_cap,
    predicted_best_of_k,
    shifted_best_of_k,
    tune_inference,
    tuned,
)


def write_learned(  # noqa: PLR0913  script helper shared by the reproduce_* scripts and seeds.py
    checkpoint: Path, kind: str, val: Sequence[SceneSample], test: Sequence[SceneSample], k: int,
    seed: int, pred_len: int, pdir: Path, method: str, as_trained: str | None = None,
    speed_shift: bool = False, rate_val: Sequence[SceneSample] | None = None,
    train: Sequence[SceneSample] | None = None,
    store_as: str | None = None, as_specified: bool = False,
) -> tuple[list[Path], dict[str, Any] | None]:
    """Test predictions of a learned method: with K > 1 at the inference settings chosen on ``val`` (and, named
    ``as_trained``, at the checkpoint's own too); with K = 1 as it is. A network that pools each target's
    neighbourhood gets the fold's neighbour cap from ``train`` (``neighbour_cap``) in every run but the as-trained
    one. Returns the files and the choice (None for K = 1), with the speed-shift check's val ADE/FDE when
    ``speed_shift`` and the frame-rate check's on ``rate_val``. ``store_as``: record the choice in the checkpoint's
    ``meta.json`` (``logpipe predict``'s defaults for it) with this description of how it was chosen.
    ``as_specified``: the paper's method as the paper specifies it, sampled as trained: nothing chosen, no cap."""
    sha = read_meta(checkpoint).weights_sha256
    net = NetPredictor.from_checkpoint(checkpoint, expect_kind=kind)
    cap = None
    if as_specified:
        return [write_predictions(net, test, k, seed, pred_len, sha, pdir / f"{method}.parquet", method)], None
    if train is not None and net.config.pools_context:
        assert net.config.context_radius_m is not None
        cap = neighbour_cap(train, net.config.context_radius_m)
        net = net.with_context_max_neighbours(cap)
    if k == 1:
        return [write_predictions(net, test, k, seed, pred_len, sha, pdir / f"{method}.parquet", method)], None
    choice, grid = tune_inference(net, val, pred_len, k, seed)
    if cap is not None:
        choice["context_max_neighbours"] = cap
    if store_as is not None:
        amend_meta(checkpoint, inference=InferenceSettings(num_modes=k, chosen_on=store_as, **choice))
    best = tuned(net, choice)
    files = [write_predictions(best, test, k, seed, pred_len, inference_id(sha, **choice),
                               pdir / f"{method}.parquet", method)]
    if as_trained is not None:
        plain = net.with_context_max_neighbours(None)
        files.append(write_predictions(plain, test, k, seed, pred_len, sha, pdir / f"{as_trained}.parquet",
                                       as_trained))
    trained_held = net.config.held_modes(k)
    chosen: dict[str, Any] = {**choice, "grid": grid, "trained_constant_velocity_modes": trained_held}
    if speed_shift:
        chosen["speed_shift_val"] = shifted_best_of_k(best, val, pred_len, k, seed)
    if rate_val is not None:
        chosen["rate_shift_val"] = predicted_best_of_k(best, rate_val, pred_len, k, seed)
    return files, chosen


def write_predictions(predictor: Predictor, samples: Sequence[SceneSample], k: int, seed: int, pred_len: int,
                      checkpoint_id: str, out: Path, name: str | None = None) -> Path:
    """Run ``predictor`` and write its predictions table (``schemas/predictions.json``) to ``out``."""
    forecasts = predictor.predict(samples, k, seed)
    meta = PredictionMeta(predictor=name or predictor.name, checkpoint_id=checkpoint_id, protocol=None,
                          obs_len=samples[0].obs_len if samples else 0, pred_len=pred_len, num_modes=k, seed=seed)
    write_parquet(samples_table(meta, samples, forecasts), out)
    return out


def write_classical(samples: Sequence[SceneSample], pred_len: int, seed: int, sampler: dict[str, float],
                    sampler_k: int, sampler_id: str, pdir: Path) -> list[Path]:
    """Predictions of the non-learned methods: CV, Linear, Kalman (K=1) and the CV sampler (K=``sampler_k``)."""
    return [
        write_predictions(ConstantVelocity(pred_len=pred_len), samples, 1, seed, pred_len, "constant_velocity",
                          pdir / "cv.parquet", "cv"),
        write_predictions(LinearFit(pred_len=pred_len), samples, 1, seed, pred_len, "linear",
                          pdir / "linear.parquet", "linear"),
        write_predictions(KalmanCV(pred_len=pred_len), samples, 1, seed, pred_len,
                          "kalman_cv accel_std=0.1 meas_std=0.05 init_vel_std=2.0", pdir / "kalman.parquet", "kalman"),
        write_predictions(chosen_sampler(sampler, pred_len), samples, sampler_k, seed, pred_len,
                          sampler_id, pdir / "cv_sampler.parquet", "cv_sampler"),
    ]


def read_forecasts(files: Sequence[Path], samples: Sequence[SceneSample], methods: Sequence[str],
                   ) -> dict[str, NDArrayFloat]:
    """Each of ``methods`` read back from its predictions file as (N, K, T, 2) in ``truth_of(samples)`` row order;
    an agent the file lacks gets NaN."""
    keys = [(s.sample_id, s.track_ids[r]) for s in samples for r in np.flatnonzero(s.target_mask)]
    row_of = {key: i for i, key in enumerate(keys)}
    out = {}
    for forecasts in (m for m in map(load_method, files) if m.name in methods):
        dense = np.full((len(keys), *forecasts.pred.shape[1:]), np.nan)
        for i, key in enumerate(zip(forecasts.sample_ids.tolist(), forecasts.track_ids.tolist(), strict=True)):
            if key in row_of:
                dense[row_of[key]] = forecasts.pred[i]
        out[forecasts.name] = dense
    return out
