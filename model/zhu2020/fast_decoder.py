"""The decoder for inference: eqs. 17-22 of Zhu et al. (IJCAI 2020) as ``decoder.decode`` computes them, without
autograd and restructured for speed (outputs equal ``decode``'s up to float rounding; tested against it).

* Agent-major (R, M) rows: the decoded rows are sorted by scene (``collate``), so each scene's agents x modes form
  one contiguous block; the per-scene max-pools are segment reductions over the agents that are decoded (no padded
  (B, A_max) grid, no mask), and q's scene lookup is a block repeat.
* One input buffer [displacement | v | q | h | 1] per step for the fused LSTM_D matmul, filled in place (no cats);
  eq. 17's W_p is folded into LSTM_D's input weights (two inputs instead of d_p) and the gates are reordered to
  (i, f, o, g) so one sigmoid and one tanh cover them.

Positions are model-frame metres; ``Prediction.positions`` is (M, R, T_pred - T_obs, 2) as ``decode``'s.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import torch
from torch import Tensor

from ..training.row_blocks import row_mm, scale_down
from .batching import Batch
from .decoder import Prediction, agent_output_basis, carried_first_step, mode_open
from .encoder import Encoded, lstm_weights
from .layers import TrajectoryLayers

_LSTM_CHUNK_ROWS = 2048
"""Rows per block of ``decode_fast``'s LSTM step: its gates stay in L2 (~2x the matmul rate of one big block here)."""


@dataclass
class _InputBuffer:
    """LSTM_D's input rows [disp (2) | v (d_v) | q (d_fst) | h (H) | 1], (R * M, width), and views of its parts.

    The trailing constant 1 multiplies the bias row of ``_fused_input_weights``.
    """

    rows: Tensor
    disp: Tensor  # (R, M, 2) scaled displacement, eq. 17's input
    env: Tensor  # (R, M, d_v), eq. 12
    q: Tensor  # (R, M, d_fst), eq. 14
    h: Tensor  # (R * M, H), h_d^(t-1); updated in place by ``_lstm_d_step``

    @classmethod
    def like(cls, noise: Tensor, r: int, mm: int, width: int, n_env: int, n_q: int, hid: int) -> _InputBuffer:
        buf = noise.new_empty(r * mm, width)
        buf[:, -1] = 1.0
        return cls(buf, buf[:, :2].view(r, mm, 2), buf[:, 2 : 2 + n_env].view(r, mm, n_env),
                   buf[:, 2 + n_env : 2 + n_env + n_q].view(r, mm, n_q), buf[:, width - 1 - hid : width - 1])


def _fused_input_weights(net: TrajectoryLayers) -> Tensor:
    """LSTM_D's weights over ``_InputBuffer.rows``: gates (i, f, g, o) reordered to (i, f, o, g), eq. 17's W_p folded
    into the displacement rows, and the bias as the weight row of the constant-1 column."""
    hid = net.config.lstm_dim
    w, bias = lstm_weights(net.decoder)
    d_p = net.disp_embed.out_features
    order = torch.cat([torch.arange(lo * hid, hi * hid, device=w.device) for lo, hi in ((0, 2), (3, 4), (2, 3))])
    w, bias = w[:, order], bias[order]
    # The bias is a weight row over a constant-1 input column: addmm's broadcast copy of it cost ~half
    # of the matmul here.
    return torch.cat((net.disp_embed.weight.t() @ w[:d_p], w[d_p:], (bias + net.disp_embed.bias @ w[:d_p])[None]))


def _scene_pool(per_scene: Tensor, b: int, mm: int) -> Callable[[Tensor], Tensor]:
    """Per-scene max over the decoded agents: (R, M, d) -> (B * M, d), zero for a scene without any (eqs. 2, 4)."""
    empty = (per_scene == 0)[:, None, None] if bool((per_scene == 0).any()) else None

    def pool(x: Tensor) -> Tensor:
        out = torch.segment_reduce(x, "max", lengths=per_scene, axis=0)
        if empty is not None:
            out = out.masked_fill(empty, 0.0)
        return out.reshape(b * mm, -1)

    return pool


