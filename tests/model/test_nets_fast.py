"""``TrajectoryNet.decode_fast`` (the inference path) equals ``decode`` (the reference) up to float rounding."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import torch

from logpipe.model.synthetic import make_scene
from logpipe.model.zhu2020.batching import collate
from logpipe.model.zhu2020.config import ConfigError, Features, ModelConfig
from logpipe.model.zhu2020.network import TrajectoryNet
from logpipe.types import SceneSample

SMALL = {"embed_dim": 8, "gru_dim": 12, "lstm_dim": 8, "obs_len": 4, "pred_len": 5, "raster_channels": 2}


def _scenes() -> list[SceneSample]:
    scenes = [make_scene(np.random.default_rng(i), n, 4, 5, channels=2, size=64, with_ego=i % 2 == 0,
                         with_raster=i != 1) for i, n in enumerate((5, 2, 7, 1, 4))]
    # A scene with nobody observed at the current step: nothing of it is decoded, its pools are empty.
    gone = scenes[3]
    gone.positions = gone.positions.copy()
    gone.positions[:, 3] = np.nan
    # An agent missing at the current step in a busy scene.
    scenes[2].positions = scenes[2].positions.copy()
    scenes[2].positions[4, 3] = np.nan
    return scenes


@pytest.mark.parametrize(
    "features",
    [
        Features(),
        Features(True, True, False, False, False),
        Features(False, False, False, False, False),
        Features(False, False, False, True, False),
        Features(True, False, True, False, True),
        Features(False, True, False, False, True),
    ],
)
@pytest.mark.parametrize("step_output", ["displacement", "velocity_change", "agent_velocity_change"])
@pytest.mark.parametrize("mode_gate", [False, True])
def test_decode_fast_equals_decode(features: Features, step_output: str, mode_gate: bool) -> None:
    torch.manual_seed(0)
    cfg = ModelConfig(features=features, noise_dim=3, step_output=step_output, mode_gate=mode_gate,  # type: ignore[arg-type]
                      **SMALL)
    net = TrajectoryNet(cfg).eval()
    batch = collate(_scenes(), cfg)
    with torch.no_grad():
        enc = net.encode(batch)
        noise = torch.randn(4, int(batch.active.sum()), 3)
        ref = net.decode(batch, enc, noise)
        fast = net.decode_fast(batch, enc, noise)
    assert torch.equal(ref.rows, fast.rows)
    assert fast.positions.shape == ref.positions.shape
    torch.testing.assert_close(fast.positions, ref.positions, rtol=1e-5, atol=1e-5)


@pytest.mark.parametrize("step_output", ["velocity_change", "agent_velocity_change"])
@pytest.mark.parametrize("fast", [False, True])
@pytest.mark.parametrize("silenced", ["output", "mode_gate"])
def test_velocity_change_with_zero_output_is_constant_velocity(fast: bool, step_output: str, silenced: str) -> None:
    """With o_t = 0 (a zero output layer, or a random one behind a closed mode gate) the decoder carries the last
    observed displacement on (and stands still where the step before the current one is unobserved), whatever
    the noise."""
    torch.manual_seed(0)
    cfg = ModelConfig(noise_dim=3, step_output=step_output, mode_gate=silenced == "mode_gate", **SMALL)  # type: ignore[arg-type]
    net = TrajectoryNet(cfg).eval()
    with torch.no_grad():
        if net.mode_gate is not None:
            net.mode_gate.weight.zero_()
            net.mode_gate.bias.fill_(-40.0)
        else:
            net.out.weight.zero_()
            net.out.bias.zero_()
    scenes = _scenes()
    scenes[0].positions = scenes[0].positions.copy()
    scenes[0].positions[1, 2] = np.nan  # agent 1 of scene 0: p_(T_obs - 1) unobserved
    batch = collate(scenes, cfg)
    with torch.no_grad():
        pred = net(batch, 3, fast=fast)
    pos = batch.positions[pred.rows]
    last, before = pos[:, 3], pos[:, 2]
    step = torch.where(batch.valid[pred.rows, 2][:, None], last - before, torch.zeros_like(last))
    horizon = torch.arange(1, 6, dtype=last.dtype)
    expected = last[:, None] + horizon[None, :, None] * step[:, None]
    agents = ~batch.ego[pred.rows]  # the ego follows its given future instead
    for mode in range(3):
        torch.testing.assert_close(pred.positions[mode][agents], expected[agents], rtol=0, atol=1e-5)
    assert bool((~batch.valid[pred.rows, 2] & agents).any())


@pytest.mark.parametrize("fast", [False, True])
def test_an_open_mode_gate_passes_the_output_through(fast: bool) -> None:
    """A gate saturated open gives the forecasts of the same weights without a gate: it only scales o_t."""
    torch.manual_seed(0)
    plain = TrajectoryNet(ModelConfig(noise_dim=3, step_output="agent_velocity_change", **SMALL)).eval()
    gated = TrajectoryNet(ModelConfig(noise_dim=3, step_output="agent_velocity_change", mode_gate=True, **SMALL)).eval()
    missing = gated.load_state_dict(plain.state_dict(), strict=False).missing_keys
    assert sorted(missing) == ["mode_gate.bias", "mode_gate.weight"]
    with torch.no_grad():
        assert gated.mode_gate is not None
        gated.mode_gate.weight.zero_()
        gated.mode_gate.bias.fill_(40.0)
    batch = collate(_scenes(), plain.config)
    with torch.no_grad():
        ref = plain(batch, 3, torch.Generator().manual_seed(1), fast=fast)
        out = gated(batch, 3, torch.Generator().manual_seed(1), fast=fast)
    torch.testing.assert_close(out.positions, ref.positions, rtol=0, atol=1e-6)


@pytest.mark.parametrize("mode_gate", [False, True])
@pytest.mark.parametrize("fast", [False, True])
def test_constant_velocity_modes_hold_the_first_modes_and_leave_the_rest(fast: bool, mode_gate: bool) -> None:
    """constant_velocity_modes = 2 of 4: modes 0-1 carry the last observed step on (what a closed gate gives),
    modes 2-3 are the forecasts without the setting (same noise)."""
    torch.manual_seed(0)
    cfg = ModelConfig(noise_dim=3, step_output="agent_velocity_change", mode_gate=mode_gate, **SMALL)
    net = TrajectoryNet(cfg).eval()
    batch = collate(_scenes(), cfg)
    with torch.no_grad():
        ref = net(batch, 4, torch.Generator().manual_seed(1), fast=fast)
        held = net(batch, 4, torch.Generator().manual_seed(1), fast=fast, constant_velocity_modes=2)
    pos = batch.positions[held.rows]
    last, before = pos[:, 3], pos[:, 2]
    step = torch.where(batch.valid[held.rows, 2][:, None], last - before, torch.zeros_like(last))
    expected = last[:, None] + torch.arange(1, 6, dtype=last.dtype)[None, :, None] * step[:, None]
    agents = ~batch.ego[held.rows]
    for mode in (0, 1):
        torch.testing.assert_close(held.positions[mode][agents], expected[agents], rtol=0, atol=1e-5)
        assert not torch.allclose(ref.positions[mode][agents], expected[agents], atol=1e-3)
    torch.testing.assert_close(held.positions[2:], ref.positions[2:], rtol=0, atol=1e-6)


@pytest.mark.parametrize("fast", [False, True])
def test_configured_constant_velocity_modes_are_the_default_and_leave_one_mode_learned(fast: bool) -> None:
    """ModelConfig.constant_velocity_modes is what a forward pass without the argument holds (training's
    path), an explicit 0 overrides it, and a single draw (K = 1) stays the network's own."""
    torch.manual_seed(0)
    plain = TrajectoryNet(ModelConfig(noise_dim=3, step_output="agent_velocity_change", **SMALL)).eval()
    held = TrajectoryNet(ModelConfig(noise_dim=3, step_output="agent_velocity_change", constant_velocity_modes=2,
                                     **SMALL)).eval()
    held.load_state_dict(plain.state_dict())
    batch = collate(_scenes(), plain.config)

    def run(net: TrajectoryNet, k: int, **kw: int) -> torch.Tensor:
        with torch.no_grad():
            return net(batch, k, torch.Generator().manual_seed(1), fast=fast, **kw).positions

    torch.testing.assert_close(run(held, 4), run(plain, 4, constant_velocity_modes=2), rtol=0, atol=0)
    torch.testing.assert_close(run(held, 4, constant_velocity_modes=0), run(plain, 4), rtol=0, atol=0)
    torch.testing.assert_close(run(held, 2), run(plain, 2, constant_velocity_modes=1), rtol=0, atol=0)
    torch.testing.assert_close(run(held, 1), run(plain, 1), rtol=0, atol=0)


