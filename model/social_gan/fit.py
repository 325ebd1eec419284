"""Training Social-GAN: the variety loss (best of k per window), the adversarial losses with the published label
smoothing, one iteration of ``d_steps`` discriminator and ``g_steps`` generator updates (each on a fresh batch, as
the published loop draws one per update), sampling forecasts, and validation by joint best-of-k ADE."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch.nn import functional

from logpipe.types import NDArrayFloat, SceneSample

from ..checkpoint.weights_folder import WeightsMeta, load_into, load_resumable, save_weights_folder
from ..training.seeding import sample_seed
from ..training.social_batch import SocialBatch, evenly, predict_scene, stack, window_tracks
from ..training.window_loop import LoopResult, LoopSettings, NextBatch, run_loop
from .config import MODEL_KIND, SocialGanConfig
from .net import Discriminator, Generator, init_weights


def variety_loss(errors: torch.Tensor, scene_of: torch.Tensor, num_scenes: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Social-GAN's variety loss: ``errors`` (K, N) each agent's summed squared step error under each of K samples;
    per window the sample with the lowest sum over its agents; returns (the sum of those minima, the chosen sample
    per window)."""
    per_scene = errors.new_zeros((errors.shape[0], num_scenes)).index_add(1, scene_of, errors)
    best, chosen = per_scene.min(dim=0)
    return best.sum(), chosen


def smoothed_labels(n: int, real: bool) -> torch.Tensor:
    """The published label smoothing: real in U(0.7, 1.2), fake in U(0, 0.3)."""
    return torch.rand(n) * 0.5 + 0.7 if real else torch.rand(n) * 0.3


@dataclass
class Gan:
    """The networks and their optimisers."""

    config: SocialGanConfig
    generator: Generator
    discriminator: Discriminator
    g_optimizer: torch.optim.Optimizer
    d_optimizer: torch.optim.Optimizer

    @classmethod
    def new(cls, config: SocialGanConfig) -> Gan:
        generator, discriminator = Generator(config), Discriminator(config)
        generator.apply(init_weights)
        discriminator.apply(init_weights)
        return cls(config, generator, discriminator, torch.optim.Adam(generator.parameters(), config.g_learning_rate),
                   torch.optim.Adam(discriminator.parameters(), config.d_learning_rate))


