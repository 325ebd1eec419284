"""The paper's network: Agent Interaction Network (eqs. 1-10), Environment Network (eqs. 11-12) and the
Trajectory Prediction Network (eqs. 13-22).

Tensor layout: agents are flattened rows (see ``batching.Batch``); per-agent tensors are ``(L, N, ...)``
with a leading axis L for modes (decoder samples) or time steps (vectorised encoder inputs); per-scene
tensors are ``(L, B, ...)``. Every max-pool over agents is ``scene_max``: rows are scattered into a
(B, A_max) grid whose empty cells and masked rows are -inf, so padding cannot win the max.

Two readings of the paper made explicit:

* **Tracking feature timing.** Eq. 4 pools h_i^(t) while eq. 16 feeds q_i^(t) (which depends on r^(t))
  into the LSTM that produces h_i^(t) -- circular as written. We pool the states *before* step t's
  update: h_e^(t-1) while encoding (zeros at t = 1) and h_d^(t-1) while decoding.
* **Decoder indexing.** h_d^(T_obs) comes from eq. 22 and gives the first displacement through eq. 19;
  LSTM_D then runs for t = T_obs+1 .. T_pred-1 on the predicted positions (eqs. 17-20). The paper leaves
  the decoder's cell state open; it starts from the encoder's cell state.

The AIN's GRU runs once per step over t = 1 .. T_pred-1 (observed steps with the true positions, then
per mode on the predicted ones). With the ego plan in use (EMF or ETF on), the ego's future positions are
inputs: the ego row is not predicted but follows its given future in the decoder (the paper's
"planned trajectory ... given for reference"). Only agents observed at the current step are decoded.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch import Tensor, nn
from torch.nn import functional as F  # noqa: N812

from .backbone import BACKBONE_CHANNELS, BACKBONE_STRIDE, ResNet18Stages12, read_state_dict, roi_align
from .batching import Batch
from .config import ConfigError, ModelConfig


def masked_max(x: Tensor, mask: Tensor) -> Tensor:
    """Max over the agent axis (-2) of ``x`` (..., A, d) where ``mask`` (..., A) is True; 0 if none is.

    Masked entries are -inf before the max, so neither padding nor unobserved agents can win; they get
    zero gradient.
    """
    filled = x.masked_fill(~mask[..., None], float("-inf"))
    out = filled.amax(dim=-2)
    return torch.where(mask.any(dim=-1, keepdim=True), out, torch.zeros_like(out))


def scene_max(x: Tensor, mask: Tensor, batch: Batch, rows: Tensor) -> Tensor:
    """Per-scene max-pool of flattened rows (Maxpool of eqs. 2 and 4).

    Args:
        x: (L, R, d) values of rows ``rows`` (R,) of the batch.
        mask: (L, R) rows that take part.
        batch: supplies scene/slot of each row.
        rows: batch row index of each of the R rows.

    Returns:
        (L, B, d), zero for a scene without any participating row.
    """
    big_l, _, d = x.shape
    b, a = batch.size, batch.max_agents
    cell = batch.scene[rows] * a + batch.slot[rows]
    grid = x.new_zeros(big_l, b * a, d).index_copy(1, cell, x)
    keep = mask.new_zeros(big_l, b * a).index_copy(1, cell, mask)
    return masked_max(grid.view(big_l, b, a, d), keep.view(big_l, b, a))


def lstm_weights(cell: nn.LSTMCell) -> tuple[Tensor, Tensor]:
    """(W, b) with W = [W_ih, W_hh]^T and b = b_ih + b_hh, so one matmul serves a step."""
    assert cell.bias_ih is not None
    assert cell.bias_hh is not None
    return torch.cat((cell.weight_ih, cell.weight_hh), dim=1).t(), cell.bias_ih + cell.bias_hh


def lstm_step(weights: tuple[Tensor, Tensor], x: Tensor, h: Tensor, c: Tensor) -> tuple[Tensor, Tensor]:
    """``nn.LSTMCell`` arithmetic (gates i, f, g, o) with one fused matmul: ~25% faster on CPU here."""
    w, b = weights
    gates = torch.addmm(b, torch.cat((x, h), dim=1), w)
    i, f, g, o = gates.chunk(4, dim=1)
    c_new = torch.sigmoid(f) * c + torch.sigmoid(i) * torch.tanh(g)
    return torch.sigmoid(o) * torch.tanh(c_new), c_new


def _bag_picks(k: int, s: int, device: torch.device) -> tuple[Tensor, Tensor]:
    """For the bag entries (ky, kx, sy, sx, cy, cx) of ``EnvironmentNet.forward``, the index into the per-axis
    (K*S*2) y and x entries (on ``device``)."""
    per_axis = torch.arange(k * s * 2, device=device).view(k, s, 2)
    full = (k, k, s, s, 2, 2)
    ypick = per_axis.view(k, 1, s, 1, 2, 1).expand(full).reshape(-1)
    xpick = per_axis.view(1, k, 1, s, 1, 2).expand(full).reshape(-1)
    return ypick, xpick


_LSTM_CHUNK_ROWS = 2048
"""Rows per block of ``decode_fast``'s LSTM step: its gates stay in L2 (~2x the matmul rate of one big block here)."""