def test_configured_constant_velocity_modes_are_checked() -> None:
    with pytest.raises(ConfigError, match="velocity-change step_output"):
        ModelConfig(constant_velocity_modes=1)
    with pytest.raises(ConfigError, match="must be >= 0"):
        ModelConfig(step_output="velocity_change", constant_velocity_modes=-1)


def test_constant_velocity_modes_are_checked() -> None:
    batch = collate(_scenes(), ModelConfig(noise_dim=3, **SMALL))
    with pytest.raises(ConfigError, match="velocity-change step_output"):
        TrajectoryNet(ModelConfig(noise_dim=3, **SMALL)).eval()(batch, 4, constant_velocity_modes=1)
    net = TrajectoryNet(ModelConfig(noise_dim=3, step_output="velocity_change", **SMALL)).eval()
    with pytest.raises(ConfigError, match=r"must be in 0\.\.4"):
        net(batch, 4, fast=True, constant_velocity_modes=5)


@pytest.mark.parametrize("fast", [False, True])
def test_agent_velocity_change_reads_the_output_in_each_agents_frame(fast: bool) -> None:
    """A constant o = (along, across) bends every agent's first step by that fraction of its own last step,
    along and to the left of it, whatever its heading; an agent slower than the floor moves by the floor."""
    torch.manual_seed(0)
    cfg = ModelConfig(noise_dim=3, step_output="agent_velocity_change", agent_min_step_m=0.05, **SMALL)  # type: ignore[arg-type]
    net = TrajectoryNet(cfg).eval()
    along, across = -0.2, 0.3
    with torch.no_grad():
        net.out.weight.zero_()
        net.out.bias.copy_(torch.tensor([along, across]))
    scenes = _scenes()
    scenes[0].positions = scenes[0].positions.copy()
    scenes[0].positions[1, 3] = scenes[0].positions[1, 2] + np.array([0.0, 0.01])  # agent 1: 1 cm, below the floor
    batch = collate(scenes, cfg)
    with torch.no_grad():
        pred = net(batch, 2, fast=fast)
    pos = batch.positions[pred.rows]
    step = pos[:, 3] - pos[:, 2]
    agents = ~batch.ego[pred.rows] & batch.valid[pred.rows, 2]
    length = torch.linalg.vector_norm(step, dim=-1, keepdim=True)
    unit = step / length
    left = torch.stack((-unit[:, 1], unit[:, 0]), dim=-1)
    expected = pos[:, 3] + step + length.clamp(min=0.05) * (along * unit + across * left)
    for mode in range(2):
        torch.testing.assert_close(pred.positions[mode, :, 0][agents], expected[agents], rtol=0, atol=1e-5)
    assert bool((length[:, 0] < 0.05)[agents].any()) and bool((length[:, 0] > 0.05)[agents].any())