def _lstm_d_step(buf: _InputBuffer, w_in: Tensor, c: Tensor, hid: int) -> None:
    """Eq. 18 on the filled buffer, in cache-sized row blocks: writes h_d^(t) into ``buf.h`` and c in place."""
    rows = buf.rows.shape[0]
    for lo in range(0, rows, _LSTM_CHUNK_ROWS):
        hi = min(lo + _LSTM_CHUNK_ROWS, rows)
        gates = row_mm(buf.rows[lo:hi], w_in)  # batch-shape invariant (row_blocks)
        sig = torch.sigmoid(gates[:, : 3 * hid])
        c_blk = c[lo:hi]
        c_blk.mul_(sig[:, hid : 2 * hid]).addcmul_(sig[:, :hid], torch.tanh(gates[:, 3 * hid :]))
        torch.mul(sig[:, 2 * hid :], torch.tanh(c_blk), out=buf.h[lo:hi])


def _interaction(net: TrajectoryLayers, enc: Encoded, pos_scaled: Tensor, h: Tensor, h_gru: Tensor | None, t: int,
                 pool: Callable[[Tensor], Tensor]) -> tuple[Tensor | None, Tensor | None]:
    """fst^(t) (B * M, d_fst) and the new GRU state at predicted step t (eqs. 1-10 on the predicted positions
    ``pos_scaled`` (R, M, 2) and the decoder states ``h`` (R * M, H)); the AIN as at T_obs without
    ``interaction_while_decoding``."""
    r, mm, _ = pos_scaled.shape
    b = enc.ego_pos.shape[0]
    f_t = None if enc.f_all is None else enc.f_all[:, None, t].expand(b, mm, -1).reshape(b * mm, -1)
    if not net.config.interaction_while_decoding:
        return net.ain.output(f_t, h_gru), h_gru
    parts = []
    if net.ain.position is not None:
        parts.append(pool(net.ain.position.embed(pos_scaled)))
    if net.ain.tracking is not None:  # h_d^(t-1)
        parts.append(pool(net.ain.tracking.embed(h).view(r, mm, -1)))
    if enc.m_all is not None:
        parts.append(enc.m_all[:, None, t].expand(b, mm, -1).reshape(b * mm, -1))
    return net.ain.step(parts, f_t, h_gru)


def _map_features(net: TrajectoryLayers, proj: Tensor | None, pos: Tensor, batch: Batch, rows: Tensor) -> Tensor:
    """v (R, M, d_v) at agent-major positions pos (R, M, 2); zero without maps."""
    if proj is None or net.env is None:
        return pos.new_zeros(*pos.shape[:2], net.config.embed_dim)
    v: Tensor = net.env(proj, pos, batch, rows, agent_major=True)
    return v


