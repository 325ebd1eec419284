"""Resampling: linear inside a track, on a shared absolute grid, no extrapolation, gaps not bridged."""

from __future__ import annotations

import numpy as np
import pytest

from logpipe.dataset.resample import ResampleSpec, grid_times, resample_track

MS = 1_000_000


def test_linear_interpolation_on_the_absolute_grid() -> None:
    t = np.array([1_050, 1_170, 1_290, 1_410]) * MS  # 120 ms apart, off-grid
    x = t / 1e9 * 3.0 + 1.0  # linear in time
    grid, out = resample_track(t, {"x": x}, ResampleSpec(hz=10))
    assert grid.tolist() == [1_100 * MS, 1_200 * MS, 1_300 * MS, 1_400 * MS]  # inside the span only
    assert np.allclose(out["x"], grid / 1e9 * 3.0 + 1.0)


def test_gap_is_not_bridged_and_ends_are_not_extrapolated() -> None:
    t = np.array([0, 100, 200, 700, 800]) * MS  # a 500 ms hole: longer than 2 periods of 100 ms
    grid, _ = resample_track(t, {"x": t / 1e8}, ResampleSpec(hz=10, gap_periods=2))
    assert (grid // MS).tolist() == [0, 100, 200, 700, 800]
    grid, _ = resample_track(t, {"x": t / 1e8}, ResampleSpec(hz=10, gap_periods=6))
    assert (grid // MS).tolist() == [0, 100, 200, 300, 400, 500, 600, 700, 800]


def test_heading_takes_the_short_arc_and_nan_stays_unknown() -> None:
    t = np.array([0, 200]) * MS
    grid, out = resample_track(t, {"heading": np.array([3.1, -3.1]), "vx": np.array([1.0, np.nan])},
                               ResampleSpec(hz=10))  # fmt: skip
    assert grid.tolist() == [0, 100 * MS, 200 * MS]
    assert abs(abs(out["heading"][1]) - np.pi) < 1e-9  # through ±pi, not through 0
    assert out["vx"][0] == 1.0 and np.isnan(out["vx"][1]) and np.isnan(out["vx"][2])


def test_unsorted_duplicates_and_single_samples() -> None:
    t = np.array([200, 0, 0, 100]) * MS
    grid, out = resample_track(t, {"x": np.array([2.0, 0.0, 9.0, 1.0])}, ResampleSpec(hz=10))
    assert out["x"].tolist() == [0.0, 1.0, 2.0]  # the first sample at a repeated time wins
    grid, out = resample_track(np.array([150 * MS]), {"x": np.array([1.0])}, ResampleSpec(hz=10))
    assert len(grid) == 0  # one off-grid sample holds no grid time
    grid, out = resample_track(np.array([300 * MS]), {"x": np.array([1.0])}, ResampleSpec(hz=10))
    assert grid.tolist() == [300 * MS] and out["x"].tolist() == [1.0]


def test_spec_and_grid_helpers() -> None:
    spec = ResampleSpec(hz=2.5, gap_periods=1.5)
    assert spec.period_ns == 400 * MS and spec.max_gap_ns == 600 * MS
    grid, idx = grid_times(np.array([0, 100]) * MS, ResampleSpec(hz=1))
    assert grid.tolist() == [0] and idx.tolist() == [0]
    with pytest.raises(ZeroDivisionError):
        _ = ResampleSpec(hz=0).period_ns


def test_slow_source_is_upsampled_but_its_dropouts_stay_gaps() -> None:
    """A 1 Hz source at 10 Hz: interpolated between its samples (median interval 1 s), but not across 5 s."""
    t = np.array([0, 1000, 2000, 3000, 8000, 9000]) * MS
    grid, out = resample_track(t, {"x": t / 1e9}, ResampleSpec(hz=10))
    kept = set((grid // MS).tolist())
    assert set(range(0, 3001, 100)) <= kept and set(range(8000, 9001, 100)) <= kept
    assert not kept & set(range(3100, 8000, 100))
    assert np.allclose(out["x"], grid / 1e9)
