"""The paper's network (and its LSTM / Noise-LSTM presets) behind the ``model.predictor.Predictor`` interface."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import torch

from logpipe.errors import LogpipeError
from logpipe.types import NDArrayFloat, SceneSample

from ..training.device import autocast, resolve_device
from ..training.seeding import sample_seed
from .batching import collate
from .checkpoint import load_checkpoint
from .config import ModelConfig
from .network import TrajectoryNet


class NetPredictor:
    """``TrajectoryNet`` behind the ``Predictor`` interface (the paper's method, Noise-LSTM and LSTM).

    Attributes:
        net: the network (put in eval mode).
        config: its architecture, frame and normalisation.
        batch_size: scenes per forward pass.
        name: label for reports.
        noise_scale: standard deviation of the noise z at inference (1 = eq. 21, what training drew).
        constant_velocity_modes: how many of the K modes are held to constant velocity (0 = none, the paper;
            None = the checkpoint's ``ModelConfig.constant_velocity_modes``, at most K - 1).
        context_max_neighbours: at most this many neighbours in each target's context (the nearest; see
            ``ModelConfig.context_max_neighbours``; None = the checkpoint's). Only with ``context_radius_m``.
        device: where the network runs (``model.training.device.resolve_device``; under autocast on CUDA); the noise
            z is drawn on the CPU and the forecasts come back to the CPU, so only the arithmetic depends on it.
    """

    @classmethod
    def from_checkpoint(
        cls,
        path: Path,
        *,
        expect_kind: str | None = None,
        expect_config: ModelConfig | None = None,
        batch_size: int = 32,
        noise_scale: float = 1.0,
        constant_velocity_modes: int | None = None,
        context_max_neighbours: int | None = None,
        device: torch.device | str = "cpu",
    ) -> NetPredictor:
        """Load a checkpoint folder (see ``checkpoints.load_checkpoint`` for the checks and errors)."""
        loaded = load_checkpoint(path, expect_kind=expect_kind, expect_config=expect_config)
        return cls(loaded.net, batch_size=batch_size, noise_scale=noise_scale,
                   constant_velocity_modes=constant_velocity_modes, context_max_neighbours=context_max_neighbours,
                   device=device)

    def __init__(self, net: TrajectoryNet, batch_size: int = 32, name: str = "zhu2020",
                 noise_scale: float = 1.0, constant_velocity_modes: int | None = None,
                 context_max_neighbours: int | None = None, device: torch.device | str = "cpu") -> None:
        if not (math.isfinite(noise_scale) and noise_scale > 0):
            raise LogpipeError(f"noise scale must be a positive number, got {noise_scale}")
        if context_max_neighbours is not None and net.config.context_radius_m is None:
            raise LogpipeError("a neighbour cap needs a checkpoint trained with model.context_radius_m")
        self.device = resolve_device(device)
        self.net = net.eval().to(self.device)
        # The cap only changes which agents are collated, so it lives in the config collate reads (which also
        # rejects a negative one).
        self.config: ModelConfig = (net.config if context_max_neighbours is None
                                    else replace(net.config, context_max_neighbours=context_max_neighbours))
        self.batch_size = batch_size
        self.name = name
        self.noise_scale = noise_scale
        self.constant_velocity_modes = constant_velocity_modes
        self.context_max_neighbours = context_max_neighbours

    def _with(self, **changes: Any) -> NetPredictor:
        settings = {"noise_scale": self.noise_scale, "constant_velocity_modes": self.constant_velocity_modes,
                    "context_max_neighbours": self.context_max_neighbours, "device": self.device} | changes
        return NetPredictor(self.net, self.batch_size, self.name, **settings)

    def with_noise_scale(self, noise_scale: float) -> NetPredictor:
        """The same network and settings, sampling z with standard deviation ``noise_scale``."""
        return self._with(noise_scale=noise_scale)

    def with_constant_velocity_modes(self, count: int | None) -> NetPredictor:
        """The same network and settings, with the first ``count`` modes held to constant velocity."""
        return self._with(constant_velocity_modes=count)

    def with_context_max_neighbours(self, count: int | None) -> NetPredictor:
        """The same network and settings, with at most ``count`` neighbours in each target's context."""
        return self._with(context_max_neighbours=count)

    @torch.inference_mode()
    def predict(self, samples: Sequence[SceneSample], num_modes: int, seed: int) -> list[NDArrayFloat]:
        """Batched inference (in torch's inference mode: no autograd bookkeeping; it returns numpy copies); each
        sample's noise z is drawn from its own generator (``sample_seed`` of ``seed`` and its id), so a sample's
        forecasts do not depend on the batch size or on the other samples."""
        out: list[NDArrayFloat] = []
        t_pred = self.config.pred_len
        for lo in range(0, len(samples), self.batch_size):
            chunk = samples[lo : lo + self.batch_size]
            batch = collate(chunk, self.config)
            with autocast(self.device):
                pred = self.net(batch.to(self.device), num_modes, fast=True, noise_scale=self.noise_scale,
                                constant_velocity_modes=self.constant_velocity_modes,
                                sample_seeds=[sample_seed(seed, s.sample_id) for s in chunk])
            n = batch.positions.shape[0]
            world = np.full((n, num_modes, t_pred, 2), np.nan)
            rows = pred.rows.cpu()
            world[rows.numpy()] = batch.to_world(pred.positions.transpose(0, 1).cpu(), batch.scene[rows])
            out += [np.ascontiguousarray(world[targets]) for targets in batch.sample_targets]
        return out
