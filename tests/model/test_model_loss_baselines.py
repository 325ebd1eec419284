"""Eq. 23 (value and gradient routing), metrics, and the classical baselines."""

from __future__ import annotations

import numpy as np
import torch

from logpipe.model.kinematic.constant_velocity import ConstantVelocity, ConstantVelocitySampler, LinearFit
from logpipe.model.kinematic.kalman import KalmanCV
from logpipe.model.predictor import Predictor
from logpipe.model.synthetic import make_scene
from logpipe.model.training.loss import DisplacementErrors, best_of_h_loss
from logpipe.types import SceneSample


def test_best_of_h_loss_value_hand_computed() -> None:
    truth = torch.zeros(3, 1, 2)  # rows 0, 1 in scene 0; row 2 in scene 1; T = 1
    pred = torch.tensor([[[[1.0, 0.0]], [[0.0, 1.0]], [[2.0, 0.0]]], [[[0.0, 0.0]], [[0.0, 3.0]], [[1.0, 0.0]]]])
    mask = torch.tensor([True, True, True])
    scene = torch.tensor([0, 0, 1])
    loss, best = best_of_h_loss(pred, truth, mask, scene, 2)
    # scene 0: mode 0 -> 1 + 1 = 2, mode 1 -> 0 + 9 = 9 -> 2; scene 1: mode 0 -> 4, mode 1 -> 1 -> 1
    assert best.tolist() == [0, 1]
    torch.testing.assert_close(loss, torch.tensor(3.0 / 3.0))
    loss_a, best_a = best_of_h_loss(pred, truth, mask, scene, 2, reduce="agent")
    assert best_a.tolist() == [1, 0, 1]
    torch.testing.assert_close(loss_a, torch.tensor((0.0 + 1.0 + 1.0) / 3.0))
    # masked rows contribute nothing: scene 0 is then mode 0 -> 1, mode 1 -> 0
    loss_m, best_m = best_of_h_loss(pred, truth, torch.tensor([True, False, True]), scene, 2)
    assert best_m.tolist() == [1, 1]
    torch.testing.assert_close(loss_m, torch.tensor((0.0 + 1.0) / 2.0))


def test_best_of_h_loss_backpropagates_only_through_best_mode() -> None:
    torch.manual_seed(0)
    pred = torch.randn(5, 4, 6, 2, requires_grad=True)
    truth = torch.randn(4, 6, 2)
    scene = torch.tensor([0, 0, 1, 1])
    loss, best = best_of_h_loss(pred, truth, torch.ones(4, dtype=torch.bool), scene, 2)
    loss.backward()
    assert pred.grad is not None
    for s in range(2):
        rows = scene == s
        nonzero_modes = (pred.grad[:, rows].abs().sum(dim=(1, 2, 3)) > 0).nonzero().flatten().tolist()
        assert nonzero_modes == [int(best[s])]


def test_displacement_errors_best_of_k() -> None:
    truth = torch.zeros(1, 2, 2)
    pred = torch.tensor([[[[3.0, 4.0], [3.0, 4.0]]], [[[0.0, 1.0], [0.0, 2.0]]]])  # (M=2, R=1, T=2, 2)
    err = DisplacementErrors()
    err.add(pred, truth, torch.tensor([True]))
    assert err.count == 1
    assert abs(err.ade - 1.5) < 1e-9 and abs(err.fde - 2.0) < 1e-9


def _line(n: int = 3, obs: int = 8, pred: int = 12) -> SceneSample:
    s = make_scene(np.random.default_rng(0), n, obs, pred)
    t = np.arange(obs + pred, dtype=np.float64)
    start = np.array([[1.0, 2.0], [-5.0, 0.0], [3.0, 3.0]])[:n]
    vel = np.array([[0.4, 0.1], [0.0, -1.2], [0.7, 0.7]])[:n]
    s.positions = start[:, None] + vel[:, None] * t[None, :, None]
    return s


def test_constant_velocity_and_linear_exact_on_a_straight_line() -> None:
    s = _line()
    for method in (ConstantVelocity(pred_len=12), LinearFit(pred_len=12)):
        assert isinstance(method, Predictor)
        out = method.predict([s], 3, seed=0)[0]
        assert out.shape == (3, 3, 12, 2)
        np.testing.assert_allclose(out, np.repeat(s.positions[:, None, 8:], 3, axis=1), atol=1e-9)


def test_linear_fit_is_least_squares_with_gaps() -> None:
    s = _line()
    s.positions[0, [1, 4]] = np.nan  # gaps do not bias a line fit
    noisy = _line()
    noisy.positions[1, :8] += np.array([0.3, -0.3, 0.3, -0.3, 0.3, -0.3, 0.3, -0.3])[:, None]
    out = LinearFit().predict([s, noisy], 1, 0)
    np.testing.assert_allclose(out[0][0, 0], s.positions[0, 8:], atol=1e-9)
    t = np.arange(8.0)
    coef = np.polyfit(t, noisy.positions[1, :8, 1], 1)
    np.testing.assert_allclose(out[1][1, 0, :, 1], np.polyval(coef, np.arange(8.0, 20.0)), atol=1e-9)


def test_kalman_close_on_a_straight_line() -> None:
    s = _line()
    out = KalmanCV().predict([s], 2, seed=0)[0]
    err = np.linalg.norm(out[:, 0] - s.positions[:, 8:], axis=-1)
    assert err.max() < 0.1
    assert err.mean() > 0  # it is a filter, not an oracle
    np.testing.assert_array_equal(out[:, 0], out[:, 1])


def test_cv_sampler_spread_and_seed() -> None:
    s = _line()
    sampler = ConstantVelocitySampler(heading_std_rad=0.2, speed_std_frac=0.1, include_unperturbed=True)
    a = sampler.predict([s], 50, seed=1)[0]
    b = sampler.predict([s], 50, seed=1)[0]
    np.testing.assert_array_equal(a, b)
    cv = ConstantVelocity().predict([s], 1, 0)[0][:, 0]
    np.testing.assert_allclose(a[:, 0], cv, atol=1e-9)  # mode 0 unperturbed
    assert not np.allclose(a, sampler.predict([s], 50, seed=2)[0])
    # heading spread ~ the configured std on the final displacement direction
    d = a[:, 1:, -1] - s.positions[:, None, 7]
    ang = (
        np.arctan2(d[..., 1], d[..., 0])
        - np.arctan2(cv[:, -1, 1] - s.positions[:, 7, 1], cv[:, -1, 0] - s.positions[:, 7, 0])[:, None]
    )
    ang = (ang + np.pi) % (2 * np.pi) - np.pi
    assert 0.12 < ang.std() < 0.3
