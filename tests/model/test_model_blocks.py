"""Each equation's block against a small hand computation, and the backbone / ROIAlign."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
from safetensors.torch import save_file

from logpipe.model.synthetic import make_scene
from logpipe.model.zhu2020.backbone import BackboneWeightsError, ResNet18Stages12, read_state_dict, roi_align
from logpipe.model.zhu2020.batching import collate
from logpipe.model.zhu2020.config import Features, ModelConfig
from logpipe.model.zhu2020.encoder import attention_q
from logpipe.model.zhu2020.interaction import (
    AgentInteractionNet,
    EgoMotionFeature,
    EgoTrajectoryFeature,
    PositionFeature,
    TrackingFeature,
    scene_max,
)
from logpipe.model.zhu2020.network import TrajectoryNet

SMALL = {"embed_dim": 8, "gru_dim": 12, "lstm_dim": 8, "noise_dim": 3, "obs_len": 4, "pred_len": 3}


def _batch_two_scenes() -> tuple[ModelConfig, object]:
    cfg = ModelConfig(features=Features(True, True, False, False, False), **SMALL)  # type: ignore[arg-type]
    rng = np.random.default_rng(0)
    scenes = [make_scene(rng, 3, 4, 3), make_scene(rng, 2, 4, 3)]
    return cfg, collate(scenes, cfg)


def _set(linear: torch.nn.Linear, weight: list[list[float]], bias: list[float]) -> None:
    with torch.no_grad():
        linear.weight.copy_(torch.tensor(weight))
        linear.bias.copy_(torch.tensor(bias))


def test_position_feature_eqs_1_2_hand_computed() -> None:
    _, batch = _batch_two_scenes()
    pf = PositionFeature(3)
    _set(pf.embed, [[1, 0], [0, 1], [1, 1]], [0, 0, 1])
    pos = torch.tensor([[[1.0, 5.0], [3.0, -1.0], [100.0, 100.0], [-2.0, 0.5], [0.0, -4.0]]])
    mask = torch.tensor([[True, True, False, True, True]])  # row 2 (scene 0) is masked out
    out = pf(pos, mask, batch, torch.arange(5))  # type: ignore[arg-type]
    # scene 0 rows 0, 1: e = (1, 5, 7), (3, -1, 3) -> max (3, 5, 7); scene 1 rows 3, 4: (-2, .5, -.5), (0, -4, -3)
    assert out.shape == (1, 2, 3)
    torch.testing.assert_close(out[0], torch.tensor([[3.0, 5.0, 7.0], [0.0, 0.5, -0.5]]))


def test_scene_max_empty_scene_is_zero_and_padding_never_wins() -> None:
    _, batch = _batch_two_scenes()
    x = torch.full((2, 5, 2), -5.0)
    mask = torch.tensor([[True, True, True, True, True], [True, True, True, False, False]])
    out = scene_max(x, mask, batch, torch.arange(5))  # type: ignore[arg-type]
    # scene 1 has 2 of A_max = 3 slots: its empty (zero-filled) slot must not beat -5
    torch.testing.assert_close(out[0], torch.tensor([[-5.0, -5.0], [-5.0, -5.0]]))
    # a scene with no participating row pools to 0
    torch.testing.assert_close(out[1], torch.tensor([[-5.0, -5.0], [0.0, 0.0]]))


def test_tracking_feature_eqs_3_4_hand_computed() -> None:
    _, batch = _batch_two_scenes()
    tf = TrackingFeature(2, 2)
    _set(tf.embed, [[2, 0], [0, -1]], [1, 0])
    h = torch.tensor([[[1.0, 1.0], [0.0, -3.0], [0.5, 0.0], [1.0, 2.0], [-1.0, 0.0]]])
    out = tf(h, torch.ones(1, 5, dtype=torch.bool), batch, torch.arange(5))  # type: ignore[arg-type]
    # scene 0: (3, -1), (1, 3), (2, 0) -> (3, 3); scene 1: (3, -2), (-1, 0) -> (3, 0)
    torch.testing.assert_close(out[0], torch.tensor([[3.0, 3.0], [3.0, 0.0]]))


def test_ego_motion_feature_eq_5() -> None:
    emf = EgoMotionFeature(2)
    _set(emf.embed, [[1, 2], [0, 1]], [0.5, 0])
    out = emf(torch.tensor([[1.0, -1.0], [2.0, 2.0]]), torch.tensor([True, False]))
    torch.testing.assert_close(out, torch.tensor([[-0.5, -1.0], [0.0, 0.0]]))


def test_ego_trajectory_feature_eqs_8_9_pools_only_later_steps() -> None:
    etf = EgoTrajectoryFeature(1)
    _set(etf.embed, [[1, 0]], [0])
    x = torch.tensor([[4.0, 1.0, 3.0, 2.0, 9.0]])
    pos = torch.stack((x, torch.zeros_like(x)), dim=-1)
    ok = torch.tensor([[True, True, True, True, False]])  # the 9 is not a valid ego step
    f = etf(pos, ok)[0, :, 0]
    # f[t] = max_{k > t, ok} x_k: t=0 -> max(1,3,2)=3, t=1 -> 3, t=2 -> 2, t=3 -> none (0), t=4 -> 0
    torch.testing.assert_close(f, torch.tensor([3.0, 3.0, 2.0, 0.0, 0.0]))


def test_ain_gru_eqs_6_7_10_against_manual_gru() -> None:
    torch.manual_seed(0)
    cfg = ModelConfig(**SMALL)  # type: ignore[arg-type]
    ain = AgentInteractionNet(cfg)
    assert ain.gru is not None and ain.st is not None
    parts = [torch.randn(2, 8) for _ in range(3)]  # o, r, m
    f_t = torch.randn(2, 8)
    h0 = torch.randn(2, 12)
    fst, h1 = ain.step(parts, f_t, h0)
    x = torch.cat(parts, dim=-1)
    w_ih, w_hh, b_ih, b_hh = ain.gru.weight_ih, ain.gru.weight_hh, ain.gru.bias_ih, ain.gru.bias_hh
    gi, gh = x @ w_ih.T + b_ih, h0 @ w_hh.T + b_hh
    r = torch.sigmoid(gi[:, :12] + gh[:, :12])
    z = torch.sigmoid(gi[:, 12:24] + gh[:, 12:24])
    n = torch.tanh(gi[:, 24:] + r * gh[:, 24:])
    h_manual = (1 - z) * n + z * h0
    torch.testing.assert_close(h1, h_manual)
    assert fst is not None
    torch.testing.assert_close(fst, torch.cat((f_t, h_manual @ ain.st.weight.T + ain.st.bias), dim=-1))


def test_attention_eqs_13_14() -> None:
    torch.manual_seed(0)
    net = TrajectoryNet(ModelConfig(features=Features(True, False, False, False, False), **SMALL))  # type: ignore[arg-type]
    assert net.attention is not None
    fst = torch.randn(1, 2, 8)  # (L, B, d_fst)
    pos = torch.randn(1, 3, 2)
    scene = torch.tensor([1, 0, 1])
    q = attention_q(net, fst, scene, pos)
    assert q is not None
    gate = torch.sigmoid(pos @ net.attention.weight.T + net.attention.bias)
    torch.testing.assert_close(q, fst[:, scene] * gate)


def test_decoder_first_step_eqs_19_22_hand_computed() -> None:
    torch.manual_seed(0)
    cfg = ModelConfig(**SMALL)  # type: ignore[arg-type]
    cfg = cfg.resolved(has_ego=False, has_map=False)
    net = TrajectoryNet(cfg).eval()
    batch = collate([make_scene(np.random.default_rng(1), 3, 4, 3)], cfg)
    enc = net.encode(batch)
    noise = torch.randn(2, 3, 3)
    pred = net.decode(batch, enc, noise)
    assert pred.positions.shape == (2, 3, 3, 2)
    h_d = torch.cat((enc.h[None].expand(2, 3, 8), noise), dim=-1) @ net.init_decoder.weight.T + net.init_decoder.bias
    step = (h_d @ net.out.weight.T + net.out.bias) * cfg.disp_scale_m
    torch.testing.assert_close(pred.positions[:, :, 0], batch.positions[None, :, 3] + step)


def test_encoder_keeps_state_of_unobserved_steps_eq_16() -> None:
    """An agent first seen late ends the encoder in the same state as one whose history starts there."""
    torch.manual_seed(0)
    cfg = ModelConfig(features=Features(False, False, False, False, False), **SMALL)  # type: ignore[arg-type]
    net = TrajectoryNet(cfg).eval()
    s = make_scene(np.random.default_rng(2), 1, 4, 3)
    late = make_scene(np.random.default_rng(2), 1, 4, 3)
    late.positions = late.positions.copy()
    late.positions[0, :2] = np.nan
    h_full = net.encode(collate([s], cfg)).h
    h_late = net.encode(collate([late], cfg)).h
    assert not torch.allclose(h_full, h_late)
    # Same as a scene that only starts at step 2: displacement input 0 at its first step in both.
    shifted = make_scene(np.random.default_rng(2), 1, 4, 3)
    shifted.positions = np.concatenate((np.full((1, 2, 2), np.nan), late.positions[:, 2:]), axis=1)
    torch.testing.assert_close(net.encode(collate([shifted], cfg)).h, h_late)


def test_roi_align_matches_hand_computation() -> None:
    f = (10.0 * torch.arange(4.0)[:, None] + torch.arange(4.0)[None, :])[None, None]  # f[y, x] = 10 y + x
    boxes = torch.tensor([[[0.5, 0.5, 2.5, 2.5]]])
    out = roi_align(f, boxes, pool=2, sampling=1)
    # bin centres at x, y in {1, 2}: bilinear of a linear map is exact
    torch.testing.assert_close(out[0, 0, 0], torch.tensor([[11.0, 12.0], [21.0, 22.0]]))
    # one-hot map, 2x2 samples per bin at (0.5, 1.5)^2: each sees the spike with weight 1/4 -> mean 1/4
    spike = torch.zeros(1, 1, 4, 4)
    spike[0, 0, 1, 1] = 1.0
    torch.testing.assert_close(
        roi_align(spike, torch.tensor([[[0.0, 0.0, 2.0, 2.0]]]), 1, 2)[0, 0, 0], torch.tensor([[0.25]])
    )
    # outside the map: half a cell beyond the border reads half the border value (zero padding)
    ones = torch.ones(1, 1, 4, 4)
    torch.testing.assert_close(
        roi_align(ones, torch.tensor([[[-1.0, 0.0, 0.0, 0.0]]]), 1, 1)[0, 0, 0], torch.tensor([[0.5]])
    )


def test_environment_fast_path_equals_eqs_11_12_reference() -> None:
    torch.manual_seed(0)
    cfg = ModelConfig(raster_channels=3, **SMALL)  # type: ignore[arg-type]
    net = TrajectoryNet(cfg).eval()
    assert net.env is not None
    rng = np.random.default_rng(3)
    scenes = [make_scene(rng, n, 4, 3, with_ego=True, with_raster=True, channels=3, size=64) for n in (3, 5)]
    batch = collate(scenes, cfg)
    fmap = net.env.feature_map(batch.raster)  # type: ignore[arg-type]
    assert fmap.shape == (2, 128, 8, 8)
    rows = torch.arange(8)
    pos = batch.positions[:, :3].transpose(0, 1) + torch.randn(3, 8, 2) * 5
    # near and beyond the 100 m raster's edges: zero padding, never the other scene's map
    pos[2, :4] = torch.tensor([[48.0, 0.0], [-55.0, 10.0], [0.0, 70.0], [52.0, -49.0]])
    fast = net.env(net.env.project(fmap), pos, batch, rows)
    ref = net.env.reference(fmap, pos, batch, rows)
    assert fast.shape == (3, 8, 8)
    torch.testing.assert_close(fast, ref, rtol=1e-4, atol=1e-4)


def test_backbone_stride_and_torchvision_state_dict(tmp_path: Path) -> None:
    torch.manual_seed(0)
    rgb = ResNet18Stages12(3)
    assert rgb(torch.zeros(1, 3, 224, 224)).shape == (1, 128, 28, 28)
    # A torchvision-layout dict: same key names, plus keys of later stages that must be ignored.
    state = {k: torch.randn_like(v) if v.is_floating_point() else v for k, v in rgb.state_dict().items()}
    state["layer3.0.conv1.weight"] = torch.randn(256, 128, 3, 3)
    state["fc.weight"] = torch.randn(1000, 512)
    save_file(state, str(tmp_path / "r18.safetensors"))
    torch.save(state, tmp_path / "r18.pth")
    for path in (tmp_path / "r18.safetensors", tmp_path / "r18.pth"):
        four = ResNet18Stages12(4)
        four.load_torchvision_state_dict(read_state_dict(path))
        expect = state["conv1.weight"].mean(dim=1, keepdim=True).repeat(1, 4, 1, 1) * 0.75
        torch.testing.assert_close(four.conv1.weight, expect)
        torch.testing.assert_close(four.layer2[1].bn2.running_var, state["layer2.1.bn2.running_var"])
    with pytest.raises(BackboneWeightsError):
        ResNet18Stages12(3).load_torchvision_state_dict({"conv1.weight": torch.zeros(64, 3, 7, 7)})


def test_backbone_bf16_stays_close_to_fp32() -> None:
    torch.manual_seed(0)
    fp32 = ResNet18Stages12(4).eval()
    bf16 = ResNet18Stages12(4, use_bf16=True).eval()
    bf16.use_bf16 = True  # the bf16 path itself, also where this CPU would run fp32 (emulated: same numbers)
    bf16.load_state_dict(fp32.state_dict())
    x = torch.rand(2, 4, 64, 64) * 2 - 1
    with torch.no_grad():
        a, b = fp32(x), bf16(x)
    assert b.dtype == torch.float32
    rel = float((a - b).norm() / a.norm())
    assert rel < 0.05


def test_backbone_uses_bf16_only_where_the_cpu_has_it() -> None:
    from logpipe.model.zhu2020.backbone import native_bf16

    assert ResNet18Stages12(4, use_bf16=True).use_bf16 is native_bf16()
    assert ResNet18Stages12(4, use_bf16=False).use_bf16 is False
    capability = torch.backends.cpu.get_cpu_capability()
    if capability in ("AVX2", "DEFAULT"):  # no AVX-512 at all: certainly no native bf16
        assert not native_bf16()


def test_fused_lstm_step_matches_lstm_cell_eqs_16_18() -> None:
    from logpipe.model.zhu2020.encoder import lstm_step, lstm_weights

    torch.manual_seed(0)
    cell = torch.nn.LSTMCell(5, 4)
    x, h, c = torch.randn(3, 5), torch.randn(3, 4), torch.randn(3, 4)
    want = cell(x, (h, c))
    got = lstm_step(lstm_weights(cell), x, h, c)
    torch.testing.assert_close(got[0], want[0])
    torch.testing.assert_close(got[1], want[1])