def test_decode_fast_row_blocks_do_not_change_results(monkeypatch: pytest.MonkeyPatch) -> None:
    from logpipe.model.zhu2020 import fast_decoder

    torch.manual_seed(0)
    cfg = ModelConfig(noise_dim=3, **SMALL)  # type: ignore[arg-type]
    net = TrajectoryNet(cfg).eval()
    batch = collate(_scenes(), cfg)
    with torch.no_grad():
        enc = net.encode(batch)
        noise = torch.randn(3, int(batch.active.sum()), 3)
        whole = net.decode_fast(batch, enc, noise).positions
        monkeypatch.setattr(fast_decoder, "_LSTM_CHUNK_ROWS", 5)
        blocks = net.decode_fast(batch, enc, noise).positions
    torch.testing.assert_close(blocks, whole, rtol=1e-6, atol=1e-6)


def test_environment_lookup_is_bag_order_independent() -> None:
    """The agent-major bag order gives the same v as looking each mode up on its own."""
    torch.manual_seed(0)
    cfg = ModelConfig(**SMALL)  # type: ignore[arg-type]
    net = TrajectoryNet(cfg).eval()
    assert net.env is not None
    batch = collate(_scenes(), cfg)
    rows = batch.active.nonzero().squeeze(1)
    with torch.no_grad():
        enc = net.encode(batch)
        assert enc.proj is not None
        pos = batch.positions[rows, 3][None] + torch.randn(3, len(rows), 2) * 5
        together = net.env(enc.proj, pos, batch, rows)
        for m in range(3):
            torch.testing.assert_close(together[m : m + 1], net.env(enc.proj, pos[m : m + 1], batch, rows))