class PositionFeature(nn.Module):
    """PF, eqs. 1-2: o^(t) = Maxpool_i(W_o p_i^(t) + b_o)."""

    def __init__(self, dim: int) -> None:
        super().__init__()
        self.embed = nn.Linear(2, dim)  # W_o, b_o

    def forward(self, pos: Tensor, mask: Tensor, batch: Batch, rows: Tensor) -> Tensor:
        """pos (L, R, 2) scaled positions of ``rows``, mask (L, R) -> o (L, B, d_o)."""
        return scene_max(self.embed(pos), mask, batch, rows)


class TrackingFeature(nn.Module):
    """TF, eqs. 3-4: r^(t) = Maxpool_i(W_r h_i + b_r) over the LSTM hidden states."""

    def __init__(self, hidden: int, dim: int) -> None:
        super().__init__()
        self.embed = nn.Linear(hidden, dim)  # W_r, b_r

    def forward(self, hidden: Tensor, mask: Tensor, batch: Batch, rows: Tensor) -> Tensor:
        """hidden (L, R, H) of ``rows``, mask (L, R) -> r (L, B, d_r)."""
        return scene_max(self.embed(hidden), mask, batch, rows)


class EgoMotionFeature(nn.Module):
    """EMF, eq. 5: m^(t) = W_m (p_0^(t) - p_0^(t-1)) + b_m; zero where the scene has no ego step."""

    def __init__(self, dim: int) -> None:
        super().__init__()
        self.embed = nn.Linear(2, dim)  # W_m, b_m

    def forward(self, disp: Tensor, ok: Tensor) -> Tensor:
        """disp (..., 2) scaled ego displacement, ok (...) -> (..., d_m)."""
        out = self.embed(disp)
        return torch.where(ok[..., None], out, torch.zeros_like(out))


class EgoTrajectoryFeature(nn.Module):
    """ETF, eqs. 8-9: f^(t) = Maxpool_{k in [t+1, T_pred]}(W_f p_0^(k) + b_f)."""

    def __init__(self, dim: int) -> None:
        super().__init__()
        self.embed = nn.Linear(2, dim)  # W_f, b_f

    def forward(self, ego_pos: Tensor, ok: Tensor) -> Tensor:
        """ego_pos (B, T, 2) scaled, ok (B, T) -> f (B, T, d_f), f[:, t] pooling steps k > t only.

        Zero where no later ego position exists (last step, no ego).
        """
        emb = self.embed(ego_pos).masked_fill(~ok[..., None], float("-inf"))
        # suffix[t] = max_{k >= t}: reverse cumulative max along time.
        suffix = torch.flip(torch.cummax(torch.flip(emb, (1,)), dim=1).values, (1,))
        later = torch.cat((suffix[:, 1:], torch.full_like(suffix[:, :1], float("-inf"))), dim=1)
        return torch.where(torch.isfinite(later), later, torch.zeros_like(later))


class AgentInteractionNet(nn.Module):
    """AIN: PF, TF, EMF -> GRU (eq. 6) -> st (eq. 7); fst = Cat(f, st) (eq. 10). Disabled parts are absent."""

    def __init__(self, config: ModelConfig) -> None:
        super().__init__()
        feats, d = config.features, config.embed_dim
        self.position = PositionFeature(d) if feats.position else None
        self.tracking = TrackingFeature(config.lstm_dim, d) if feats.tracking else None
        self.ego_motion = EgoMotionFeature(d) if feats.ego_motion else None
        self.ego_trajectory = EgoTrajectoryFeature(d) if feats.ego_trajectory else None
        gru_in = d * (int(feats.position) + int(feats.tracking) + int(feats.ego_motion))
        self.gru = nn.GRUCell(gru_in, config.gru_dim) if gru_in else None  # eq. 6, 128 cells
        self.st = nn.Linear(config.gru_dim, d) if gru_in else None  # eq. 7, W_s, b_s
        self.out_dim = d * (int(feats.ego_trajectory) + int(gru_in > 0))

    def step(
        self, parts: list[Tensor], f_t: Tensor | None, h_gru: Tensor | None
    ) -> tuple[Tensor | None, Tensor | None]:
        """One time step for a set of scenes.

        Args:
            parts: [o^(t), r^(t), m^(t)] of the enabled features, each (S, d).
            f_t: f^(t) (S, d_f) when ETF is on.
            h_gru: GRU state (S, gru_dim) (None without GRU).

        Returns:
            fst^(t) (S, out_dim), or None when the AIN is empty, and the new GRU state.
        """
        if self.gru is not None:
            h_gru = self.gru(torch.cat(parts, dim=-1), h_gru)  # eq. 6
        return self.output(f_t, h_gru), h_gru

    def output(self, f_t: Tensor | None, h_gru: Tensor | None) -> Tensor | None:
        """fst^(t) (S, out_dim) = Cat(f^(t), W_s h_gru + b_s) (eqs. 7, 10) from the GRU state as it is; None when
        the AIN is empty."""
        out: list[Tensor] = []
        if f_t is not None:
            out.append(f_t)
        if self.st is not None and h_gru is not None:
            out.append(self.st(h_gru))  # eq. 7
        return torch.cat(out, dim=-1) if out else None  # eq. 10


