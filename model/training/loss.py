"""Best-of-H loss (eq. 23) and best-of-K displacement metrics."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor


def best_of_h_loss(
    pred: Tensor, truth: Tensor, mask: Tensor, scene: Tensor, num_scenes: int, reduce: str = "scene"
) -> tuple[Tensor, Tensor]:
    """Eq. 23: L = 1/(N T) min_i sum_j sum_t ||p̂_{j,i}^(t) - p_j^(t)||^2.

    The min picks one mode per scene (``reduce="scene"``, the paper: the error is summed over the scene's
    targets j before the min over modes i) or per target (``"agent"``). Only the picked mode enters the
    loss, so the gradient reaches only that mode (``argmin`` is not differentiable, ``gather`` routes).

    Args:
        pred: (M, R, T, 2) predictions of R agent rows.
        truth: (R, T, 2) ground truth (any finite value where ``mask`` is False).
        mask: (R,) targets with a complete ground-truth future.
        scene: (R,) scene index of each row.
        num_scenes: B.
        reduce: ``scene`` or ``agent``.

    Returns:
        (loss, best): the batch sum of the picked errors divided by (targets x T), and the picked mode
        indices, (B,) or (R,).
    """
    t = pred.shape[2]
    sq = ((pred - truth[None]) ** 2).sum(dim=(-1, -2))  # (M, R): sum over steps and x, y
    sq = torch.where(mask[None], sq, torch.zeros_like(sq))
    n = mask.sum().clamp(min=1) * t
    if reduce == "scene":
        err = sq.new_zeros(sq.shape[0], num_scenes).index_add(1, scene, sq)  # (M, B)
        best = err.detach().argmin(dim=0)
        return err.gather(0, best[None]).sum() / n, best
    if reduce == "agent":
        best = sq.detach().argmin(dim=0)  # (R,)
        return sq.gather(0, best[None]).sum() / n, best
    raise ValueError(f"reduce must be 'scene' or 'agent', got {reduce!r}")


@dataclass
class DisplacementErrors:
    """Sums of per-target best-of-K errors in metres, to be averaged over ``count``.

    Attributes:
        ade_sum: sum over targets of min over modes of the mean Euclidean error over steps.
        fde_sum: sum over targets of min over modes of the final-step Euclidean error (the min is taken
            separately from ADE's, as Social-GAN reports).
        count: number of targets.
    """

    ade_sum: float = 0.0
    fde_sum: float = 0.0
    count: int = 0

    def add(self, pred: Tensor, truth: Tensor, mask: Tensor) -> None:
        """pred (M, R, T, 2), truth (R, T, 2), mask (R,) rows to score."""
        dist = torch.linalg.vector_norm(pred - truth[None], dim=-1)  # (M, R, T)
        ade = dist.mean(dim=-1).amin(dim=0)[mask]
        fde = dist[..., -1].amin(dim=0)[mask]
        self.ade_sum += float(ade.double().sum())
        self.fde_sum += float(fde.double().sum())
        self.count += int(mask.sum())

    @property
    def ade(self) -> float:
        """Mean best-of-K ADE (NaN without targets)."""
        return self.ade_sum / self.count if self.count else float("nan")

    @property
    def fde(self) -> float:
        """Mean best-of-K FDE (NaN without targets)."""
        return self.fde_sum / self.count if self.count else float("nan")
