"""Eq. 23 of Zhu et al. (IJCAI 2020) for one training batch: the best-of-H loss over the network's H noise draws,
back-propagated through the picked modes only (``TrainConfig.select_then_backprop``). Positions and errors are
model-frame (``batching``); the loss is in model-frame metres squared.
"""

from __future__ import annotations

import torch

from ..training.loss import best_of_h_loss
from .batching import Batch
from .network import TrajectoryNet


def targets_with_future(batch_target: torch.Tensor, valid: torch.Tensor, obs_len: int) -> torch.Tensor:
    """Targets whose whole predicted horizon has ground truth (the rows eq. 23 sums over)."""
    return batch_target & valid[:, obs_len:].all(dim=1)


def best_of_h_step_loss(
    net: TrajectoryNet, batch: Batch, num_modes: int, generator: torch.Generator, reduce: str, select_first: bool,
    feature_map: torch.Tensor | None = None,
) -> torch.Tensor:
    """Eq. 23 for one batch, ready for ``backward`` (``feature_map``: the backbone's maps of ``batch.raster``
    from ``feature_cache``, else the backbone runs).

    With ``select_first`` the H modes are decoded without autograd, the best modes are picked, and only
    those are decoded again with autograd from the same encoder state and the same noise z. Modes are
    independent copies of the scene, so the re-decoded trajectories equal the picked ones and the gradient
    is exactly eq. 23's (which reaches only the picked modes), at the cost of a small extra decode instead of
    back-propagating through all H:

    * per-scene min (the paper): one mode per scene, a one-mode decode;
    * per-agent min: each scene's distinct picked modes, packed into as many decode slots as the scene
      with the most of them needs (slot l holds a different mode in each scene; scenes never interact).
    """
    cfg = net.config
    enc = net.encode(batch, feature_map)
    rows = batch.active.nonzero().squeeze(1)
    # z from the CPU generator whatever the device: a run draws the same z on every device.
    noise = torch.randn(num_modes, len(rows), cfg.noise_dim, generator=generator).to(rows.device)
    truth = batch.positions[rows, cfg.obs_len :]
    mask = targets_with_future(batch.target, batch.valid, cfg.obs_len)[rows]
    scene = batch.scene[rows]
    if not select_first or num_modes == 1:
        pred = net.decode(batch, enc, noise)
        return best_of_h_loss(pred.positions, truth, mask, scene, batch.size, reduce)[0]
    with torch.no_grad():
        pred = net.decode(batch, enc, noise)
        _, best = best_of_h_loss(pred.positions, truth, mask, scene, batch.size, reduce)
    every_row = torch.arange(len(rows), device=rows.device)
    if reduce == "scene":
        pred = net.decode(batch, enc, noise[best[scene], every_row][None])  # (1, R, noise_dim)
        return best_of_h_loss(pred.positions, truth, mask, scene, batch.size, reduce)[0]
    picked = torch.zeros(batch.size, num_modes, dtype=torch.bool, device=rows.device)
    picked[scene[mask], best[mask]] = True
    slot_of = picked.cumsum(dim=1) - 1  # (B, H): slot of each picked mode in its scene
    slots = max(int(picked.sum(dim=1).max()), 1)
    mode_in_slot = torch.zeros(batch.size, slots, dtype=torch.long, device=rows.device)  # unused: mode 0
    pick_scene, pick_mode = picked.nonzero(as_tuple=True)
    mode_in_slot[pick_scene, slot_of[pick_scene, pick_mode]] = pick_mode
    pred = net.decode(batch, enc, noise[mode_in_slot[scene].t(), every_row])  # (slots, R, noise_dim)
    mine = pred.positions[slot_of[scene, best].clamp(min=0), every_row]  # (R, T, 2): each row's picked mode
    loss, _ = best_of_h_loss(mine[None], truth, mask, scene, batch.size, "agent")
    return loss