class EnvironmentNet(nn.Module):
    """EN, eqs. 11-12: ResNet18 stages 1-2 on the raster, ROIAlign (K x K) over the 2 R_s square around an
    agent, flatten (eq. 11) and embed to d_v (eq. 12).

    Fast path: eq. 12 is linear in G and bilinear sampling is linear in the map, so W_v is applied to the
    feature map first, one d_v-channel map per ROI bin (``project``), and each bin then samples only its
    own map (``forward``). The result equals ``reference`` (roi_align then W_v) up to rounding; sampling
    64 instead of 128 channels, with no padded rows, and skipping the (C, K, K) intermediate.
    """

    def __init__(self, config: ModelConfig) -> None:
        super().__init__()
        self.backbone = ResNet18Stages12(config.raster_channels, use_bf16=config.backbone_bf16)
        self.pool_size = config.roi_pool
        self.sampling = config.roi_sampling
        self.half_size_m = config.roi_half_size_m
        self.embed = nn.Linear(BACKBONE_CHANNELS * config.roi_pool**2, config.embed_dim)  # W_v, b_v
        self.frozen = config.freeze_backbone
        if self.frozen:
            self.backbone.requires_grad_(False)

    def train(self, mode: bool = True) -> EnvironmentNet:
        """As ``nn.Module.train`` but a frozen backbone stays in eval mode (fixed batch-norm stats)."""
        super().train(mode)
        if self.frozen:
            self.backbone.eval()
        return self

    def feature_map(self, raster: Tensor) -> Tensor:
        """(B, C, H, W) in [0, 1] -> (B, 128, H/8, W/8); once per scene, shared by every agent and step."""
        return self.backbone(raster * 2.0 - 1.0)  # type: ignore[no-any-return]

    def boxes(self, pos: Tensor, batch: Batch, rows: Tensor) -> Tensor:
        """ROI boxes (L, R, 4) in feature coordinates for model-frame positions pos (L, R, 2) of ``rows``."""
        sc = batch.scene[rows]
        aff = batch.frame_to_px[sc]  # (R, 2, 3)
        px = torch.einsum("rij,lrj->lri", aff[:, :, :2], pos) + aff[:, :, 2]
        centre = px / BACKBONE_STRIDE
        half = (self.half_size_m * batch.px_per_m[sc] / BACKBONE_STRIDE)[None, :, None]
        return torch.cat((centre - half, centre + half), dim=-1)

    def reference(self, fmap: Tensor, pos: Tensor, batch: Batch, rows: Tensor) -> Tensor:
        """Eqs. 11-12 literally: v = W_v Reshape(ROIAlign(fmap)) + b_v; pos (L, R, 2) -> (L, R, d_v)."""
        boxes = self.boxes(pos, batch, rows)  # (L, R, 4)
        sc = batch.scene[rows]
        g = roi_align(fmap[sc], boxes.transpose(0, 1), self.pool_size, self.sampling)  # (R, L, C, K, K)
        v: Tensor = self.embed(g.flatten(2))  # eq. 11 (reshape), eq. 12
        return v.transpose(0, 1)

    def project(self, fmap: Tensor) -> Tensor:
        """(B, C, h, w) -> (K*K, B, h, w, d_v): W_v's slice for each ROI bin applied to the map.

        The 1/S^2 of the bin average is folded in here so ``forward`` can sum.
        """
        c = fmap.shape[1]
        weight = self.embed.weight.view(-1, c, self.pool_size**2) / self.sampling**2  # Reshape(G) = (C, K, K)
        return torch.einsum("vck,bchw->kbhwv", weight, fmap).contiguous()

    def forward(self, proj: Tensor, pos: Tensor, batch: Batch, rows: Tensor, *, agent_major: bool = False) -> Tensor:
        """v (L, R, d_v) for model-frame positions pos (L, R, 2) of ``rows`` from ``project(fmap)``; with
        ``agent_major`` pos is (R, L, 2) and v (R, L, d_v) (``decode_fast``'s layout).

        Each output is one weighted bag of map cells: per bin k, per sub-sample, the four bilinear corners
        in bin k's projected map (``embedding_bag``, whose backward is a contiguous index-add, far cheaper
        on CPU than ``grid_sample``'s). Corners outside the map get weight 0 (zero padding).

        Bilinear weights and cell indices are separable: they are computed per axis (K*S samples x 2
        corners) and combined by one broadcast. Bags run agent-major (R, L) so consecutive bags read the
        same scene's maps (~3x faster gathers than mode-major here). Same bag contents and summation order
        as the per-corner formulation, so the same result.
        """
        k, s = self.pool_size, self.sampling
        kk, b, hf, wf, dv = proj.shape
        n = k * s
        if agent_major:
            r, big_l, _ = pos.shape
            boxes = self._boxes_agent_major(pos, batch, rows)
        else:
            big_l, r, _ = pos.shape
            boxes = self.boxes(pos, batch, rows).transpose(0, 1)  # (R, L, 4)
        steps = (torch.arange(n, dtype=pos.dtype, device=pos.device) + 0.5) / n  # sample fractions, (bin, sub)
        corner = torch.tensor([0.0, 1.0], dtype=pos.dtype, device=pos.device)

        def axis(lo: Tensor, hi: Tensor, size: int) -> tuple[Tensor, Tensor]:
            """Cell index and weight (R * L, K*S*2) of the two bilinear corners of each sample along one axis."""
            c = lo + (hi - lo) * steps
            c0 = torch.floor(c)
            f = (c - c0)[..., None]
            i = c0[..., None] + corner
            w = corner * f + (1 - corner) * (1 - f)
            w = torch.where((i >= 0) & (i <= size - 1), w, torch.zeros_like(w))
            return i.clamp(0, size - 1).reshape(r * big_l, -1), w.reshape(r * big_l, -1)

        xi, wx = axis(boxes[..., 0:1], boxes[..., 2:3], wf)
        yi, wy = axis(boxes[..., 1:2], boxes[..., 3:4], hf)
        # Flat cell = ((bin * B + scene) * h + y) * w + x = y part (bin row, scene, y) + x part (bin column, x).
        bins = torch.arange(k, dtype=pos.dtype, device=pos.device).repeat_interleave(2 * s)  # bin of each entry
        scene = batch.scene[rows].to(pos.dtype).repeat_interleave(big_l)[:, None]
        cells = kk * b * hf * wf
        # Integer arithmetic in floats: exact below 2**24 (fp32) / 2**53, and float gathers ran ~3x faster than
        # int64 ones on these sizes.
        exact = torch.float32 if cells < 2**24 else torch.float64
        y_part = ((bins * (k * b) + scene) * hf + yi) * wf
        x_part = bins * (b * hf * wf) + xi
        # Bag layout (ky, kx, sy, sx, cy, cx): bin, sub-sample, then corner (y-major); the picks say which per-axis
        # entry each of the K*K*S*S*4 bag entries uses.
        ypick, xpick = _bag_picks(k, s, pos.device)
        flat = y_part.to(exact).index_select(1, ypick) + x_part.to(exact).index_select(1, xpick)
        wts = wx.index_select(1, xpick) * wy.index_select(1, ypick)
        v = F.embedding_bag(
            flat.to(torch.int32 if cells < 2**31 else torch.int64),
            proj.view(-1, dv),
            per_sample_weights=wts.to(proj.dtype),
            mode="sum",
        )
        v = v.view(r, big_l, dv) + self.embed.bias
        return v if agent_major else v.transpose(0, 1)

    def _boxes_agent_major(self, pos: Tensor, batch: Batch, rows: Tensor) -> Tensor:
        """``boxes`` for pos (R, L, 2) -> (R, L, 4), elementwise (einsum's batched 2x2 matmuls were ~10x slower)."""
        sc = batch.scene[rows]
        aff = batch.frame_to_px[sc][:, None]  # (R, 1, 2, 3)
        px = aff[..., 0] * pos[..., 0:1] + aff[..., 1] * pos[..., 1:2] + aff[..., 2]
        centre = px / BACKBONE_STRIDE
        half = (self.half_size_m * batch.px_per_m[sc] / BACKBONE_STRIDE)[:, None, None]
        return torch.cat((centre - half, centre + half), dim=-1)


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


