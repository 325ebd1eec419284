"""The adaptive kinematic prior: exact on lines, each track's own window, partial tracks, and on real tracks."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from logpipe.model.kinematic.adaptive_prior import WINDOWS, AdaptiveConstantVelocity, adaptive_fit
from logpipe.stages.ingest import IngestOptions, ingest
from logpipe.stages.train import scene_samples

DATA = Path(__file__).resolve().parents[1] / "data" / "commonroad"


def test_a_straight_track_is_continued_exactly() -> None:
    t = np.arange(20, dtype=np.float64)
    track = np.stack([3.0 + 1.5 * t, -2.0 + 0.5 * t], axis=1)[None]
    fit = adaptive_fit(track)
    np.testing.assert_allclose(fit.origin, track[:, -1])
    np.testing.assert_allclose(fit.velocity, [[1.5, 0.5]])
    np.testing.assert_allclose(fit.forecast(3)[0], track[0, -1] + np.outer([1, 2, 3], [1.5, 0.5]))


def test_noisy_tracks_choose_long_windows_and_smooth_ones_short() -> None:
    rng = np.random.default_rng(0)
    t = np.arange(20, dtype=np.float64)
    line = np.stack([1.2 * t, 0.0 * t], axis=1)
    noisy = line + rng.normal(0, 0.3, (200, 20, 2))  # detections jitter around a straight drive
    speeding = np.stack([0.5 * t + 0.05 * t**2, 0.0 * t], axis=1)  # a smooth accelerating track
    assert np.median(adaptive_fit(noisy).window) >= 8
    assert adaptive_fit(speeding[None]).window[0] == 2
    # smoothing pays: the noisy tracks' 3 s error is far below the last displacement's
    truth = np.stack([1.2 * np.arange(20, 50), np.zeros(30)], axis=1)
    adaptive = np.linalg.norm(adaptive_fit(noisy).forecast(30)[:, -1] - truth[-1], axis=1).mean()
    last = noisy[:, -1] + (noisy[:, -1] - noisy[:, -2]) * 30
    assert adaptive < 0.5 * np.linalg.norm(last - truth[-1], axis=1).mean()


def test_partial_tracks_use_what_they_have() -> None:
    t = np.arange(20, dtype=np.float64)
    track = np.stack([2.0 * t, t], axis=1)
    parts = np.repeat(track[None], 3, axis=0)
    parts[0, :17] = np.nan  # 3 trailing steps: no backtest, the last displacement
    parts[1, :19] = np.nan  # 1 step: stands still
    parts[2, -1] = np.nan  # not observed now: no forecast
    fit = adaptive_fit(parts)
    assert fit.window.tolist() == [2, 0, 0]
    np.testing.assert_allclose(fit.velocity[0], [2.0, 1.0])
    np.testing.assert_allclose(fit.velocity[1], [0.0, 0.0])
    assert np.isnan(fit.forecast(5)[2]).all()
    assert set(WINDOWS) >= {2, 12}


def test_baseline_predictor_on_real_scenarios(tmp_path: Path) -> None:
    ingest([DATA], IngestOptions(out=tmp_path / "ds", write_mcap=False))
    from logpipe.dataset.reader import Dataset

    samples = scene_samples(Dataset.open(tmp_path / "ds"), "all")
    forecasts = AdaptiveConstantVelocity(pred_len=30).predict(samples, num_modes=2, seed=0)
    for sample, fc in zip(samples, forecasts, strict=True):
        targets = int(np.asarray(sample.target_mask).sum())
        assert fc.shape == (targets, 2, 30, 2) and np.isfinite(fc).all()
        np.testing.assert_array_equal(fc[:, 0], fc[:, 1])
        last = sample.positions[np.asarray(sample.target_mask, bool), sample.obs_len - 1]
        assert np.linalg.norm(fc[:, 0, 0] - last, axis=1).max() < 3.0  # starts where the car is
    with pytest.raises(ValueError, match="must be"):
        adaptive_fit(np.zeros((1, 20, 3)))
