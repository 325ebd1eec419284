"""One training iteration of each social baseline (issue 63) against its direct form, in the same run.

The direct forms are the first round's code, kept here as the reference: Social-LSTM's social tensor built dense
(N x grid² x H) and fed to its linear layer, where the model sums only the occupied cells' blocks; Social-GAN's
generator update backpropagating through all ``best_k`` decoded samples, where the model decodes them without
autograd and backpropagates through each window's best sample only. Same maths (``tests/model/test_social_speed.py``
checks outputs and gradients); ``speedup`` = direct / model seconds per iteration, medians of alternating rounds,
single-threaded, on the same synthetic batches (windows of 2-40 pedestrians on a 12 m square, like ETH/UCY's crowds)
or, with ``--dataset``, on six real training batches.

Run: ``OMP_NUM_THREADS=1 .venv/bin/python -m benchmarks.bench_social [--quick] [--rounds N] [--dataset out/ethucy
--split zara1/train]`` (prints JSON; with ``--dataset``, six real training batches of the split).
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any
from unittest import mock

import numpy as np
import torch
from torch.nn import functional

from logpipe.model.social_gan import fit as gan_fit
from logpipe.model.social_gan.config import preset_config
from logpipe.model.social_lstm import net as lstm_net
from logpipe.model.social_lstm.config import SocialLstmConfig
from logpipe.model.social_lstm.fit import train_step
from logpipe.model.training.social_batch import SocialBatch, stack
from logpipe.types import NDArrayFloat


def synthetic_tracks(windows: int, seed: int, obs_len: int = 8, pred_len: int = 12) -> list[NDArrayFloat]:
    """(T, N, 2) windows of 2-40 pedestrians walking at ~1.3 m/s with jitter, starting on a 12 m square."""
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(windows):
        n = int(rng.integers(2, 41))
        start = rng.uniform(0, 12, (n, 2))
        heading = rng.uniform(0, 2 * np.pi, n)
        velocity = 1.3 * 0.4 * np.stack([np.cos(heading), np.sin(heading)], axis=1)  # metres per 0.4 s step
        steps = velocity[None] + rng.normal(0, 0.05, (obs_len + pred_len, n, 2))
        out.append(start[None] + np.cumsum(steps, axis=0))
    return out


def direct_embedded_social_tensor(hidden: torch.Tensor, positions: torch.Tensor, pair_i: torch.Tensor,
                                  pair_j: torch.Tensor, config: SocialLstmConfig,
                                  layer: torch.nn.Linear) -> torch.Tensor:
    """The reference: the dense social tensor (eq. 1 of the paper) through ``layer``."""
    out: torch.Tensor = layer(lstm_net.social_tensor(hidden, positions, pair_i, pair_j, config))
    return out


@contextmanager
def direct_social_lstm() -> Iterator[None]:
    """Social-LSTM's steps run the direct social tensor while inside."""
    with mock.patch.object(lstm_net, "embedded_social_tensor", direct_embedded_social_tensor):
        yield


def direct_generator_step(gan: gan_fit.Gan, batch: SocialBatch) -> tuple[float, float]:
    """The reference generator update: every one of the ``best_k`` samples decoded with autograd."""
    config = gan.config
    obs, obs_rel, fut_rel = gan_fit._split(batch, config.obs_len)
    noise = gan_fit._noise(config, batch, config.best_k)
    fake_rel = gan.generator.sample(obs, obs_rel, batch.pair_i, batch.pair_j, noise)
    errors = ((fake_rel - fut_rel.unsqueeze(0)) ** 2).sum(dim=(1, 3))  # (K, N)
    best, _ = gan_fit.variety_loss(errors, batch.scene_of, batch.num_scenes)
    l2 = best / (errors.shape[1] * config.pred_len)
    scores = gan.discriminator(torch.cat([obs_rel, fake_rel[0]]))
    adversarial = functional.binary_cross_entropy_with_logits(scores, gan_fit.smoothed_labels(scores.shape[0], True))
    loss = adversarial + config.l2_loss_weight * l2
    gan.g_optimizer.zero_grad()
    loss.backward()  # type: ignore[no-untyped-call]
    if config.clipping_threshold_g > 0:
        torch.nn.utils.clip_grad_norm_(gan.generator.parameters(), config.clipping_threshold_g)
    gan.g_optimizer.step()
    return float(adversarial.detach()), float(l2.detach())