@dataclass
class Prediction:
    """Decoder output.

    Attributes:
        positions: (M, R, T_pred - T_obs, 2) model-frame metres p̂^(T_obs+1 .. T_pred).
        rows: (R,) batch rows that were decoded (the agents observed at the current step).
    """

    positions: Tensor
    rows: Tensor


class TrajectoryNet(nn.Module):
    """The full predictor: AIN + EN + prediction network (eqs. 1-22). Outputs model-frame positions."""

    def __init__(self, config: ModelConfig, *, load_backbone: bool = True) -> None:
        super().__init__()
        self.config = config
        feats, d, hid = config.features, config.embed_dim, config.lstm_dim
        self.ain = AgentInteractionNet(config)
        self.env = EnvironmentNet(config) if feats.environment else None
        if self.env is not None and config.backbone_weights and load_backbone:
            self.env.backbone.load_torchvision_state_dict(read_state_dict(Path(config.backbone_weights)))
        d_fst = self.ain.out_dim
        self.attention = nn.Linear(2, d_fst) if d_fst else None  # eq. 13, W_c, b_c
        self.disp_embed = nn.Linear(2, d)  # eqs. 15/17, W_p, b_p
        lstm_in = d + (d if self.env is not None else 0) + d_fst
        self.encoder = nn.LSTMCell(lstm_in, hid)  # eq. 16, LSTM_E
        self.decoder = nn.LSTMCell(lstm_in, hid)  # eq. 18, LSTM_D
        self.out = nn.Linear(hid, 2)  # eq. 19, W_u, b_u
        self.init_decoder = nn.Linear(hid + config.noise_dim, hid)  # eqs. 21-22, W_phi, b_phi
        self.mode_gate = nn.Linear(hid, 1) if config.mode_gate else None  # see ModelConfig.mode_gate

    def _q(self, fst: Tensor | None, scene: Tensor, pos_scaled: Tensor) -> Tensor | None:
        """Eqs. 13-14: q_i = fst ⊙ σ(W_c p_i + b_c); fst (L, B, d_fst), pos (L, R, 2) -> (L, R, d_fst)."""
        if fst is None or self.attention is None:
            return None
        return fst[:, scene] * torch.sigmoid(self.attention(pos_scaled))

    def _env(self, proj: Tensor | None, pos: Tensor, batch: Batch, rows: Tensor) -> Tensor:
        """v (L, R, d_v): eqs. 11-12 at pos (L, R, 2); zero for scenes without a raster."""
        if proj is None or self.env is None:
            return pos.new_zeros(*pos.shape[:2], self.config.embed_dim)
        # Positions are detached: the map is a lookup of context, not a path for position gradients.
        v = self.env(proj, pos.detach(), batch, rows)
        return torch.where(batch.has_raster[batch.scene[rows]][None, :, None], v, torch.zeros_like(v))

    def encode(self, batch: Batch, feature_map: Tensor | None = None) -> Encoded:
        """Run LSTM_E (eq. 16) and the AIN GRU over the observed steps t = 1 .. T_obs; ``feature_map``: the
        backbone's maps of ``batch.raster`` when the caller has them (``feature_cache``), else computed here."""
        cfg = self.config
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
        e_p = self.disp_embed(disp / ds)  # (T_obs, N, d): eq. 15 for all steps at once
        # Ego track per scene, used by EMF/ETF and by the decoder's ego override.
        ego_rows = batch.ego.nonzero().squeeze(1)
        ego_pos = batch.positions.new_zeros(b, batch.positions.shape[1], 2)
        ego_pos[batch.scene[ego_rows]] = batch.positions[ego_rows]
        ego_ok = batch.valid.new_zeros(b, batch.positions.shape[1])
        ego_ok[batch.scene[ego_rows]] = batch.valid[ego_rows]
        m_all = f_all = None
        if self.ain.ego_motion is not None:
            ego_disp = torch.zeros_like(ego_pos)
            ego_disp[:, 1:] = ego_pos[:, 1:] - ego_pos[:, :-1]
            ego_disp_ok = torch.zeros_like(ego_ok)
            ego_disp_ok[:, 1:] = ego_ok[:, 1:] & ego_ok[:, :-1]
            m_all = self.ain.ego_motion(ego_disp / ds, ego_disp_ok)  # eq. 5, (B, T, d)
        if self.ain.ego_trajectory is not None:
            f_all = self.ain.ego_trajectory(ego_pos / ps, ego_ok)  # eqs. 8-9, (B, T, d)
        o_all = None
        if self.ain.position is not None:  # eqs. 1-2 for all observed steps at once: (T_obs, B, d)
            o_all = self.ain.position(obs / ps, ok, batch, rows)
        proj = v_all = None
        if self.env is not None:
            if batch.raster is not None:
                fmap = self.env.feature_map(batch.raster) if feature_map is None else feature_map
                proj = self.env.project(fmap)
            v_all = self._env(proj, obs, batch, rows)  # (T_obs, N, d_v)
            v_all = torch.where(ok[..., None], v_all, torch.zeros_like(v_all))
        gate = torch.sigmoid(self.attention(obs / ps)) if self.attention is not None else None  # eq. 13
        hid = cfg.lstm_dim
        h = obs.new_zeros(n, hid)
        c = obs.new_zeros(n, hid)
        h_gru = obs.new_zeros(b, cfg.gru_dim) if self.ain.gru is not None else None
        lstm_e = lstm_weights(self.encoder)
        for t in range(t_obs):
            ok_t = ok[t]
            r = None
            if self.ain.tracking is not None:  # eqs. 3-4 on h_e^(t-1)
                r = self.ain.tracking(h[None], ok_t[None], batch, rows)[0]
            m_t = None if m_all is None else m_all[:, t]
            parts = [x for x in (None if o_all is None else o_all[t], r, m_t) if x is not None]
            fst, h_gru = self.ain.step(parts, None if f_all is None else f_all[:, t], h_gru)
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

    def decode(self, batch: Batch, enc: Encoded, noise: Tensor,
               constant_velocity_modes: int | None = None) -> Prediction:
        """Eqs. 17-22 for M modes of the rows observed at the current step.

        Args:
            batch: the batch that was encoded.
            enc: ``encode(batch)``.
            noise: (M, R, noise_dim) Gaussian z of eq. 21, R = number of active rows.
            constant_velocity_modes: the first this many modes get no step outputs (see ``_mode_open``;
                None: the config's).
        """
        cfg = self.config
        ps, ds = cfg.pos_scale_m, cfg.disp_scale_m
        t_obs = batch.obs_len
        rows = batch.active.nonzero().squeeze(1)
        mm, r, _ = noise.shape
        b = batch.size
        hid = cfg.lstm_dim
        scene = batch.scene[rows]
        every = torch.ones(mm, r, dtype=torch.bool, device=noise.device)
        h = self.init_decoder(torch.cat((enc.h[rows][None].expand(mm, r, hid), noise), dim=-1))  # eqs. 21-22
        mode_open = self._mode_open(h, constant_velocity_modes, mode_dim=0)  # (M, R, 1)
        c = enc.c[rows][None].expand(mm, r, hid).reshape(mm * r, hid)
        h_gru = None if enc.h_gru is None else enc.h_gru[None].expand(mm, b, -1).reshape(mm * b, -1)
        ego_ok = (batch.ego[rows][:, None] & enc.ego_ok[scene]) if cfg.features.uses_ego_plan else None
        p_prev = batch.positions[rows, t_obs - 2][None].expand(mm, r, 2)
        p_cur = batch.positions[rows, t_obs - 1][None].expand(mm, r, 2)
        carried = self._carried_first_step(batch, rows)
        basis = self._agent_output_basis(carried)
        outputs: list[Tensor] = []
        lstm_d = lstm_weights(self.decoder)
        for k in range(cfg.pred_len):
            if k > 0:  # one LSTM_D step at t = T_obs + k on the predicted positions
                t = t_obs - 1 + k
                f_t = None if enc.f_all is None else enc.f_all[None, :, t].expand(mm, b, -1).reshape(mm * b, -1)
                if cfg.interaction_while_decoding:
                    parts = []
                    if self.ain.position is not None:
                        parts.append(self.ain.position(p_cur / ps, every, batch, rows).reshape(mm * b, -1))
                    if self.ain.tracking is not None:  # h_d^(t-1)
                        parts.append(self.ain.tracking(h, every, batch, rows).reshape(mm * b, -1))
                    if enc.m_all is not None:
                        parts.append(enc.m_all[None, :, t].expand(mm, b, -1).reshape(mm * b, -1))
                    fst, h_gru = self.ain.step(parts, f_t, h_gru)
                else:  # the AIN's state as observed at T_obs
                    fst = self.ain.output(f_t, h_gru)
                x = [self.disp_embed((p_cur - p_prev) / ds)]  # eq. 17
                if self.env is not None:
                    x.append(self._env(enc.proj, p_cur, batch, rows))
                q = self._q(None if fst is None else fst.view(mm, b, -1), scene, p_cur / ps)
                if q is not None:
                    x.append(q)
                h_flat, c = lstm_step(lstm_d, torch.cat(x, dim=-1).reshape(mm * r, -1), h.reshape(mm * r, hid), c)
                h = h_flat.view(mm, r, hid)  # eq. 18
            o = self.out(h) if mode_open is None else self.out(h) * mode_open  # mode_gate, constant_velocity_modes
            # eqs. 19-20; agent_velocity_change reads o_t in the agent's frame and speed units
            p_next = p_cur + (o * ds if basis is None else torch.einsum("mrj,rij->mri", o, basis))
            if carried is not None:  # the velocity-change outputs: o_t corrects a constant-velocity step
                p_next = p_next + (carried[None] if k == 0 else p_cur - p_prev)
            if ego_ok is not None:  # the ego follows its given (planned) future
                given = ego_ok[:, t_obs + k]
                p_next = torch.where(given[None, :, None], enc.ego_pos[scene, t_obs + k][None], p_next)
            outputs.append(p_next)
            p_prev, p_cur = p_cur, p_next
        return Prediction(torch.stack(outputs, dim=2), rows)

    @torch.no_grad()
    def decode_fast(self, batch: Batch, enc: Encoded, noise: Tensor,
                    constant_velocity_modes: int | None = None) -> Prediction:
        """``decode`` for inference (no autograd): the same equations, restructured for speed; outputs equal
        ``decode``'s up to float rounding (tested against it).

        * Agent-major (R, M) rows: the decoded rows are sorted by scene (``collate``), so each scene's agents x
          modes form one contiguous block; the per-scene max-pools are segment reductions over the agents that
          are decoded (no padded (B, A_max) grid, no mask), and q's scene lookup is a block repeat.
        * One input buffer [displacement | v | q | h] per step for the fused LSTM matmul, filled in place (no
          cats); eq. 17's W_p is folded into LSTM_D's input weights (two inputs instead of d_p) and the gates
          are reordered to (i, f, o, g) so one sigmoid and one tanh cover them.
        """
        cfg = self.config
        ps, ds = cfg.pos_scale_m, cfg.disp_scale_m
        t_obs = batch.obs_len
        rows = batch.active.nonzero().squeeze(1)
        mm, r, _ = noise.shape
        b = batch.size
        hid = cfg.lstm_dim
        scene = batch.scene[rows]
        if r > 1 and bool((scene[1:] < scene[:-1]).any()):
            raise ValueError("decode_fast needs the rows of a scene together, in scene order (collate's layout)")
        per_scene = torch.bincount(scene, minlength=b)
        empty = (per_scene == 0)[:, None, None] if bool((per_scene == 0).any()) else None

        def pool(x: Tensor) -> Tensor:
            """Per-scene max over the decoded agents: (R, M, d) -> (B * M, d), zero for a scene without any."""
            out = torch.segment_reduce(x, "max", lengths=per_scene, axis=0)
            if empty is not None:
                out = out.masked_fill(empty, 0.0)
            return out.reshape(b * mm, -1)

        w, bias = lstm_weights(self.decoder)
        d_p = self.disp_embed.out_features
        # Gates (i, f, g, o) -> (i, f, o, g); eq. 17's embedding folded into the input weights.
        order = torch.cat([torch.arange(lo * hid, hi * hid, device=w.device) for lo, hi in ((0, 2), (3, 4), (2, 3))])
        w, bias = w[:, order], bias[order]
        # The bias is a weight row over a constant-1 input column: addmm's broadcast copy of it cost ~half
        # of the matmul here.
        w_in = torch.cat((self.disp_embed.weight.t() @ w[:d_p], w[d_p:], (bias + self.disp_embed.bias @ w[:d_p])[None]))
        width = w_in.shape[0]
        n_env = self.config.embed_dim if self.env is not None else 0
        n_q = self.ain.out_dim if self.attention is not None else 0
        buf = noise.new_empty(r * mm, width)  # [disp (2) | v | q | h | 1]
        buf[:, -1] = 1.0
        disp = buf[:, :2].view(r, mm, 2)
        env_in = buf[:, 2 : 2 + n_env].view(r, mm, n_env)
        q_in = buf[:, 2 + n_env : 2 + n_env + n_q].view(r, mm, n_q)
        h = buf[:, width - 1 - hid : width - 1]
        h.copy_(self.init_decoder(torch.cat((enc.h[rows][:, None].expand(r, mm, hid), noise.transpose(0, 1)), -1))
                .view(r * mm, hid))  # eqs. 21-22
        mode_open = self._mode_open(h.view(r, mm, hid), constant_velocity_modes, mode_dim=1)  # (R, M, 1)
        c = enc.c[rows].repeat_interleave(mm, dim=0)
        h_gru = None if enc.h_gru is None else enc.h_gru.repeat_interleave(mm, dim=0)  # (B * M, G)
        ego_ok = (batch.ego[rows][:, None] & enc.ego_ok[scene]) if cfg.features.uses_ego_plan else None
        raster_ok = batch.has_raster[scene][:, None, None]
        all_raster = bool(raster_ok.all())
        p_prev = batch.positions[rows, t_obs - 2][:, None].expand(r, mm, 2)
        p_cur = batch.positions[rows, t_obs - 1][:, None].expand(r, mm, 2)
        carried = self._carried_first_step(batch, rows)
        basis = self._agent_output_basis(carried)
        outputs = noise.new_empty(r, mm, cfg.pred_len, 2)
        for k in range(cfg.pred_len):
            if k > 0:  # one LSTM_D step at t = T_obs + k on the predicted positions
                t = t_obs - 1 + k
                pos_scaled = p_cur / ps
                f_t = None if enc.f_all is None else enc.f_all[:, None, t].expand(b, mm, -1).reshape(b * mm, -1)
                if cfg.interaction_while_decoding:
                    parts = []
                    if self.ain.position is not None:
                        parts.append(pool(self.ain.position.embed(pos_scaled)))
                    if self.ain.tracking is not None:  # h_d^(t-1)
                        parts.append(pool(self.ain.tracking.embed(h).view(r, mm, -1)))
                    if enc.m_all is not None:
                        parts.append(enc.m_all[:, None, t].expand(b, mm, -1).reshape(b * mm, -1))
                    fst, h_gru = self.ain.step(parts, f_t, h_gru)
                else:  # the AIN's state as observed at T_obs
                    fst = self.ain.output(f_t, h_gru)
                torch.div(p_cur - p_prev, ds, out=disp)  # eq. 17 (W_p folded into LSTM_D)
                if self.env is not None:
                    v = self._env_fast(enc.proj, p_cur, batch, rows)
                    env_in.copy_(v if all_raster else torch.where(raster_ok, v, torch.zeros_like(v)))
                if n_q and fst is not None and self.attention is not None:  # eqs. 13-14
                    gate = torch.sigmoid(self.attention(pos_scaled))
                    torch.mul(fst.view(b, mm, -1).repeat_interleave(per_scene, dim=0), gate, out=q_in)
                for lo in range(0, r * mm, _LSTM_CHUNK_ROWS):  # eq. 18, in cache-sized row blocks
                    hi = min(lo + _LSTM_CHUNK_ROWS, r * mm)
                    gates = torch.mm(buf[lo:hi], w_in)
                    sig = torch.sigmoid(gates[:, : 3 * hid])
                    c_blk = c[lo:hi]
                    c_blk.mul_(sig[:, hid : 2 * hid]).addcmul_(sig[:, :hid], torch.tanh(gates[:, 3 * hid :]))
                    torch.mul(sig[:, 2 * hid :], torch.tanh(c_blk), out=h[lo:hi])
            o = self.out(h).view(r, mm, 2)
            if mode_open is not None:  # ModelConfig.mode_gate, constant_velocity_modes
                o = o * mode_open
            p_next = p_cur + (o * ds if basis is None else torch.einsum("rmj,rij->rmi", o, basis))  # eqs. 19-20
            if carried is not None:
                p_next = p_next + (carried[:, None] if k == 0 else p_cur - p_prev)
            if ego_ok is not None:  # the ego follows its given (planned) future
                given = ego_ok[:, t_obs + k]
                p_next = torch.where(given[:, None, None], enc.ego_pos[scene, t_obs + k][:, None], p_next)
            outputs[:, :, k] = p_next
            p_prev, p_cur = p_cur, p_next
        return Prediction(outputs.transpose(0, 1), rows)

    def _carried_first_step(self, batch: Batch, rows: Tensor) -> Tensor | None:
        """(R, 2) last observed displacement p_(T_obs) - p_(T_obs - 1) that the velocity-change step outputs
        carry into the first predicted step (zero where p_(T_obs - 1) is unobserved); None otherwise."""
        if self.config.step_output == "displacement":
            return None
        t_obs = batch.obs_len
        step = batch.positions[rows, t_obs - 1] - batch.positions[rows, t_obs - 2]
        return torch.where(batch.valid[rows, t_obs - 2][:, None], step, torch.zeros_like(step))

    def _agent_output_basis(self, carried: Tensor | None) -> Tensor | None:
        """(R, 2, 2) map of ``agent_velocity_change``'s o_t = (along, across) to model-frame metres: columns
        s e and s e_perp, e the direction of the last observed step (+x where it is zero) and s its length
        floored at ``agent_min_step_m``; None for the other step outputs."""
        if self.config.step_output != "agent_velocity_change" or carried is None:
            return None
        length = torch.linalg.vector_norm(carried, dim=-1, keepdim=True)
        unit = torch.where(length > 1e-6, carried / length.clamp(min=1e-6), carried.new_tensor([1.0, 0.0]))
        s = length.clamp(min=self.config.agent_min_step_m)
        along = unit * s
        across = torch.stack((-along[:, 1], along[:, 0]), dim=-1)
        return torch.stack((along, across), dim=-1)

    def _env_fast(self, proj: Tensor | None, pos: Tensor, batch: Batch, rows: Tensor) -> Tensor:
        """v (R, M, d_v) at agent-major positions pos (R, M, 2); zero without maps."""
        if proj is None or self.env is None:
            return pos.new_zeros(*pos.shape[:2], self.config.embed_dim)
        v: Tensor = self.env(proj, pos, batch, rows, agent_major=True)
        return v

    def _mode_open(self, h0: Tensor, constant_velocity_modes: int | None, mode_dim: int) -> Tensor | None:
        """The factor (..., 1) on each mode's step outputs o_t, from the decoder's initial state ``h0`` whose
        modes run along ``mode_dim``: the mode gate (``ModelConfig.mode_gate``), times 0 for the first
        ``constant_velocity_modes`` modes. With a velocity-change output such a mode is exactly the
        constant-velocity forecast (standing still for an agent standing still), a mode the learned gate may
        never reach; None when every factor is 1. ``constant_velocity_modes`` None: the config's
        (``ModelConfig.held_modes``)."""
        gate = None if self.mode_gate is None else torch.sigmoid(self.mode_gate(h0))
        num_modes = h0.shape[mode_dim]
        if constant_velocity_modes is None:
            constant_velocity_modes = self.config.held_modes(num_modes)
        if constant_velocity_modes == 0:
            return gate
        if self.config.step_output == "displacement":
            raise ConfigError("constant-velocity modes need a velocity-change step_output; with 'displacement' "
                              "a zero output means standing still, not constant velocity")
        if not 0 < constant_velocity_modes <= num_modes:
            raise ConfigError(f"constant_velocity_modes must be in 0..{num_modes} (the modes drawn), "
                              f"got {constant_velocity_modes}")
        shape = [1] * h0.dim()
        shape[mode_dim] = num_modes
        keep = (torch.arange(num_modes, device=h0.device) >= constant_velocity_modes).to(h0.dtype).view(shape)
        return keep if gate is None else gate * keep

    def _noise_per_sample(self, batch: Batch, num_modes: int, sample_seeds: Sequence[int]) -> Tensor:
        """(M, R, noise_dim) z of the active rows, each sample's rows (in row order) from its own seed (on the CPU)."""
        of_row = batch.sample[batch.active.cpu().numpy()]
        noise = torch.empty(num_modes, len(of_row), self.config.noise_dim)
        if len(sample_seeds) != len(batch.sample_targets):
            raise ValueError(f"{len(sample_seeds)} sample seeds for {len(batch.sample_targets)} samples")
        bounds = np.searchsorted(of_row, np.arange(len(sample_seeds) + 1))  # rows are grouped by sample, in order
        for i, seed in enumerate(sample_seeds):
            lo, hi = int(bounds[i]), int(bounds[i + 1])
            if hi > lo:
                gen = torch.Generator().manual_seed(seed)
                noise[:, lo:hi] = torch.randn(num_modes, hi - lo, self.config.noise_dim, generator=gen)
        return noise

    def forward(
        self, batch: Batch, num_modes: int, generator: torch.Generator | None = None, *, fast: bool = False,
        noise_scale: float = 1.0, constant_velocity_modes: int | None = None,
        sample_seeds: Sequence[int] | None = None,
    ) -> Prediction:
        """Predictions for ``num_modes`` noise draws z (one per mode and agent); ``fast``: ``decode_fast``
        (inference only). ``noise_scale``: z ~ N(0, noise_scale^2 I) instead of eq. 21's N(0, I), a sampling
        setting (spread of the K futures) for inference, chosen on validation data like a sampler's.
        ``constant_velocity_modes``: the first this many modes are held to constant velocity (their step
        outputs zeroed; see ``_mode_open``; None: ``ModelConfig.constant_velocity_modes``, also used in
        training), an inference setting to choose on validation data. ``sample_seeds``: one seed per input
        sample (``Batch.sample``); each sample's z is drawn from its own generator, so its forecasts do not
        depend on which other samples share the batch (else z comes from ``generator``)."""
        r = int(batch.active.sum())
        if sample_seeds is None:
            noise = torch.randn(num_modes, r, self.config.noise_dim, generator=generator)
        else:
            noise = self._noise_per_sample(batch, num_modes, sample_seeds)
        # z is drawn on the CPU generators whatever the device, so a seed gives the same z on every device.
        noise = noise.to(batch.positions.device)
        if noise_scale != 1.0:
            noise = noise * noise_scale
        enc = self.encode(batch)
        decode = self.decode_fast if fast else self.decode
        return decode(batch, enc, noise, constant_velocity_modes)
