"""Validation metrics of a network: best-of-K ADE/FDE in metres over the targets with a full future, with the
noise z drawn from one seeded generator (so a run validates on the same draws at every evaluation).
"""

from __future__ import annotations

import itertools
from collections.abc import Iterable

import torch

from logpipe.types import SceneSample

from ..training.device import autocast
from ..training.loss import DisplacementErrors
from .batching import collate
from .network import TrajectoryNet
from .step_loss import targets_with_future


@torch.no_grad()
def evaluate(
    net: TrajectoryNet,
    samples: Iterable[SceneSample],
    *,
    num_modes: int,
    seed: int = 0,
    batch_size: int = 32,
    limit: int | None = None,
) -> DisplacementErrors:
    """Best-of-K ADE/FDE (metres) of ``net`` on ``samples`` (targets with a full future only), on the device
    ``net`` is on (under ``device.autocast`` there)."""
    was_training = net.training
    net.eval()
    device = next(net.parameters()).device
    gen = torch.Generator().manual_seed(seed)
    errors = DisplacementErrors()
    cfg = net.config
    it = iter(samples if limit is None else itertools.islice(samples, limit))
    while chunk := list(itertools.islice(it, batch_size)):
        batch = collate(chunk, cfg).to(device)
        with autocast(device):
            pred = net(batch, num_modes, gen)
        rows = pred.rows
        mask = targets_with_future(batch.target, batch.valid, cfg.obs_len)[rows]
        scene = batch.scene[rows]  # errors in metres whatever the model frame's scale
        errors.add(batch.metres(pred.positions.transpose(0, 1), scene).transpose(0, 1),
                   batch.metres(batch.positions[rows, cfg.obs_len :], scene), mask)
    net.train(was_training)
    return errors
