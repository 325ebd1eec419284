"""The social baselines' faster training code computes what the direct forms compute (issue 63, round two): Social-
LSTM's occupied-cells pooling against the dense social tensor, and Social-GAN's select-then-backprop variety loss
against backpropagating through all ``best_k`` samples: same outputs, same gradients, on small scenes."""

from __future__ import annotations

import copy

import numpy as np
import torch

from benchmarks.bench_social import direct_embedded_social_tensor, direct_generator_step, synthetic_tracks
from logpipe.model.social_gan.config import preset_config
from logpipe.model.social_gan.fit import Gan, generator_step
from logpipe.model.social_lstm.config import SocialLstmConfig
from logpipe.model.social_lstm.net import SocialLstm, embedded_social_tensor, grid_cells
from logpipe.model.training.social_batch import stack, within_pairs


def test_the_occupied_cells_pooling_equals_the_dense_social_tensor_and_its_gradients() -> None:
    torch.manual_seed(0)
    config = SocialLstmConfig(obs_len=8, pred_len=12)
    net = SocialLstm(config)
    starts = np.array([0, 6, 13, 14, 40])  # a lone agent, and a crowd of 26 on a 3 m square
    pair_i, pair_j = (torch.from_numpy(a) for a in within_pairs(starts))
    positions = torch.rand(40, 2) * 3
    _, inside = grid_cells(positions[pair_j] - positions[pair_i], config.neighbourhood_m, config.grid_size)
    assert 20 < int((inside & (pair_i != pair_j)).sum()) < 40 * 39  # some neighbours in the grid, not all
    hidden = torch.randn(40, config.hidden_dim, requires_grad=True)
    layer = net.social_embedding
    wrt = [hidden, layer.weight, layer.bias]
    fast = embedded_social_tensor(hidden, positions, pair_i, pair_j, config, layer)
    direct = direct_embedded_social_tensor(hidden, positions, pair_i, pair_j, config, layer)
    upstream = torch.randn_like(direct)
    fast_grads = torch.autograd.grad(fast, wrt, upstream)
    direct_grads = torch.autograd.grad(direct, wrt, upstream)
    torch.testing.assert_close(fast, direct, rtol=1e-5, atol=1e-5)
    assert torch.equal(fast[13], layer.bias)  # the lone agent pools nothing
    for a, b in zip(fast_grads, direct_grads, strict=True):
        torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-5)
    assert fast_grads[0].abs().sum() > 0


def test_select_then_backprop_gives_the_variety_losss_value_and_gradients() -> None:
    for preset in ("social_gan_20v", "social_gan_20vp"):
        torch.manual_seed(1)
        gan = Gan.new(preset_config(preset))
        twin = copy.deepcopy(gan)
        batch = stack(synthetic_tracks(6, seed=3))
        torch.manual_seed(7)  # the same noise and label draws for both
        fast = generator_step(gan, batch)
        torch.manual_seed(7)
        direct = direct_generator_step(twin, batch)
        assert np.allclose(fast, direct, rtol=1e-5), (preset, fast, direct)
        for (name, a), b in zip(gan.generator.named_parameters(), twin.generator.parameters(), strict=True):
            assert a.grad is not None and b.grad is not None
            torch.testing.assert_close(a.grad, b.grad, rtol=1e-4, atol=1e-6, msg=f"{preset}: {name}")
            # Adam's first step is ~lr x sign(grad): compared where the gradient is above rounding (a bias before a
            # batch norm has none: the norm removes it)
            clear = b.grad.abs() > 1e-6
            torch.testing.assert_close(a[clear], b[clear], rtol=1e-4, atol=1e-5, msg=f"{preset}: {name} updated")
        assert any(float(p.grad.abs().sum()) > 0 for p in gan.generator.decoder.parameters() if p.grad is not None)
