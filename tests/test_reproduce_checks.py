"""The validation-only checks of scripts/reproduce_ethucy.py, on a bundled real ETH/UCY file."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "scripts"))

from reproduce_ethucy import FRAME_RATE_SHIFT, rate_shifted_text  # noqa: E402

ZARA = REPO / "tests" / "data" / "ethucy" / "eth" / "train" / "crowds_zara01_train.txt"


def _rows(text: str) -> np.ndarray:
    return np.array([[float(v) for v in line.split("\t")] for line in text.splitlines()])


def test_rate_shift_by_one_keeps_every_row() -> None:
    src = np.loadtxt(ZARA, ndmin=2)
    out = _rows(rate_shifted_text(ZARA, factor=1.0))
    order = np.lexsort((src[:, 1], src[:, 0]))
    np.testing.assert_allclose(out, src[order], atol=5e-5)


def test_rate_shift_interpolates_each_track_on_the_longer_step() -> None:
    src = np.loadtxt(ZARA, ndmin=2)
    out = _rows(rate_shifted_text(ZARA))
    step_s = 0.4 * FRAME_RATE_SHIFT
    checked = 0
    for ped in np.unique(src[:, 1])[:20]:
        track = src[src[:, 1] == ped]
        mine = out[out[:, 1] == ped]
        if len(mine) == 0:  # shorter than one new step: nothing on the new grid
            assert (track[-1, 0] - track[0, 0]) * 0.04 < 2 * step_s
            continue
        # independent: the new step k sits at k x step_s on the recording's clock, 10 frames per new step
        t_new = mine[:, 0] / 10 * step_s
        t_src = track[:, 0] * 0.04
        assert t_new[0] >= t_src[0] - 1e-6 and t_new[-1] <= t_src[-1] + 1e-6
        np.testing.assert_allclose(mine[:, 2], np.interp(t_new, t_src, track[:, 2]), atol=2e-3)
        np.testing.assert_allclose(mine[:, 3], np.interp(t_new, t_src, track[:, 3]), atol=2e-3)
        assert np.all(np.diff(mine[:, 0]) == 10)
        checked += 1
    assert checked >= 10
    assert len(out) == pytest.approx(len(src) / FRAME_RATE_SHIFT, rel=0.1)
