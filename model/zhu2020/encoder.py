"""The encoder of the Trajectory Prediction Network of Zhu et al. (IJCAI 2020): the attention q over the AIN
output (eqs. 13-14), the displacement embedding (eq. 15) and LSTM_E over the observed steps t = 1 .. T_obs
(eq. 16), which also runs the AIN (eqs. 1-10) and looks up the EN (eqs. 11-12) at every observed step.

Tensors: positions are model-frame metres, divided by ``ModelConfig.pos_scale_m`` (displacements by
``disp_scale_m``) at each layer's input; per-agent tensors are ``(L, N, ...)`` with a leading axis L for modes
or time steps, per-scene ones ``(L, B, ...)`` (``batching.Batch``).

Tracking feature timing (a reading of the paper made explicit): eq. 4 pools h_i^(t) while eq. 16 feeds q_i^(t)
(which depends on r^(t)) into the LSTM that produces h_i^(t) -- circular as written. We pool the states *before*
step t's update: h_e^(t-1) while encoding (zeros at t = 1) and h_d^(t-1) while decoding (``decoder``).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor, nn

from ..training.row_blocks import row_mm, scale_down
from .batching import Batch
from .layers import TrajectoryLayers


def lstm_weights(cell: nn.LSTMCell) -> tuple[Tensor, Tensor]:
    """(W, b) with W = [W_ih, W_hh]^T and b = b_ih + b_hh, so one matmul serves a step."""
    assert cell.bias_ih is not None
    assert cell.bias_hh is not None
    return torch.cat((cell.weight_ih, cell.weight_hh), dim=1).t(), cell.bias_ih + cell.bias_hh


def lstm_step(weights: tuple[Tensor, Tensor], x: Tensor, h: Tensor, c: Tensor) -> tuple[Tensor, Tensor]:
    """``nn.LSTMCell`` arithmetic (gates i, f, g, o) with one fused matmul: ~25% faster on CPU here."""
    w, b = weights
    xh = torch.cat((x, h), dim=1)
    gates = torch.addmm(b, xh, w) if torch.is_grad_enabled() else row_mm(xh, w, b)  # see row_blocks
    i, f, g, o = gates.chunk(4, dim=1)
    c_new = torch.sigmoid(f) * c + torch.sigmoid(i) * torch.tanh(g)
    return torch.sigmoid(o) * torch.tanh(c_new), c_new


@dataclass
class Encoded:
    """Encoder output for one batch.

    Attributes:
        h: (N, H) LSTM_E hidden state at T_obs.
        c: (N, H) LSTM_E cell state at T_obs.
        h_gru: (B, G) AIN GRU state after T_obs, or None.
        proj: environment maps from ``EnvironmentNet.project``, or None.
        ego_pos: (B, T, 2) ego positions (model frame, metres), zeros where absent.
        ego_ok: (B, T) ego observed/planned at that step.
        m_all: (B, T, d_m) eq. 5 for every step, or None.
        f_all: (B, T, d_f) eq. 9 for every step, or None.
    """

    h: Tensor
    c: Tensor
    h_gru: Tensor | None
    proj: Tensor | None
    ego_pos: Tensor
    ego_ok: Tensor
    m_all: Tensor | None
    f_all: Tensor | None


def attention_q(net: TrajectoryLayers, fst: Tensor | None, scene: Tensor, pos_scaled: Tensor) -> Tensor | None:
    """Eqs. 13-14: q_i = fst ⊙ σ(W_c p_i + b_c); fst (L, B, d_fst), pos (L, R, 2) -> (L, R, d_fst)."""
    if fst is None or net.attention is None:
        return None
    return fst[:, scene] * torch.sigmoid(net.attention(pos_scaled))


def map_features(net: TrajectoryLayers, proj: Tensor | None, pos: Tensor, batch: Batch, rows: Tensor) -> Tensor:
    """v (L, R, d_v): eqs. 11-12 at pos (L, R, 2); zero for scenes without a raster."""
    if proj is None or net.env is None:
        return pos.new_zeros(*pos.shape[:2], net.config.embed_dim)
    # Positions are detached: the map is a lookup of context, not a path for position gradients.
    v = net.env(proj, pos.detach(), batch, rows)
    return torch.where(batch.has_raster[batch.scene[rows]][None, :, None], v, torch.zeros_like(v))


def encode(net: TrajectoryLayers, batch: Batch, feature_map: Tensor | None = None) -> Encoded:
    """Run ``net``'s LSTM_E (eq. 16) and the AIN GRU over the observed steps t = 1 .. T_obs; ``feature_map``: the
    backbone's maps of ``batch.raster`` when the caller has them (``feature_cache``), else computed here."""
    cfg = net.config
    t_obs = batch.obs_len
    ps, ds = cfg.pos_scale_m, cfg.disp_scale_m
    n = batch.positions.shape[0]
    b = batch.size
    rows = torch.arange(n, device=batch.positions.device)
    obs = batch.positions[:, :t_obs].transpose(0, 1)  # (T_obs, N, 2)
    ok = batch.valid[:, :t_obs].transpose(0, 1)  # (T_obs, N)
    # Displacements where both ends are observed (eq. 15); the first step has none.
    disp = torch.zeros_like(obs)
    disp[1:] = torch.where((ok[1:] & ok[:-1])[..., None], obs[1:] - obs[:-1], 0.0)
    e_p = net.disp_embed(scale_down(disp, ds))  # (T_obs, N, d): eq. 15 for all steps at once
    # Ego track per scene, used by EMF/ETF and by the decoder's ego override.
    ego_rows = batch.ego.nonzero().squeeze(1)
    ego_pos = batch.positions.new_zeros(b, batch.positions.shape[1], 2)
    ego_pos[batch.scene[ego_rows]] = batch.positions[ego_rows]
    ego_ok = batch.valid.new_zeros(b, batch.positions.shape[1])
    ego_ok[batch.scene[ego_rows]] = batch.valid[ego_rows]
    m_all = f_all = None
    if net.ain.ego_motion is not None:
        ego_disp = torch.zeros_like(ego_pos)
        ego_disp[:, 1:] = ego_pos[:, 1:] - ego_pos[:, :-1]
        ego_disp_ok = torch.zeros_like(ego_ok)
        ego_disp_ok[:, 1:] = ego_ok[:, 1:] & ego_ok[:, :-1]
        m_all = net.ain.ego_motion(scale_down(ego_disp, ds), ego_disp_ok)  # eq. 5, (B, T, d)
    if net.ain.ego_trajectory is not None:
        f_all = net.ain.ego_trajectory(scale_down(ego_pos, ps), ego_ok)  # eqs. 8-9, (B, T, d)
    obs_scaled = scale_down(obs, ps)  # PF's and the attention gate's input
    o_all = None
    if net.ain.position is not None:  # eqs. 1-2 for all observed steps at once: (T_obs, B, d)
        o_all = net.ain.position(obs_scaled, ok, batch, rows)
    proj = v_all = None
    if net.env is not None:
        if batch.raster is not None:
            fmap = net.env.feature_map(batch.raster) if feature_map is None else feature_map
            proj = net.env.project(fmap)
        v_all = map_features(net, proj, obs, batch, rows)  # (T_obs, N, d_v)
        v_all = torch.where(ok[..., None], v_all, torch.zeros_like(v_all))
    gate = torch.sigmoid(net.attention(obs_scaled)) if net.attention is not None else None  # eq. 13
    hid = cfg.lstm_dim
    h = obs.new_zeros(n, hid)
    c = obs.new_zeros(n, hid)
    h_gru = obs.new_zeros(b, cfg.gru_dim) if net.ain.gru is not None else None
    lstm_e = lstm_weights(net.encoder)
    for t in range(t_obs):
        ok_t = ok[t]
        r = None
        if net.ain.tracking is not None:  # eqs. 3-4 on h_e^(t-1)
            r = net.ain.tracking(h[None], ok_t[None], batch, rows)[0]
        m_t = None if m_all is None else m_all[:, t]
        parts = [x for x in (None if o_all is None else o_all[t], r, m_t) if x is not None]
        fst, h_gru = net.ain.step(parts, None if f_all is None else f_all[:, t], h_gru)
        x = [e_p[t]]
        if v_all is not None:
            x.append(v_all[t])
        if fst is not None and gate is not None:
            x.append(fst[batch.scene] * gate[t])  # eq. 14
        h_new, c_new = lstm_step(lstm_e, torch.cat(x, dim=-1), h, c)  # eq. 16
        # Agents not observed at t keep their state (eq. 16 only runs on observed steps).
        h = torch.where(ok_t[:, None], h_new, h)
        c = torch.where(ok_t[:, None], c_new, c)
    return Encoded(h, c, h_gru, proj, ego_pos, ego_ok, m_all, f_all)
