"""The residual driving network (our extension of the paper, issue 57): corrections to a kinematic prior, read in
each target's own frame (``model.residual.inputs``).

Parts, named after the paper's where they play the same role:

* target encoder: an MLP over the target's own track and motion (the paper's LSTM encoder of the agent's history,
  eq. 16, as a feed-forward layer over the whole window);
* interaction: an MLP per neighbour, max-pooled over the neighbours (the paper's max-pooled position features,
  eqs. 1-2, and the neighbours' recent motion standing in for its LSTM tracking features, eqs. 3-4), per target;
* environment net (EN, optional): a CNN over the target's map crop in its own frame (the paper's ResNet18 stages
  1-2 + ROIAlign, eqs. 10-12, read instead around and ahead of each target, so a lane reads the same whichever way
  the raster was drawn);
* heads: the mean residual (K = 1, trained on the displacement error itself) and ``modes`` residual modes with
  scores (trained best-of-K, the paper's eq. 23 with fixed heads in place of noise draws, plus a cross-entropy
  on which mode was best).

Residuals are (T_pred, 2) in the target's frame in units of its scale L; all heads start at zero, so an untrained
network is the prior exactly, and a network that has learned nothing for a situation stays near it.

At inference a target's forecast does not depend on the batch it shares (issue 35's promise, kept as for the
paper's network): every linear layer runs ``row_blocks.row_mm`` (``RowLinear``, same parameters and keys) and the
environment CNN runs on zero-padded blocks of a fixed ``CONV_BLOCK`` crops, so every convolution sees one shape.
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

from ..training.row_blocks import RowLinear
from .config import ResidualConfig
from .inputs import CROP_CHANNELS, feature_width, neighbour_width

CONV_BLOCK = 32
"""Crops per environment-net call at inference: oneDNN picks a convolution's algorithm by the batch size, so
every call gets this one shape (the tail zero-padded)."""


class ResidualNet(nn.Module):
    """Inputs of N targets → (mean residual (N, T, 2), mode residuals (N, K, T, 2), mode logits (N, K))."""

    def __init__(self, config: ResidualConfig) -> None:
        super().__init__()
        self.config = config
        h, t = config.hidden, config.pred_len
        self.target = nn.Sequential(RowLinear(feature_width(config), h), nn.ReLU(), RowLinear(h, h), nn.ReLU())
        self.neighbour = nn.Sequential(RowLinear(neighbour_width(config), h // 2), nn.ReLU(),
                                       RowLinear(h // 2, h // 2), nn.ReLU())
        width = h + h // 2
        self.environment: nn.Sequential | None = None
        if config.environment:
            cells = config.crop_px // 16
            self.environment = nn.Sequential(
                nn.Conv2d(len(CROP_CHANNELS), 32, 3, 2, 1), nn.ReLU(), nn.Conv2d(32, 64, 3, 2, 1), nn.ReLU(),
                nn.Conv2d(64, 64, 3, 2, 1), nn.ReLU(), nn.Conv2d(64, 64, 3, 2, 1), nn.ReLU(), nn.Flatten(),
                RowLinear(64 * cells * cells, h), nn.ReLU())
            width += h
        g = config.head_hidden
        self.fuse = nn.Sequential(RowLinear(width, g), nn.ReLU(), RowLinear(g, g), nn.ReLU())
        self.mean = RowLinear(g, t * 2)
        self.modes = RowLinear(g, config.modes * t * 2)
        self.logits = RowLinear(g, config.modes)
        for head in (self.mean, self.modes):  # start at the prior
            nn.init.zeros_(head.weight)
            nn.init.zeros_(head.bias)

    def forward(self, features: Tensor, neighbours: Tensor, mask: Tensor, crops: Tensor | None
                ) -> tuple[Tensor, Tensor, Tensor]:
        """See the class docstring; ``mask`` (N, K) marks real neighbours (the pool ignores the padding)."""
        parts = [self.target(features)]
        pooled = self.neighbour(neighbours).masked_fill(~mask[..., None], 0.0)
        parts.append(pooled.max(dim=1).values if pooled.shape[1] else pooled.new_zeros(len(features), 0))
        if self.environment is not None:
            if crops is None:
                raise ValueError("the environment net needs crops")
            parts.append(self._environment(crops))
        z = self.fuse(torch.cat(parts, dim=1))
        t, k = self.config.pred_len, self.config.modes
        return self.mean(z).view(-1, t, 2), self.modes(z).view(-1, k, t, 2), self.logits(z)

    def _environment(self, crops: Tensor) -> Tensor:
        assert self.environment is not None
        if torch.is_grad_enabled() or not len(crops):
            return self.environment(crops)  # type: ignore[no-any-return]
        rows = len(crops)
        padded = crops.new_zeros(rows + (-rows) % CONV_BLOCK, *crops.shape[1:])
        padded[:rows] = crops
        blocks = [self.environment(padded[lo : lo + CONV_BLOCK]) for lo in range(0, len(padded), CONV_BLOCK)]
        return torch.cat(blocks)[:rows]


def displacement_errors(residual: Tensor, truth: Tensor, scale: Tensor) -> Tensor:
    """Per target (and mode) ADE + FDE in metres of residuals against the truth's residual: (N, ..., T, 2) in
    units of L, ``scale`` (N,) metres."""
    dist = (residual - truth).norm(dim=-1) * scale.view(-1, *([1] * (residual.dim() - 2)))
    total: Tensor = dist.mean(dim=-1) + dist[..., -1]
    return total


def training_loss(outputs: tuple[Tensor, Tensor, Tensor], truth: Tensor, scale: Tensor,
                  score_weight: float) -> Tensor:
    """The mean head's ADE + FDE, the best mode's (best-of-K, eq. 23 with fixed heads), and the cross-entropy
    of the scores on which mode was best; errors in units of 5 m so the terms weigh alike."""
    mean, modes, logits = outputs
    mean_error = displacement_errors(mean, truth, scale)
    mode_errors = displacement_errors(modes, truth[:, None], scale)
    best = mode_errors.argmin(dim=1)
    picked = mode_errors.gather(1, best[:, None])[:, 0]
    score = nn.functional.cross_entropy(logits, best)
    loss: Tensor = (mean_error.mean() + picked.mean()) / 5.0 + score_weight * score
    return loss