@contextmanager
def direct_social_gan() -> Iterator[None]:
    """Social-GAN's iterations run the direct generator update while inside."""
    with mock.patch.object(gan_fit, "generator_step", direct_generator_step):
        yield


def _seconds(step: Callable[[], object], direct: Callable[[], Any], rounds: int) -> tuple[float, float]:
    """Medians of (model, direct) seconds per call, the two alternating each round."""
    step()  # warm-up
    model_s, direct_s = [], []
    for _ in range(rounds):
        started = time.perf_counter()
        step()
        model_s.append(time.perf_counter() - started)
        with direct():
            started = time.perf_counter()
            step()
            direct_s.append(time.perf_counter() - started)
    return statistics.median(model_s), statistics.median(direct_s)


def real_batches(dataset: Path, split: str, batch_size: int) -> list[SocialBatch]:
    """Six training batches of ``split`` drawn as a run draws them (seed 0)."""
    from logpipe.dataset.reader import Dataset
    from logpipe.model.social import split_samples
    from logpipe.model.training.social_batch import window_tracks
    from logpipe.model.training.window_loop import batches

    samples, _ = split_samples([Dataset.open(dataset)], split)
    source = batches(window_tracks(samples), batch_size, np.random.default_rng(0))
    return [source() for _ in range(6)]


def run(quick: bool = False, rounds: int = 7, dataset: Path | None = None, split: str = "") -> dict[str, Any]:
    """Seconds per training iteration of each model and its direct form (see the module docstring); with
    ``dataset``, on six real batches of ``split`` instead of the synthetic ones."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    rounds = 2 if quick else rounds
    try:
        results: dict[str, Any] = {"threads": 1, "rounds": rounds, "batches": f"{dataset}:{split}" if dataset
                                   else "synthetic"}
        if dataset is not None:
            lstm_batches, gan_batches = real_batches(dataset, split, 32), real_batches(dataset, split, 64)
        else:
            lstm_batches = [stack(synthetic_tracks(32, seed)) for seed in range(3)]
            gan_batches = [stack(synthetic_tracks(64, 10 + seed)) for seed in range(3)]
        torch.manual_seed(0)
        config = SocialLstmConfig(obs_len=8, pred_len=12)
        net = lstm_net.SocialLstm(config)
        optimizer = torch.optim.RMSprop(net.parameters(), lr=config.learning_rate)
        cycle = iter(range(10**9))

        def lstm_step() -> object:
            return train_step(net, optimizer, lambda: lstm_batches[next(cycle) % len(lstm_batches)])

        rows = {"social_lstm": _seconds(lstm_step, direct_social_lstm, rounds)}
        for preset in ("social_gan_20v", "social_gan_20vp"):
            gan = gan_fit.Gan.new(preset_config(preset))

            def gan_step(gan: gan_fit.Gan = gan) -> object:
                return gan_fit.iteration(gan, lambda: gan_batches[next(cycle) % len(gan_batches)])

            rows[preset] = _seconds(gan_step, direct_social_gan, rounds)
        for name, (model_s, direct_s) in rows.items():
            results[name] = {"seconds_per_iteration": round(model_s, 4), "direct_seconds_per_iteration":
                             round(direct_s, 4), "speedup": round(direct_s / model_s, 2)}
        return results
    finally:
        torch.set_num_threads(threads)


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--rounds", type=int, default=7)
    parser.add_argument("--dataset", type=Path, help="an ingested dataset: time its real batches")
    parser.add_argument("--split", default="zara1/train")
    args = parser.parse_args()
    print(json.dumps(run(args.quick, args.rounds, args.dataset, args.split), indent=2))
