"""Training Social-LSTM: the negative log-likelihood of the predicted steps (the true positions fed in, eq. 5 of the
paper), one RMSprop update per batch, forecasts (the Gaussian's mean for K = 1; K sampled rollouts otherwise), and
validation by the mean forecast's ADE."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch

from logpipe.types import NDArrayFloat, SceneSample

from ..checkpoint.weights_folder import WeightsMeta, load_into, load_resumable, save_weights_folder
from ..training.seeding import sample_seed
from ..training.social_batch import SocialBatch, evenly, predict_scene, replicate, stack, window_tracks
from ..training.window_loop import LoopResult, LoopSettings, NextBatch, run_loop
from .config import MODEL_KIND, SocialLstmConfig
from .net import SocialLstm, bivariate_nll


def nll_loss(net: SocialLstm, batch: SocialBatch) -> torch.Tensor:
    """Mean NLL of every agent's predicted steps (steps ``obs_len`` ..), the whole track fed in."""
    steps = batch.relative()
    params = net.teacher_forced(batch.positions, steps, batch.pair_i, batch.pair_j)
    first = net.config.obs_len - 1  # params[t] is the Gaussian of step t + 1
    return bivariate_nll(params[first:], steps[first + 1:]).mean()


def train_step(net: SocialLstm, optimizer: torch.optim.Optimizer, next_batch: NextBatch) -> dict[str, float]:
    """One update on a fresh batch; returns its loss."""
    loss = nll_loss(net, next_batch())
    optimizer.zero_grad()
    loss.backward()  # type: ignore[no-untyped-call]
    torch.nn.utils.clip_grad_norm_(net.parameters(), net.config.clip_grad_norm)
    optimizer.step()
    return {"nll": float(loss.detach())}


@torch.no_grad()
def forecast(net: SocialLstm, tracks: Sequence[NDArrayFloat], num_modes: int, seeds: Sequence[int],
             sampled: bool) -> list[NDArrayFloat]:
    """(K, T_pred, N_s, 2) world-metre forecasts per window from its observed (T_obs, N_s, 2) track: K copies of
    the mean rollout, or (``sampled``) K rollouts drawn with window s's normals from ``seeds[s]`` alone, each a joint
    draw of the window's agents."""
    net.eval()
    batch = stack(list(tracks))
    pred_len, copies = net.config.pred_len, num_modes if sampled else 1
    run = replicate(batch, copies) if copies > 1 else batch
    normal = None
    if sampled:
        draws = [torch.randn(copies, pred_len, t.shape[1], 2, generator=torch.Generator().manual_seed(s))
                 for t, s in zip(tracks, seeds, strict=True)]
        normal = torch.cat([d[c] for c in range(copies) for d in draws], dim=1)  # copy-major, as ``replicate``
    steps = net.rollout(run.positions, run.relative(), run.pair_i, run.pair_j, normal)
    world = (steps.cumsum(dim=0) + run.positions[-1]).numpy().astype(np.float64)  # (T_pred, copies * N, 2)
    n = batch.starts[-1]
    world = world.reshape(pred_len, copies, n, 2).transpose(1, 0, 2, 3)
    if not sampled:
        world = np.repeat(world, num_modes, axis=0)
    net.train()
    return [world[:, :, a:b] for a, b in zip(batch.starts[:-1], batch.starts[1:], strict=True)]


def validate(net: SocialLstm, val: Sequence[NDArrayFloat]) -> dict[str, float]:
    """ADE/FDE of the mean forecast (K = 1) over validation windows."""
    obs_len = net.config.obs_len
    preds = forecast(net, [t[:obs_len] for t in val], 1, list(range(len(val))), sampled=False)
    dist = np.concatenate([np.linalg.norm(p[0] - t[obs_len:], axis=-1) for p, t in zip(preds, val, strict=True)],
                          axis=1)  # (T_pred, agents)
    return {"ade": float(dist.mean()), "fde": float(dist[-1].mean())}


def train_social_lstm(train: Sequence[SceneSample], val: Sequence[SceneSample], config: SocialLstmConfig,
                      out_dir: Path, meta: WeightsMeta, progress: Callable[[int], None] | None = None, *,
                      resume: bool = False) -> LoopResult:
    """Train into ``out_dir`` (``best/``, ``last/``, ``train_log.jsonl``), or with ``resume`` go on from its
    ``last/``; ``meta`` gives what every checkpoint records beside its weights."""
    torch.manual_seed(config.seed)
    net = SocialLstm(config)
    optimizer = torch.optim.RMSprop(net.parameters(), lr=config.learning_rate)
    tracks = window_tracks(train)
    val_tracks = evenly(window_tracks(val) if val else tracks, config.val_windows)
    settings = LoopSettings(config.steps, config.batch_size, config.val_every, config.patience, config.seed,
                            config.time_budget_s)

    meta.model_kind, meta.config = MODEL_KIND, config.to_dict()

    def save(folder: Path, step: int, metrics: dict[str, float], train_state: bytes | None) -> None:
        meta.step, meta.metrics = step, metrics
        save_weights_folder(folder, dict(net.state_dict()), meta, train_state)

    def restore(folder: Path) -> dict[str, Any]:
        weights, train_state = load_resumable(folder, meta)
        load_into(net, weights, folder)
        return train_state

    return run_loop(tracks, settings, out_dir, step=lambda nb: train_step(net, optimizer, nb),
                    validate=lambda: validate(net, val_tracks), save=save, progress=progress,
                    optimizers={"rmsprop": optimizer}, restore=restore if resume else None)


def scene_forecasts(net: SocialLstm, samples: Sequence[SceneSample], num_modes: int,
                    seed: int) -> list[NDArrayFloat]:
    """Per sample (N_targets, K, T_pred, 2): its targets' forecasts, the mean for K = 1 and sampled rollouts
    otherwise (NaN for a target not observed now)."""
    pred_len = net.config.pred_len
    out: list[NDArrayFloat] = [np.full((int(s.target_mask.sum()), num_modes, pred_len, 2), np.nan) for s in samples]
    scenes = [predict_scene(s) for s in samples]
    live = [i for i, sc in enumerate(scenes) if sc.positions.shape[1]]
    if not live:
        return out
    preds = forecast(net, [scenes[i].positions for i in live], num_modes,
                     [sample_seed(seed, samples[i].sample_id) for i in live], sampled=num_modes > 1)
    for i, pred in zip(live, preds, strict=True):
        rows = scenes[i].targets
        seen = rows >= 0
        out[i][seen] = pred[:, :, rows[seen]].transpose(2, 0, 1, 3)
    return out
