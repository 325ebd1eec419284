"""Social-LSTM's network (Alahi et al., CVPR 2016, §3): one LSTM per agent (shared weights), whose input at each
step is its embedded step and the embedded social tensor, the hidden states of its neighbours summed into the cells
of a grid centred on it; the LSTM's output gives a bivariate Gaussian over the next step, trained by its negative
log-likelihood.

Batches are ``model.training.social_batch.SocialBatch`` (agents of all windows stacked, within-window pairs).
"""

from __future__ import annotations

import math

import torch
from torch import nn
from torch.nn import functional

from .config import SocialLstmConfig


def grid_cells(relative: torch.Tensor, neighbourhood_m: float, grid_size: int) -> tuple[torch.Tensor, torch.Tensor]:
    """For neighbours at ``relative`` (P, 2) metres from the agent pooling: their cell (row-major, x fastest, in
    ``0 .. grid_size² - 1``) in a ``grid_size`` x ``grid_size`` grid of side ``neighbourhood_m`` centred on the
    agent, and whether they are inside it (a neighbour on the outer edge is outside)."""
    half = neighbourhood_m / 2
    inside = (relative.abs() < half).all(dim=1)
    cell_xy = torch.floor((relative + half) / neighbourhood_m * grid_size).long().clamp(0, grid_size - 1)
    return cell_xy[:, 1] * grid_size + cell_xy[:, 0], inside


def social_tensor(hidden: torch.Tensor, positions: torch.Tensor, pair_i: torch.Tensor, pair_j: torch.Tensor,
                  config: SocialLstmConfig) -> torch.Tensor:
    """(N, grid² * H): for each agent i the hidden states ``hidden`` (N, H) of its neighbours j (pairs, self pairs
    ignored) summed per grid cell (eq. 1 of the paper)."""
    n, h = hidden.shape
    cells = config.grid_size**2
    other = pair_i != pair_j
    i, j = pair_i[other], pair_j[other]
    cell, inside = grid_cells(positions[j] - positions[i], config.neighbourhood_m, config.grid_size)
    i, j, cell = i[inside], j[inside], cell[inside]
    pooled = hidden.new_zeros((n * cells, h)).index_add(0, i * cells + cell, hidden[j])
    return pooled.reshape(n, cells * h)


def embedded_social_tensor(hidden: torch.Tensor, positions: torch.Tensor, pair_i: torch.Tensor,
                           pair_j: torch.Tensor, config: SocialLstmConfig, layer: nn.Linear) -> torch.Tensor:
    """``layer(social_tensor(...))`` (N, E) without building the social tensor, which is mostly zeros (few
    neighbours fall in a 2 m grid): each in-grid neighbour's hidden state goes through the block of ``layer`` its
    cell reads, one matrix product per occupied cell, and each agent sums its neighbours'. The same sum, at the
    cost of the occupied cells only."""
    n, h = hidden.shape
    other = pair_i != pair_j
    i, j = pair_i[other], pair_j[other]
    cell, inside = grid_cells(positions[j] - positions[i], config.neighbourhood_m, config.grid_size)
    order = torch.argsort(cell[inside], stable=True)
    i, j, cell = i[inside][order], j[inside][order], cell[inside][order]
    out = layer.bias.expand(n, -1)
    if not len(cell):
        return out
    occupied, counts = torch.unique_consecutive(cell, return_counts=True)
    # (H, E) per cell; unbind, not indexing, so the backward stacks the blocks' gradients once
    blocks = layer.weight.reshape(-1, config.grid_size**2, h).permute(1, 2, 0).unbind(0)
    neighbours = torch.split(hidden[j], counts.tolist())
    parts = [rows @ blocks[c] for c, rows in zip(occupied.tolist(), neighbours, strict=True)]
    return out.index_add(0, i, torch.cat(parts))


