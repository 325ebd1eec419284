"""The paper's network, Zhu et al. (IJCAI 2020): ``TrajectoryNet`` puts together the Agent Interaction Network
(eqs. 1-10, ``interaction``), the Environment Network (eqs. 11-12, ``environment``) and the Trajectory Prediction
Network's LSTM encoder (eqs. 13-16, ``encoder``) and noise-initialised decoder (eqs. 17-22, ``decoder``; for
inference ``fast_decoder``). The parameters are ``layers.TrajectoryLayers`` (their names are the
checkpoints' state_dict keys); this module draws the noise z of eq. 21 and picks the decoder: both decoders are
``decoder.Decoder`` functions of the layers, so training and inference share one interface.

Tensor layout: agents are flattened rows (see ``batching.Batch``); per-agent tensors are ``(L, N, ...)`` with a
leading axis L for modes (decoder samples) or time steps (vectorised encoder inputs); per-scene tensors are
``(L, B, ...)``. Positions are model-frame metres (``batching``), scaled by ``ModelConfig.pos_scale_m`` /
``disp_scale_m`` at the layers' inputs.

The AIN's GRU runs once per step over t = 1 .. T_pred-1 (observed steps with the true positions, then per mode
on the predicted ones). Only agents observed at the current step are decoded.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch
from torch import Tensor

from .batching import Batch
from .decoder import Decoder, Prediction, decode
from .encoder import Encoded, encode
from .fast_decoder import decode_fast
from .layers import TrajectoryLayers


class TrajectoryNet(TrajectoryLayers):
    """The full predictor: AIN + EN + prediction network (eqs. 1-22). Outputs model-frame positions."""

    def encode(self, batch: Batch, feature_map: Tensor | None = None) -> Encoded:
        """LSTM_E and the AIN over the observed steps (eqs. 1-16; ``encoder.encode``); ``feature_map``: the
        backbone's maps of ``batch.raster`` when the caller has them (``feature_cache``), else computed here."""
        return encode(self, batch, feature_map)

    def decode(self, batch: Batch, enc: Encoded, noise: Tensor,
               constant_velocity_modes: int | None = None) -> Prediction:
        """Eqs. 17-22 for the (M, R, noise_dim) z ``noise`` of the rows observed at the current step
        (``decoder.decode``; with autograd)."""
        return decode(self, batch, enc, noise, constant_velocity_modes)

    def decode_fast(self, batch: Batch, enc: Encoded, noise: Tensor,
                    constant_velocity_modes: int | None = None) -> Prediction:
        """``decode`` for inference, without autograd (``fast_decoder.decode_fast``; equal up to float rounding)."""
        return decode_fast(self, batch, enc, noise, constant_velocity_modes)

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
        outputs zeroed; see ``decoder.mode_open``; None: ``ModelConfig.constant_velocity_modes``, also used in
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
        decoder: Decoder = decode_fast if fast else decode
        return decoder(self, batch, enc, noise, constant_velocity_modes)
