"""Closed-form checks of the metric conventions in ``logpipe.scoring.metrics``."""

from __future__ import annotations

import numpy as np
import pytest

from logpipe.scoring import metrics


def _line(n: int, t: int, v: tuple[float, float], start: tuple[float, float] = (0.0, 0.0)) -> np.ndarray:
    """(n, t, 2) straight lines from ``start`` at ``v`` metres per step (steps 1..t)."""
    k = np.arange(1, t + 1, dtype=np.float64)[:, None]
    return np.broadcast_to(np.asarray(start) + k * np.asarray(v), (n, t, 2)).copy()


def test_stationary_and_perfect_forecasts_score_zero() -> None:
    truth = np.zeros((3, 12, 2))
    err = metrics.displacement_errors(truth[:, None].repeat(4, axis=1), truth)
    for scores in (metrics.best_of_k_per_agent(err), metrics.argoverse(err),
                   metrics.best_of_k_joint(err, np.array([0, 0, 1]))):
        assert np.all(scores.ade == 0.0) and np.all(scores.fde == 0.0)
    assert not metrics.miss(metrics.argoverse(err).fde).any()


def test_constant_offset_gives_its_length_everywhere() -> None:
    truth = _line(2, 12, (0.5, 0.2))
    pred = (truth + np.array([3.0, 4.0]))[:, None]  # 5 m off at every step
    err = metrics.displacement_errors(pred, truth)
    assert err.shape == (2, 1, 12)
    np.testing.assert_allclose(metrics.ade_per_mode(err), 5.0)
    np.testing.assert_allclose(metrics.fde_per_mode(err), 5.0)
    np.testing.assert_allclose(metrics.error_by_step(err, np.zeros(2, np.int64)), np.full(12, 5.0))
    assert metrics.miss(metrics.argoverse(err).fde).all()


def test_wrong_speed_on_a_straight_line_grows_linearly() -> None:
    # Truth moves 1.0 m/step along x; the forecast 0.8 m/step: error at step k is 0.2 k metres.
    t = 12
    truth = _line(1, t, (1.0, 0.0))
    pred = _line(1, t, (0.8, 0.0))[:, None]
    err = metrics.displacement_errors(pred, truth)
    np.testing.assert_allclose(err[0, 0], 0.2 * np.arange(1, t + 1))
    best = metrics.best_of_k_per_agent(err)
    assert best.ade[0] == pytest.approx(0.2 * (t + 1) / 2)  # mean of 0.2 * (1..T)
    assert best.fde[0] == pytest.approx(0.2 * t)


def test_per_agent_min_ade_and_min_fde_may_come_from_different_modes_argoverse_may_not() -> None:
    t = 4
    truth = np.zeros((1, t, 2))
    # mode 0: 1 m off at steps 1-3, 3 m at the end (ADE 1.5, FDE 3); mode 1: 2 m off everywhere (ADE 2, FDE 2).
    m0 = np.array([[1.0, 0], [1.0, 0], [1.0, 0], [3.0, 0]])
    m1 = np.full((t, 2), [0.0, 2.0])
    err = metrics.displacement_errors(np.stack([m0, m1])[None], truth)
    per_agent = metrics.best_of_k_per_agent(err)
    assert per_agent.ade[0] == pytest.approx(1.5) and per_agent.fde[0] == pytest.approx(2.0)
    assert per_agent.mode[0] == 0
    argo = metrics.argoverse(err)  # lowest FDE is mode 1: its ADE (2.0) is reported, not the min ADE (1.5)
    assert argo.mode[0] == 1 and argo.ade[0] == pytest.approx(2.0) and argo.fde[0] == pytest.approx(2.0)
    assert not metrics.miss(argo.fde)[0]  # exactly 2.0 m is not a miss (strictly greater)
    assert metrics.miss(argo.fde, 1.9)[0]
    k1 = metrics.best_of_k_per_agent(metrics.top_k(err, 1))
    assert k1.ade[0] == pytest.approx(1.5) and k1.fde[0] == pytest.approx(3.0)


