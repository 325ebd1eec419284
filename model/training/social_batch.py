"""Scenes as the social baselines (``model.social_lstm``, ``model.social_gan``) see them: every agent of a window
with its track, and the windows of a batch stacked with the pairs of agents that share a window.

Which agents a window holds (Social-GAN's loader keeps the pedestrians present over the whole window):

* for training (``training_scene``), the agents observed at every step of the window; they are all trained on,
  as both papers train on every pedestrian of a sequence;
* for prediction (``predict_scene``), the agents observed at the current step (the future is not known then); a
  gap in an agent's history is filled with its next observed position (it stood), so it still pools.

Arrays are time-major like the papers' code: positions (T, N, 2) in world metres.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch

from logpipe.types import NDArrayFloat, NDArrayInt, SceneSample


@dataclass(frozen=True)
class SocialScene:
    """One window's agents.

    Attributes:
        positions: (T, N, 2) world metres (training: the whole window; prediction: the observed steps).
        targets: (N_t,) rows of the sample's targets among the N agents, in ``target_mask`` order; -1 for a target
            not observed at the current step (it gets NaN).
    """

    positions: NDArrayFloat
    targets: NDArrayInt


def training_scene(sample: SceneSample) -> SocialScene | None:
    """The agents observed over the whole window (None when there are none)."""
    full = np.isfinite(sample.positions).all(axis=(1, 2))
    if not full.any():
        return None
    return SocialScene(np.ascontiguousarray(sample.positions[full].transpose(1, 0, 2)), np.zeros(0, dtype=np.int64))


def predict_scene(sample: SceneSample) -> SocialScene:
    """The agents observed at the current step, their history gaps filled backwards (see the module docstring)."""
    obs = sample.positions[:, : sample.obs_len]
    present = np.isfinite(obs[:, -1]).all(axis=1)
    track = obs[present].copy()
    for t in range(sample.obs_len - 2, -1, -1):  # fill each gap with the next observed position
        gap = ~np.isfinite(track[:, t]).all(axis=1)
        track[gap, t] = track[gap, t + 1]
    row_of = np.full(present.shape[0], -1, dtype=np.int64)
    row_of[present] = np.arange(int(present.sum()))
    return SocialScene(np.ascontiguousarray(track.transpose(1, 0, 2)), row_of[sample.target_mask])


@dataclass(frozen=True)
class SocialBatch:
    """Windows stacked along the agent axis.

    Attributes:
        positions: (T, N, 2) float32 tensor, every window's agents one after the other.
        scene_of: (N,) long tensor: the window of each agent.
        starts: (S + 1,) offsets of each window's first agent (the last is N).
        pair_i, pair_j: long tensors of every ordered pair of agents of one window, self pairs included (``i`` is
            the agent pooling, ``j`` its neighbour).
    """

    positions: torch.Tensor
    scene_of: torch.Tensor
    starts: NDArrayInt
    pair_i: torch.Tensor
    pair_j: torch.Tensor

    @property
    def num_scenes(self) -> int:
        """Windows in the batch."""
        return len(self.starts) - 1

    def relative(self) -> torch.Tensor:
        """(T, N, 2) steps between consecutive positions, 0 at the first (the papers' ``traj_rel``)."""
        steps = self.positions[1:] - self.positions[:-1]
        return torch.cat([torch.zeros_like(self.positions[:1]), steps], dim=0)


def stack(tracks: Sequence[NDArrayFloat]) -> SocialBatch:
    """Stack windows' (T, N_s, 2) tracks (same T) into one batch with their within-window pairs."""
    counts = np.array([t.shape[1] for t in tracks], dtype=np.int64)
    starts = np.concatenate([[0], np.cumsum(counts)])
    scene_of = np.repeat(np.arange(len(tracks)), counts)
    pair_i, pair_j = within_pairs(starts)
    positions = torch.from_numpy(np.concatenate(tracks, axis=1).astype(np.float32))
    return SocialBatch(positions, torch.from_numpy(scene_of), starts, torch.from_numpy(pair_i),
                       torch.from_numpy(pair_j))


def within_pairs(starts: NDArrayInt) -> tuple[NDArrayInt, NDArrayInt]:
    """Every ordered (i, j) of agents in the same window, self pairs included, for windows at ``starts``."""
    firsts, ends = starts[:-1], starts[1:]
    counts = ends - firsts
    pair_i = np.repeat(np.arange(starts[-1]), np.repeat(counts, counts))
    # j runs over i's window: its first agent plus 0..n-1, for each of the window's n agents
    offsets = np.concatenate([np.tile(np.arange(n), n) for n in counts]) if len(counts) else np.zeros(0, np.int64)
    pair_j = np.repeat(firsts, counts * counts) + offsets
    return pair_i.astype(np.int64), pair_j.astype(np.int64)


def replicate(batch: SocialBatch, copies: int) -> SocialBatch:
    """``copies`` independent copies of every window (copy-major: copy c of window s is window c * S + s), so K
    samples run as one batch and never pool across samples."""
    tracks = [batch.positions[:, a:b].numpy() for a, b in zip(batch.starts[:-1], batch.starts[1:], strict=True)]
    return stack(tracks * copies)


def window_tracks(samples: Sequence[SceneSample]) -> list[NDArrayFloat]:
    """Each sample's agents observed over the whole window, (T, N, 2) (windows without any are left out)."""
    return [s.positions for s in (training_scene(x) for x in samples) if s is not None]


def evenly(items: Sequence[NDArrayFloat], n: int) -> list[NDArrayFloat]:
    """At most ``n`` of ``items``, evenly spaced (a fixed validation subset)."""
    if len(items) <= n:
        return list(items)
    return [items[i] for i in np.linspace(0, len(items) - 1, n).round().astype(int)]
