"""Agent Interaction Network (AIN), eqs. 1-10 of Zhu et al. (IJCAI 2020): the position feature o (eqs. 1-2),
the tracking feature r (eqs. 3-4), the ego-motion feature m (eq. 5), the GRU over them and its embedding st
(eqs. 6-7), the future ego-trajectory feature f (eqs. 8-9) and the AIN output fst = Cat(f, st) (eq. 10).

Positions are model-frame and scaled by ``ModelConfig.pos_scale_m`` (displacements by ``disp_scale_m``) before
they reach these layers. Agents are flattened rows (``batching.Batch``); every max-pool over a scene's agents
is ``scene_max``: rows are scattered into a (B, A_max) grid whose empty cells and masked rows are -inf, so
padding cannot win the max.
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

from ..training.row_blocks import RowLinear, gru_cell
from .batching import Batch
from .config import ModelConfig


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


class PositionFeature(nn.Module):
    """PF, eqs. 1-2: o^(t) = Maxpool_i(W_o p_i^(t) + b_o)."""

    def __init__(self, dim: int) -> None:
        super().__init__()
        self.embed = RowLinear(2, dim)  # W_o, b_o

    def forward(self, pos: Tensor, mask: Tensor, batch: Batch, rows: Tensor) -> Tensor:
        """pos (L, R, 2) scaled positions of ``rows``, mask (L, R) -> o (L, B, d_o)."""
        return scene_max(self.embed(pos), mask, batch, rows)


class TrackingFeature(nn.Module):
    """TF, eqs. 3-4: r^(t) = Maxpool_i(W_r h_i + b_r) over the LSTM hidden states."""

    def __init__(self, hidden: int, dim: int) -> None:
        super().__init__()
        self.embed = RowLinear(hidden, dim)  # W_r, b_r

    def forward(self, hidden: Tensor, mask: Tensor, batch: Batch, rows: Tensor) -> Tensor:
        """hidden (L, R, H) of ``rows``, mask (L, R) -> r (L, B, d_r)."""
        return scene_max(self.embed(hidden), mask, batch, rows)


class EgoMotionFeature(nn.Module):
    """EMF, eq. 5: m^(t) = W_m (p_0^(t) - p_0^(t-1)) + b_m; zero where the scene has no ego step."""

    def __init__(self, dim: int) -> None:
        super().__init__()
        self.embed = RowLinear(2, dim)  # W_m, b_m

    def forward(self, disp: Tensor, ok: Tensor) -> Tensor:
        """disp (..., 2) scaled ego displacement, ok (...) -> (..., d_m)."""
        out = self.embed(disp)
        return torch.where(ok[..., None], out, torch.zeros_like(out))


class EgoTrajectoryFeature(nn.Module):
    """ETF, eqs. 8-9: f^(t) = Maxpool_{k in [t+1, T_pred]}(W_f p_0^(k) + b_f)."""

    def __init__(self, dim: int) -> None:
        super().__init__()
        self.embed = RowLinear(2, dim)  # W_f, b_f

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
        self.st = RowLinear(config.gru_dim, d) if gru_in else None  # eq. 7, W_s, b_s
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
            h_gru = gru_cell(self.gru, torch.cat(parts, dim=-1), h_gru)  # eq. 6
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