def gaussian(params: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(mean (..., 2), standard deviations (..., 2), correlation (...)) of the raw output (..., 5)."""
    return params[..., :2], torch.exp(params[..., 2:4]), torch.tanh(params[..., 4])


def bivariate_nll(params: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Negative log-likelihood (...,) of ``target`` (..., 2) under the bivariate Gaussian of ``params`` (..., 5)."""
    mean, std, rho = gaussian(params)
    z = (target - mean) / std
    one_minus = (1 - rho**2).clamp_min(1e-6)
    mahalanobis = (z[..., 0] ** 2 + z[..., 1] ** 2 - 2 * rho * z[..., 0] * z[..., 1]) / one_minus
    log_det = torch.log(std[..., 0]) + torch.log(std[..., 1]) + 0.5 * torch.log(one_minus)
    return 0.5 * mahalanobis + log_det + math.log(2 * math.pi)


def sample_gaussian(params: torch.Tensor, normal: torch.Tensor) -> torch.Tensor:
    """A draw (..., 2) from the Gaussian of ``params`` given standard normals ``normal`` (..., 2) (Cholesky)."""
    mean, std, rho = gaussian(params)
    x = std[..., 0] * normal[..., 0]
    y = std[..., 1] * (rho * normal[..., 0] + torch.sqrt((1 - rho**2).clamp_min(0)) * normal[..., 1])
    return mean + torch.stack([x, y], dim=-1)


class SocialLstm(nn.Module):
    """The network (see the module docstring); ``step`` advances every agent by one time step."""

    def __init__(self, config: SocialLstmConfig) -> None:
        super().__init__()
        self.config = config
        self.input_embedding = nn.Linear(2, config.embedding_dim)
        self.social_embedding = nn.Linear(config.grid_size**2 * config.hidden_dim, config.embedding_dim)
        self.cell = nn.LSTMCell(2 * config.embedding_dim, config.hidden_dim)
        self.output = nn.Linear(config.hidden_dim, 5)

    def step(self, state: tuple[torch.Tensor, torch.Tensor], positions: torch.Tensor, step: torch.Tensor,
             pair_i: torch.Tensor, pair_j: torch.Tensor) -> tuple[tuple[torch.Tensor, torch.Tensor], torch.Tensor]:
        """New (h, c) and the Gaussian's raw parameters (N, 5) of the next step, from the agents' positions and
        last steps (N, 2) now and their hidden states before."""
        social = embedded_social_tensor(state[0], positions, pair_i, pair_j, self.config, self.social_embedding)
        embedded = functional.relu(self.input_embedding(step))
        x = torch.cat([embedded, functional.relu(social)], dim=1)
        h, c = self.cell(x, state)
        return (h, c), self.output(h)

    def initial_state(self, agents: int) -> tuple[torch.Tensor, torch.Tensor]:
        """Zero (h, c) for ``agents`` agents."""
        zeros = torch.zeros(agents, self.config.hidden_dim)
        return zeros, zeros.clone()

    def teacher_forced(self, positions: torch.Tensor, steps: torch.Tensor, pair_i: torch.Tensor,
                       pair_j: torch.Tensor) -> torch.Tensor:
        """(T - 1, N, 5): the Gaussian of each next step, fed the true positions (training)."""
        state = self.initial_state(positions.shape[1])
        out = []
        for t in range(positions.shape[0] - 1):
            state, params = self.step(state, positions[t], steps[t], pair_i, pair_j)
            out.append(params)
        return torch.stack(out)

    def rollout(self, observed: torch.Tensor, observed_steps: torch.Tensor, pair_i: torch.Tensor,
                pair_j: torch.Tensor, normal: torch.Tensor | None) -> torch.Tensor:
        """(T_pred, N, 2) predicted steps after the observed (T_obs, N, 2): each step the Gaussian's mean
        (``normal`` None) or a draw with the standard normals ``normal`` (T_pred, N, 2), fed back as the next
        input, the neighbours' predictions pooled as the paper's test time does."""
        state = self.initial_state(observed.shape[1])
        params = observed.new_zeros((observed.shape[1], 5))
        for t in range(observed.shape[0]):
            state, params = self.step(state, observed[t], observed_steps[t], pair_i, pair_j)
        position = observed[-1]
        out = []
        for t in range(self.config.pred_len):
            step = gaussian(params)[0] if normal is None else sample_gaussian(params, normal[t])
            position = position + step
            out.append(step)
            if t + 1 < self.config.pred_len:
                state, params = self.step(state, position, step, pair_i, pair_j)
        return torch.stack(out)