@pytest.mark.parametrize("fast", [False, True])
def test_without_interaction_while_decoding_a_neighbours_noise_does_not_reach_a_forecast(fast: bool) -> None:
    """Redrawing the noise of every agent but one changes that agent's forecast through the predicted-step pools
    of eqs. 2 and 4 (the paper), and not at all when the decoder reads the AIN as observed."""
    torch.manual_seed(0)
    for during, changes in ((True, True), (False, False)):
        cfg = ModelConfig(features=Features(True, True, False, False, False), noise_dim=3,
                          step_output="agent_velocity_change", interaction_while_decoding=during, **SMALL)
        net = TrajectoryNet(cfg).eval()
        batch = collate(_scenes()[:1], cfg)
        r = int(batch.active.sum())
        assert r >= 3
        noise = torch.randn(4, r, 3)
        other = noise.clone()
        other[:, 1:] = torch.randn(4, r - 1, 3)  # every agent's noise but row 0's redrawn
        with torch.no_grad():
            enc = net.encode(batch)
            decode = net.decode_fast if fast else net.decode
            first, second = decode(batch, enc, noise).positions[:, 0], decode(batch, enc, other).positions[:, 0]
            if not during:
                torch.testing.assert_close(net.decode_fast(batch, enc, noise).positions,
                                           net.decode(batch, enc, noise).positions, rtol=1e-5, atol=1e-5)
        assert (not torch.allclose(first, second, atol=1e-6)) is changes


def test_without_an_ain_holding_it_while_decoding_changes_nothing() -> None:
    """Noise-LSTM has no fst^(t) to hold: the same weights give the same forecasts either way, and
    ``ModelConfig.effective`` calls the two configs one recipe (while the paper's method's differ)."""
    torch.manual_seed(0)
    base = ModelConfig(features=Features(False, False, False, False, False), noise_dim=3,
                       step_output="agent_velocity_change", **SMALL)
    held = replace(base, interaction_while_decoding=False)
    paper, mine = TrajectoryNet(base).eval(), TrajectoryNet(held).eval()
    mine.load_state_dict(paper.state_dict())
    batch = collate(_scenes(), base)
    noise = torch.randn(4, int(batch.active.sum()), 3)
    with torch.no_grad():
        torch.testing.assert_close(mine.decode(batch, mine.encode(batch), noise).positions,
                                   paper.decode(batch, paper.encode(batch), noise).positions, rtol=0, atol=0)
    assert held.effective() == base.effective() == base
    full = ModelConfig(features=Features(True, True, False, False, False), **SMALL)
    assert replace(full, interaction_while_decoding=False).effective() != full.effective()