@torch.no_grad()
def decode_fast(net: TrajectoryLayers, batch: Batch, enc: Encoded, noise: Tensor,
                constant_velocity_modes: int | None = None) -> Prediction:
    """``decoder.decode`` for inference (no autograd), restructured for speed (see the module docstring).

    Args:
        net: the network whose layers run.
        batch: the batch that was encoded; its rows of a scene together, in scene order (``collate``'s layout).
        enc: ``encode(batch)``.
        noise: (M, R, noise_dim) Gaussian z of eq. 21, R = number of active rows.
        constant_velocity_modes: the first this many modes get no step outputs (``decoder.mode_open``; None: the
            config's).
    """
    cfg = net.config
    ps, ds = cfg.pos_scale_m, cfg.disp_scale_m
    t_obs = batch.obs_len
    rows = batch.active.nonzero().squeeze(1)
    mm, r, _ = noise.shape
    hid = cfg.lstm_dim
    scene = batch.scene[rows]
    if r > 1 and bool((scene[1:] < scene[:-1]).any()):
        raise ValueError("decode_fast needs the rows of a scene together, in scene order (collate's layout)")
    per_scene = torch.bincount(scene, minlength=batch.size)
    pool = _scene_pool(per_scene, batch.size, mm)
    w_in = _fused_input_weights(net)
    n_env = cfg.embed_dim if net.env is not None else 0
    n_q = net.ain.out_dim if net.attention is not None else 0
    buf = _InputBuffer.like(noise, r, mm, w_in.shape[0], n_env, n_q, hid)
    h = buf.h
    h.copy_(net.init_decoder(torch.cat((enc.h[rows][:, None].expand(r, mm, hid), noise.transpose(0, 1)), -1))
            .view(r * mm, hid))  # eqs. 21-22
    open_factor = mode_open(net, h.view(r, mm, hid), constant_velocity_modes, mode_dim=1)  # (R, M, 1)
    c = enc.c[rows].repeat_interleave(mm, dim=0)
    h_gru = None if enc.h_gru is None else enc.h_gru.repeat_interleave(mm, dim=0)  # (B * M, G)
    ego_ok = (batch.ego[rows][:, None] & enc.ego_ok[scene]) if cfg.features.uses_ego_plan else None
    raster_ok = batch.has_raster[scene][:, None, None]
    all_raster = bool(raster_ok.all())
    p_prev = batch.positions[rows, t_obs - 2][:, None].expand(r, mm, 2)
    p_cur = batch.positions[rows, t_obs - 1][:, None].expand(r, mm, 2)
    carried = carried_first_step(cfg, batch, rows)
    basis = agent_output_basis(cfg, carried)
    outputs = noise.new_empty(r, mm, cfg.pred_len, 2)
    for k in range(cfg.pred_len):
        if k > 0:  # one LSTM_D step at t = T_obs + k on the predicted positions
            pos_scaled = scale_down(p_cur, ps)
            fst, h_gru = _interaction(net, enc, pos_scaled, h, h_gru, t_obs - 1 + k, pool)
            # eq. 17 (W_p folded into LSTM_D); times 1 / ds, not divided: see row_blocks.scale_down
            torch.mul(p_cur - p_prev, 1.0 / ds, out=buf.disp)
            if net.env is not None:
                v = _map_features(net, enc.proj, p_cur, batch, rows)
                buf.env.copy_(v if all_raster else torch.where(raster_ok, v, torch.zeros_like(v)))
            if n_q and fst is not None and net.attention is not None:  # eqs. 13-14
                gate = torch.sigmoid(net.attention(pos_scaled))
                torch.mul(fst.view(batch.size, mm, -1).repeat_interleave(per_scene, dim=0), gate, out=buf.q)
            _lstm_d_step(buf, w_in, c, hid)  # eq. 18
        o = net.out(h).view(r, mm, 2)
        if open_factor is not None:  # ModelConfig.mode_gate, constant_velocity_modes
            o = o * open_factor
        # eqs. 19-20: the turn into each agent's basis as products and a sum (an einsum's bmm took other kernels
        # for one agent than for several and moved its bits)
        turned = None if basis is None else o[..., :1] * basis[:, None, :, 0] + o[..., 1:] * basis[:, None, :, 1]
        p_next = p_cur + (o * ds if turned is None else turned)
        if carried is not None:
            p_next = p_next + (carried[:, None] if k == 0 else p_cur - p_prev)
        if ego_ok is not None:  # the ego follows its given (planned) future
            given = ego_ok[:, t_obs + k]
            p_next = torch.where(given[:, None, None], enc.ego_pos[scene, t_obs + k][:, None], p_next)
        outputs[:, :, k] = p_next
        p_prev, p_cur = p_cur, p_next
    return Prediction(outputs.transpose(0, 1), rows)
