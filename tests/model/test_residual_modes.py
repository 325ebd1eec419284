"""How the residual model's K modes are taken from its K = 1 forecast and its scored heads."""

from __future__ import annotations

import numpy as np

from logpipe.model.residual.modes import MODE_GAP_M, spread_modes


def _straight(end_x: float, end_y: float = 0.0, steps: int = 30) -> np.ndarray:
    """(T, 2) a straight track from the origin to (end_x, end_y)."""
    return np.linspace(0.0, 1.0, steps)[:, None] * np.array([end_x, end_y])


def test_heads_ending_near_a_taken_mode_give_way_to_the_next_scored_head() -> None:
    first = _straight(30.0)[None]
    # In score order: a head 0.3 m from mode 0, one 5 m to the left, one 0.5 m from that, one 5 m to the right.
    heads = np.stack([_straight(30.3), _straight(30.0, 5.0), _straight(30.0, 5.5), _straight(30.0, -5.0)])[None]
    picked = spread_modes(first, heads, 3)
    np.testing.assert_array_equal(picked[0, 0], first[0])
    np.testing.assert_array_equal(picked[0, 1], heads[0, 1])
    np.testing.assert_array_equal(picked[0, 2], heads[0, 3])  # the two near-duplicates are skipped
    # Asked for every forecast: the skipped heads follow, in score order.
    everything = spread_modes(first, heads, 5)
    np.testing.assert_array_equal(everything[0, 3], heads[0, 0])
    np.testing.assert_array_equal(everything[0, 4], heads[0, 2])


def test_spread_heads_keep_score_order_and_short_sets_repeat_mode_0() -> None:
    rng = np.random.default_rng(0)
    first = rng.normal(size=(4, 30, 2))
    heads = first[:, None] + 10.0 * np.arange(1, 7)[None, :, None, None]  # every end >= 10 m from the others
    np.testing.assert_array_equal(spread_modes(first, heads, 6)[:, 1:], heads[:, :5])
    padded = spread_modes(first, heads, 9)
    assert padded.shape == (4, 9, 30, 2)
    np.testing.assert_array_equal(padded[:, 7], first)
    np.testing.assert_array_equal(padded[:, 8], first)
    # Without a gap the heads come in plain score order, duplicates and all.
    close = first[:, None] + 0.01 * np.arange(1, 7)[None, :, None, None]
    np.testing.assert_array_equal(spread_modes(first, close, 4, gap_m=0.0)[:, 1:], close[:, :3])
    assert MODE_GAP_M > 0


def test_one_mode_is_mode_0_alone() -> None:
    first = _straight(20.0)[None]
    heads = np.stack([_straight(25.0), _straight(15.0)])[None]
    np.testing.assert_array_equal(spread_modes(first, heads, 1), first[:, None])
