"""Social-GAN's networks (Gupta et al., CVPR 2018, §3): the generator (encoder LSTM over each agent's steps, the
pooling module, a context MLP whose output is completed with noise z into the decoder LSTM's initial state) and the
local discriminator (an LSTM over the whole 20-step track, scored real or fake by an MLP).

Batches are ``model.training.social_batch.SocialBatch``: agents of all windows stacked, ``pair_i`` / ``pair_j``
every within-window pair (self pairs included, as the paper's pooling compares each agent with all agents of its
scene, itself too).
"""

from __future__ import annotations

import itertools

import torch
from torch import nn

from .config import SocialGanConfig


def mlp(dims: list[int], *, last_activation: bool, batch_norm: bool = False) -> nn.Sequential:
    """Linear layers with ReLU between them (and after the last when ``last_activation``); with ``batch_norm``
    each ReLU follows a batch norm, as the published ``make_mlp`` builds it with ``batch_norm`` 1."""
    layers: list[nn.Module] = []
    for k, (a, b) in enumerate(itertools.pairwise(dims)):
        layers.append(nn.Linear(a, b))
        if last_activation or k < len(dims) - 2:
            layers += [nn.BatchNorm1d(b), nn.ReLU()] if batch_norm else [nn.ReLU()]
    return nn.Sequential(*layers)


def max_pool_pairs(values: torch.Tensor, pair_i: torch.Tensor, agents: int) -> torch.Tensor:
    """(agents, D): for each agent i the element-wise max of ``values`` (P, D) over its pairs (i, j). Every agent
    has its self pair, so none is left empty."""
    out = values.new_full((agents, values.shape[1]), float("-inf"))
    index = pair_i.unsqueeze(1).expand_as(values)
    return out.scatter_reduce(0, index, values, reduce="amax", include_self=True)


class PoolingModule(nn.Module):
    """The paper's pooling: for each agent i, every j of its window gives MLP([embed(p_j - p_i), h_j]) and the
    element-wise max over j is i's pooled vector (permutation invariant, any number of neighbours)."""

    def __init__(self, config: SocialGanConfig) -> None:
        super().__init__()
        self.spatial_embedding = nn.Linear(2, config.embedding_dim)
        self.mlp_pre_pool = mlp([config.embedding_dim + config.encoder_h_dim, config.pool_hidden_dim,
                                 config.bottleneck_dim], last_activation=True, batch_norm=config.pool_batch_norm)

    def forward(self, hidden: torch.Tensor, end_pos: torch.Tensor, pair_i: torch.Tensor,
                pair_j: torch.Tensor) -> torch.Tensor:
        relative = end_pos[pair_j] - end_pos[pair_i]
        features = self.mlp_pre_pool(torch.cat([self.spatial_embedding(relative), hidden[pair_j]], dim=1))
        return max_pool_pairs(features, pair_i, hidden.shape[0])


class TrackEncoder(nn.Module):
    """An LSTM over each agent's steps (embedded by a linear layer); returns the last hidden state (N, h)."""

    def __init__(self, embedding_dim: int, hidden_dim: int) -> None:
        super().__init__()
        self.spatial_embedding = nn.Linear(2, embedding_dim)
        self.lstm = nn.LSTM(embedding_dim, hidden_dim)

    def forward(self, steps: torch.Tensor) -> torch.Tensor:
        _, (h, _) = self.lstm(self.spatial_embedding(steps))
        last: torch.Tensor = h[0]
        return last


class Generator(nn.Module):
    """Encoder, pooling (20VP only), context MLP + noise, decoder (see the module docstring)."""

    def __init__(self, config: SocialGanConfig) -> None:
        super().__init__()
        self.config = config
        self.encoder = TrackEncoder(config.embedding_dim, config.encoder_h_dim)
        self.pool = PoolingModule(config) if config.pooling else None
        context_in = config.encoder_h_dim + (config.bottleneck_dim if config.pooling else 0)
        self.context = mlp([context_in, config.mlp_dim, config.decoder_h_dim - config.noise_dim], last_activation=True,
                           batch_norm=config.context_batch_norm)
        self.decoder_embedding = nn.Linear(2, config.embedding_dim)
        self.decoder = nn.LSTMCell(config.embedding_dim, config.decoder_h_dim)
        self.hidden2pos = nn.Linear(config.decoder_h_dim, 2)

    def encode(self, obs: torch.Tensor, obs_rel: torch.Tensor, pair_i: torch.Tensor,
               pair_j: torch.Tensor) -> torch.Tensor:
        """(N, decoder_h - noise_dim): each agent's context, pooled over its window with 20VP."""
        hidden = self.encoder(obs_rel)
        if self.pool is not None:
            hidden = torch.cat([hidden, self.pool(hidden, obs[-1], pair_i, pair_j)], dim=1)
        out: torch.Tensor = self.context(hidden)
        return out

    def decode(self, context: torch.Tensor, noise: torch.Tensor, last_rel: torch.Tensor) -> torch.Tensor:
        """(T_pred, M, 2) predicted steps from contexts (M, ·), noise (M, noise_dim) and the last observed step."""
        h = torch.cat([context, noise], dim=1)
        c = torch.zeros_like(h)
        step = last_rel
        out = []
        for _ in range(self.config.pred_len):
            h, c = self.decoder(self.decoder_embedding(step), (h, c))
            step = self.hidden2pos(h)
            out.append(step)
        return torch.stack(out)

    def sample(self, obs: torch.Tensor, obs_rel: torch.Tensor, pair_i: torch.Tensor, pair_j: torch.Tensor,
               noise: torch.Tensor) -> torch.Tensor:
        """(K, T_pred, N, 2) predicted steps for noise (K, N, noise_dim): the encoder and pooling run once, the
        decoder once per noise draw."""
        return self.decode_samples(self.encode(obs, obs_rel, pair_i, pair_j), noise, obs_rel[-1])

    def decode_samples(self, context: torch.Tensor, noise: torch.Tensor, last_rel: torch.Tensor) -> torch.Tensor:
        """(K, T_pred, N, 2) predicted steps for contexts (N, ·) and noise (K, N, noise_dim), one batch."""
        k, n = noise.shape[:2]
        steps = self.decode(context.repeat(k, 1), noise.reshape(k * n, -1), last_rel.repeat(k, 1))
        return steps.reshape(self.config.pred_len, k, n, 2).permute(1, 0, 2, 3)


class Discriminator(nn.Module):
    """The local discriminator: an LSTM over each agent's whole track of steps, an MLP to one logit."""

    def __init__(self, config: SocialGanConfig) -> None:
        super().__init__()
        self.encoder = TrackEncoder(config.embedding_dim, config.discriminator_h_dim)
        self.classifier = mlp([config.discriminator_h_dim, config.mlp_dim, 1], last_activation=False)

    def forward(self, track_rel: torch.Tensor) -> torch.Tensor:
        out: torch.Tensor = self.classifier(self.encoder(track_rel)).squeeze(1)
        return out


def init_weights(module: nn.Module) -> None:
    """Kaiming-normal linear layers (the published code's initialisation; its authors found training depends on
    it)."""
    if isinstance(module, nn.Linear):
        nn.init.kaiming_normal_(module.weight)
