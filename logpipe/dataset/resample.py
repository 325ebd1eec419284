"""Resampling tracks to a fixed rate.

Every track of a log is sampled on the same absolute time grid (multiples of the period on the log's clock), so
steps line up across tracks. Values are interpolated linearly between the two source samples around a grid
time (heading along the shorter arc); a grid time is kept only inside the track's span and only when the
source samples around it are at most ``gap_periods`` periods apart (the longer of the output period and the
track's median source interval, so that a slow source is upsampled while a dropout in a fast one stays a gap):
no extrapolation, no bridging of gaps. The raw
messages stay in the input file, so the original timestamps remain recoverable from it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from logpipe.types import NDArrayFloat, NDArrayInt

ANGLE_COLUMNS = frozenset({"heading"})


@dataclass(frozen=True)
class ResampleSpec:
    """Target rate and gap rule.

    Attributes:
        hz: output rate in Hz (> 0).
        gap_periods: source samples further apart than this many periods are a gap (not bridged); the period is
            the longer of the output period and the track's median source interval.
    """

    hz: float = 10.0
    gap_periods: float = 2.0

    @property
    def period_ns(self) -> int:
        """Output period in nanoseconds."""
        return round(1e9 / self.hz)

    @property
    def max_gap_ns(self) -> int:
        """Longest source interval (ns) interpolated across for a source at least as fast as the output."""
        return round(self.gap_periods * 1e9 / self.hz)

    def max_gap_for(self, t: NDArrayInt) -> int:
        """Longest interval (ns) interpolated across for the sorted source times ``t``."""
        median = int(np.median(np.diff(t))) if len(t) > 2 else 0
        return max(self.max_gap_ns, round(self.gap_periods * median))


def grid_times(t: NDArrayInt, spec: ResampleSpec) -> tuple[NDArrayInt, NDArrayInt]:
    """Grid times inside the sorted, unique source times ``t`` that are not in a gap, and the index of the
    source sample at or before each (so that value i lies between ``t[idx]`` and ``t[idx + 1]``)."""
    period = spec.period_ns
    if len(t) == 0:
        empty = np.zeros(0, dtype=np.int64)
        return empty, empty
    first = -(-int(t[0]) // period) * period  # ceil to the grid
    grid = np.arange(first, int(t[-1]) + 1, period, dtype=np.int64)
    idx = np.searchsorted(t, grid, side="right") - 1
    exact = t[idx] == grid
    nxt = np.minimum(idx + 1, len(t) - 1)
    bridged = (t[nxt] - t[idx]) <= spec.max_gap_for(t)
    keep = exact | bridged
    return grid[keep], idx[keep]


def resample_track(
    t: NDArrayInt, values: dict[str, NDArrayFloat], spec: ResampleSpec
) -> tuple[NDArrayInt, dict[str, NDArrayFloat]]:
    """Resample one track.

    Args:
        t: source timestamps (ns), any order, duplicates allowed (the first sample at a time wins).
        values: float columns of the same length (NaN = unknown; it stays unknown where it is used).
        spec: rate and gap rule.

    Returns:
        The grid timestamps and the interpolated columns.
    """
    order = np.argsort(t, kind="stable")
    t = t[order]
    first = np.ones(len(t), dtype=bool)
    first[1:] = t[1:] != t[:-1]
    t = t[first]
    grid, idx = grid_times(t, spec)
    out: dict[str, NDArrayFloat] = {}
    if len(t) == 1:
        return grid, {k: np.asarray(v, dtype=np.float64)[order][first][idx] for k, v in values.items()}
    i0 = np.minimum(idx, len(t) - 2)
    t0 = t[i0]
    w = ((grid - t0) / np.maximum(t[i0 + 1] - t0, 1)).astype(np.float64)
    for name, col in values.items():
        v = np.asarray(col, dtype=np.float64)[order][first]
        if name in ANGLE_COLUMNS:
            finite = np.isfinite(v)
            v = v.copy()
            v[finite] = np.unwrap(v[finite])
        res = v[i0] * (1.0 - w) + v[i0 + 1] * w
        # exactly on a source sample: take it as is (also keeps values next to a NaN neighbour)
        on = w == 0.0
        res[on] = v[i0][on]
        on1 = w == 1.0
        res[on1] = v[i0 + 1][on1]
        if name in ANGLE_COLUMNS:
            res = (res + np.pi) % (2 * np.pi) - np.pi
        out[name] = res
    return grid, out