def _split(batch: SocialBatch, obs_len: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    rel = batch.relative()
    return batch.positions[:obs_len], rel[:obs_len], rel[obs_len:]


def _noise(config: SocialGanConfig, batch: SocialBatch, k: int) -> torch.Tensor:
    """(k, N, noise_dim) Gaussian noise, one draw per window shared by its agents (the published 'global' mix)."""
    return torch.randn(k, batch.num_scenes, config.noise_dim)[:, batch.scene_of]


def discriminator_step(gan: Gan, batch: SocialBatch) -> float:
    """One discriminator update on real tracks and one generated sample of each."""
    config = gan.config
    obs, obs_rel, fut_rel = _split(batch, config.obs_len)
    with torch.no_grad():
        fake_rel = gan.generator.sample(obs, obs_rel, batch.pair_i, batch.pair_j, _noise(config, batch, 1))[0]
    real = gan.discriminator(torch.cat([obs_rel, fut_rel]))
    fake = gan.discriminator(torch.cat([obs_rel, fake_rel]))
    n = real.shape[0]
    loss = (functional.binary_cross_entropy_with_logits(real, smoothed_labels(n, True))
            + functional.binary_cross_entropy_with_logits(fake, smoothed_labels(n, False)))
    gan.d_optimizer.zero_grad()
    loss.backward()  # type: ignore[no-untyped-call]
    if config.clipping_threshold_d > 0:
        torch.nn.utils.clip_grad_norm_(gan.discriminator.parameters(), config.clipping_threshold_d)
    gan.d_optimizer.step()
    return float(loss.detach())


def generator_step(gan: Gan, batch: SocialBatch) -> tuple[float, float]:
    """One generator update: the adversarial loss of one sample plus ``l2_loss_weight`` x the variety loss over
    ``best_k`` samples; returns (adversarial, variety) losses.

    The variety loss is a minimum, so its gradient flows through each window's best sample alone: the ``best_k``
    samples are decoded without autograd, then only the chosen ones and the adversarial sample are decoded again
    with it (the same value and gradient as backpropagating through all ``best_k``, at 2/``best_k`` of the
    decoder's backward; ``tests/model/test_social_speed.py`` checks it against the direct form)."""
    config = gan.config
    obs, obs_rel, fut_rel = _split(batch, config.obs_len)
    noise = _noise(config, batch, config.best_k)
    context = gan.generator.encode(obs, obs_rel, batch.pair_i, batch.pair_j)
    n = context.shape[0]
    with torch.no_grad():
        candidates = gan.generator.decode_samples(context, noise, obs_rel[-1])
        errors = ((candidates - fut_rel.unsqueeze(0)) ** 2).sum(dim=(1, 3))  # (K, N)
        _, chosen = variety_loss(errors, batch.scene_of, batch.num_scenes)
    picked = noise[chosen[batch.scene_of], torch.arange(n)]
    # sample 0 for the discriminator, each window's best sample for the variety loss, as one batch
    fake_rel = gan.generator.decode_samples(context, torch.stack([noise[0], picked]), obs_rel[-1])
    best_errors = ((fake_rel[1] - fut_rel) ** 2).sum()
    l2 = best_errors / (n * config.pred_len)
    scores = gan.discriminator(torch.cat([obs_rel, fake_rel[0]]))
    adversarial = functional.binary_cross_entropy_with_logits(scores, smoothed_labels(scores.shape[0], True))
    loss = adversarial + config.l2_loss_weight * l2
    gan.g_optimizer.zero_grad()
    loss.backward()  # type: ignore[no-untyped-call]
    if config.clipping_threshold_g > 0:
        torch.nn.utils.clip_grad_norm_(gan.generator.parameters(), config.clipping_threshold_g)
    gan.g_optimizer.step()
    return float(adversarial.detach()), float(l2.detach())


def iteration(gan: Gan, next_batch: NextBatch) -> dict[str, float]:
    """``d_steps`` discriminator updates then ``g_steps`` generator updates, each on a fresh batch."""
    d_losses = [discriminator_step(gan, next_batch()) for _ in range(gan.config.d_steps)]
    g_losses = [generator_step(gan, next_batch()) for _ in range(gan.config.g_steps)]
    return {"d_loss": float(np.mean(d_losses)), "g_adv_loss": float(np.mean([g[0] for g in g_losses])),
            "g_l2_loss": float(np.mean([g[1] for g in g_losses]))}


@torch.no_grad()
def forecast(generator: Generator, tracks: Sequence[NDArrayFloat], num_modes: int,
             seeds: Sequence[int]) -> list[NDArrayFloat]:
    """(K, T_pred, N_s, 2) world-metre forecasts per window from its observed (T_obs, N_s, 2) track; window s's
    noise is drawn from ``seeds[s]`` alone, so a forecast never depends on its batch mates."""
    config = generator.config
    generator.eval()
    batch = stack(list(tracks))
    noise = torch.stack([torch.randn(num_modes, config.noise_dim, generator=torch.Generator().manual_seed(s))
                         for s in seeds], dim=1)[:, batch.scene_of]
    rel = batch.relative()
    steps = generator.sample(batch.positions, rel, batch.pair_i, batch.pair_j, noise)
    world = (steps.cumsum(dim=1) + batch.positions[-1]).numpy().astype(np.float64)
    return [world[:, :, a:b] for a, b in zip(batch.starts[:-1], batch.starts[1:], strict=True)]


def validate(generator: Generator, val: Sequence[NDArrayFloat], config: SocialGanConfig) -> dict[str, float]:
    """Joint best-of-``best_k`` ADE/FDE over validation windows (per window, the sample with the lowest summed ADE
    of its agents; Social-GAN's evaluation rule), and the per-agent rule beside it."""
    obs = [t[: config.obs_len] for t in val]
    preds = forecast(generator, obs, config.best_k, list(range(len(val))))
    joint_ade, joint_fde, agent_ade, agent_fde = [], [], [], []
    for pred, track in zip(preds, val, strict=True):
        dist = np.linalg.norm(pred - track[config.obs_len:][None], axis=-1)  # (K, T, N)
        ade, fde = dist.mean(axis=1), dist[:, -1]
        k = int(ade.sum(axis=1).argmin())
        joint_ade += ade[k].tolist()
        joint_fde += fde[k].tolist()
        agent_ade += ade.min(axis=0).tolist()
        agent_fde += fde[ade.argmin(axis=0), np.arange(ade.shape[1])].tolist()
    generator.train()
    return {"ade": float(np.mean(joint_ade)), "fde": float(np.mean(joint_fde)),
            "ade_per_agent": float(np.mean(agent_ade)), "fde_per_agent": float(np.mean(agent_fde))}


def train_social_gan(train: Sequence[SceneSample], val: Sequence[SceneSample], config: SocialGanConfig,
                     out_dir: Path, meta: WeightsMeta, progress: Callable[[int], None] | None = None, *,
                     resume: bool = False) -> LoopResult:
    """Train into ``out_dir`` (``best/``, ``last/``, ``train_log.jsonl``), or with ``resume`` go on from its
    ``last/``; ``meta`` gives what every checkpoint records beside its weights (kind, dataset, training data)."""
    torch.manual_seed(config.seed)
    gan = Gan.new(config)
    tracks = window_tracks(train)
    val_tracks = evenly(window_tracks(val), config.val_windows) if val else evenly(tracks, config.val_windows)
    settings = LoopSettings(config.steps, config.batch_size, config.val_every, config.patience, config.seed,
                            config.time_budget_s)

    meta.model_kind, meta.config = MODEL_KIND, config.to_dict()

    def save(folder: Path, step: int, metrics: dict[str, float], train_state: bytes | None) -> None:
        state = {f"generator.{k}": v for k, v in gan.generator.state_dict().items()}
        state |= {f"discriminator.{k}": v for k, v in gan.discriminator.state_dict().items()}
        meta.step, meta.metrics = step, metrics
        save_weights_folder(folder, state, meta, train_state)

    def restore(folder: Path) -> dict[str, Any]:
        weights, train_state = load_resumable(folder, meta)
        for name, net in (("generator", gan.generator), ("discriminator", gan.discriminator)):
            load_into(net, {k[len(name) + 1:]: v for k, v in weights.items() if k.startswith(name + ".")}, folder)
        return train_state

    return run_loop(tracks, settings, out_dir, step=lambda nb: iteration(gan, nb),
                    validate=lambda: validate(gan.generator, val_tracks, config), save=save, progress=progress,
                    optimizers={"generator": gan.g_optimizer, "discriminator": gan.d_optimizer},
                    restore=restore if resume else None)


def scene_forecasts(generator: Generator, samples: Sequence[SceneSample], num_modes: int,
                    seed: int) -> list[NDArrayFloat]:
    """Per sample (N_targets, K, T_pred, 2): its targets' forecasts (NaN for a target not observed now)."""
    config = generator.config
    out: list[NDArrayFloat] = [np.full((int(s.target_mask.sum()), num_modes, config.pred_len, 2), np.nan)
                               for s in samples]
    scenes = [predict_scene(s) for s in samples]
    live = [i for i, sc in enumerate(scenes) if sc.positions.shape[1]]
    if not live:
        return out
    preds = forecast(generator, [scenes[i].positions for i in live], num_modes,
                     [sample_seed(seed, samples[i].sample_id) for i in live])
    for i, pred in zip(live, preds, strict=True):
        rows = scenes[i].targets
        seen = rows >= 0
        out[i][seen] = pred[:, :, rows[seen]].transpose(2, 0, 1, 3)
    return out