def test_joint_best_of_k_picks_one_mode_per_sample() -> None:
    t = 3
    truth = np.zeros((2, t, 2))
    pred = np.zeros((2, 2, t, 2))
    pred[0, 1] += [1.0, 0.0]  # agent 0: mode 0 perfect, mode 1 1 m off
    pred[1, 0] += [0.0, 2.0]  # agent 1: mode 0 2 m off, mode 1 perfect
    err = metrics.displacement_errors(pred, truth)
    per_agent = metrics.best_of_k_per_agent(err)
    np.testing.assert_allclose(per_agent.ade, [0.0, 0.0])
    # Same sample: summed ADE is 2 for mode 0 and 1 for mode 1, so mode 1 for both agents.
    joint = metrics.best_of_k_joint(err, np.array([7, 7]))
    np.testing.assert_allclose(joint.ade, [1.0, 0.0])
    np.testing.assert_allclose(joint.fde, [1.0, 0.0])
    # Different samples: the joint choice is per agent again.
    separate = metrics.best_of_k_joint(err, np.array([0, 1]))
    np.testing.assert_allclose(separate.ade, [0.0, 0.0])


def test_horizon_curve_averages_to_ade_and_shapes_are_checked() -> None:
    rng = np.random.default_rng(3)
    truth = rng.normal(size=(5, 12, 2))
    pred = truth[:, None] + rng.normal(size=(5, 6, 12, 2))
    err = metrics.displacement_errors(pred, truth)
    best = metrics.best_of_k_per_agent(err)
    assert metrics.error_by_step(err, best.mode).mean() == pytest.approx(best.ade.mean())
    assert np.all(metrics.best_of_k_per_agent(metrics.top_k(err, 6)).ade
                  <= metrics.best_of_k_per_agent(metrics.top_k(err, 1)).ade)
    with pytest.raises(ValueError, match="shapes"):
        metrics.displacement_errors(pred, truth[:, :11])
    with pytest.raises(ValueError, match="modes"):
        metrics.top_k(err, 7)


def test_paired_interval_of_a_constant_difference_is_that_constant() -> None:
    got = metrics.paired_difference_interval(np.full(30, -0.25), np.arange(30) // 3)
    assert (got.mean, got.low, got.high, got.agents, got.clusters) == (-0.25, -0.25, -0.25, 30, 10)


def test_paired_interval_covers_the_true_mean_and_widens_with_clustering() -> None:
    rng = np.random.default_rng(7)
    covered = 0
    for trial in range(200):
        diff = rng.normal(0.1, 1.0, 60)
        got = metrics.paired_difference_interval(diff, np.arange(60), resamples=500, seed=trial)
        assert got.low <= got.mean <= got.high and got.mean == pytest.approx(diff.mean())
        covered += got.low <= 0.1 <= got.high
    assert 0.88 <= covered / 200 <= 0.99  # a 95 % interval
    # Ten agents per cluster sharing one value carry the information of one agent each: treated as clusters the
    # interval is about sqrt(10) times wider than if every agent counted on its own.
    shared = np.repeat(rng.normal(0.0, 1.0, 40), 10)
    clustered = metrics.paired_difference_interval(shared, np.arange(400) // 10)
    naive = metrics.paired_difference_interval(shared, np.arange(400))
    ratio = (clustered.high - clustered.low) / (naive.high - naive.low)
    assert 2.5 < ratio < 4.0


def test_paired_interval_rejects_mismatched_input() -> None:
    with pytest.raises(ValueError, match="diff"):
        metrics.paired_difference_interval(np.zeros(3), np.zeros(4, dtype=np.int64))
    with pytest.raises(ValueError, match="diff"):
        metrics.paired_difference_interval(np.zeros(0), np.zeros(0, dtype=np.int64))
