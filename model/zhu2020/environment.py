"""Environment Network (EN), eqs. 11-12 of Zhu et al. (IJCAI 2020): ResNet18 stages 1-2 (``backbone``) on the
ego-centred map raster, ROIAlign over the 2 R_s square around each agent (G_i, C x K x K), flattened (eq. 11)
and embedded to d_v (eq. 12).

Positions are model-frame metres; ``Batch.frame_to_px`` maps them to raster pixels and ``BACKBONE_STRIDE`` to
feature-map cells.
"""

from __future__ import annotations

import torch
from torch import Tensor, nn
from torch.nn import functional as F  # noqa: N812

from ..training.row_blocks import RowLinear
from .backbone import (
    BACKBONE_CHANNELS,
    BACKBONE_STRIDE,
    ResNet18Stages12,
    backbone_runs_bf16,
    roi_align,
)
from .batching import Batch
from .config import ModelConfig


def _bag_picks(k: int, s: int, device: torch.device) -> tuple[Tensor, Tensor]:
    """For the bag entries (ky, kx, sy, sx, cy, cx) of ``EnvironmentNet.forward``, the index into the per-axis
    (K*S*2) y and x entries (on ``device``)."""
    per_axis = torch.arange(k * s * 2, device=device).view(k, s, 2)
    full = (k, k, s, s, 2, 2)
    ypick = per_axis.view(k, 1, s, 1, 2, 1).expand(full).reshape(-1)
    xpick = per_axis.view(1, k, 1, s, 1, 2).expand(full).reshape(-1)
    return ypick, xpick


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
        self.backbone = ResNet18Stages12(config.raster_channels, use_bf16=backbone_runs_bf16(config))
        self.pool_size = config.roi_pool
        self.sampling = config.roi_sampling
        self.half_size_m = config.roi_half_size_m
        self.embed = RowLinear(BACKBONE_CHANNELS * config.roi_pool**2, config.embed_dim)  # W_v, b_v
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
        """(B, C, h, w) -> (B, h, w, K*K, d_v): W_v's slice for each ROI bin applied to the map.

        The 1/S^2 of the bin average is folded in here so ``forward`` can sum. One (B*h*w, C) x (C, K*K*d_v)
        product lays the result out as stored, so only the (smaller) map is transposed: half the time of the
        bin-major layout's batched product and copy, and the same values.
        """
        b, c, h, w = fmap.shape
        kk = self.pool_size**2
        weight = self.embed.weight.view(-1, c, kk) / self.sampling**2  # Reshape(G) = (C, K, K)
        cells = fmap.permute(0, 2, 3, 1).reshape(b * h * w, c)
        return (cells @ weight.permute(1, 2, 0).reshape(c, kk * weight.shape[0])).view(b, h, w, kk, -1)

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
        b, hf, wf, kk, dv = proj.shape
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
        # Flat cell = ((scene * h + y) * w + x) * K*K + bin row * K + bin column
        #           = y part (scene, y, bin row) + x part (x, bin column).
        bins = torch.arange(k, dtype=pos.dtype, device=pos.device).repeat_interleave(2 * s)  # bin of each entry
        scene = batch.scene[rows].to(pos.dtype).repeat_interleave(big_l)[:, None]
        cells = kk * b * hf * wf
        # Integer arithmetic in floats: exact below 2**24 (fp32) / 2**53, and float gathers ran ~3x faster than
        # int64 ones on these sizes.
        exact = torch.float32 if cells < 2**24 else torch.float64
        y_part = (scene * hf + yi) * (wf * kk) + bins * k
        x_part = xi * kk + bins
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
