"""The training scenes as the loop sees them: probed to fit the config to the data (``resolve_config``), then
drawn in batches (``training_batches``): a Sequence is permuted per epoch, a stream goes through a shuffle
buffer, both from a generator seeded with (seed, epoch), so a run resumed at (epoch, position) draws the same
batches as the uninterrupted run (for Sequence inputs; a stream restarts its current pass).
"""

from __future__ import annotations

import itertools
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import replace

import numpy as np

from logpipe.errors import LogpipeError
from logpipe.types import SceneSample

from .config import ConfigError, TrainConfig


class TrainingError(LogpipeError):
    """Training cannot start or continue (empty data, existing run without ``resume``)."""


def _probe(samples: Iterable[SceneSample], limit: int = 256) -> tuple[bool, int | None, int, int]:
    """(any ego, raster channels or None, obs_len, total steps) over the first ``limit`` samples."""
    has_ego = False
    channels: int | None = None
    obs_len = steps = -1
    for s in itertools.islice(samples, limit):
        has_ego |= s.ego_index >= 0
        if s.raster is not None:
            channels = int(s.raster.shape[0])
        obs_len, steps = s.obs_len, int(s.positions.shape[1])
    if obs_len < 0:
        raise TrainingError("the training data is empty")
    return has_ego, channels, obs_len, steps


def resolve_config(config: TrainConfig, train: Iterable[SceneSample]) -> TrainConfig:
    """Fit the config to the data: switch off the features the data cannot feed (no ego: EMF, ETF; no
    raster: EF), take the raster channel count C from the rasters, and check the sample lengths."""
    has_ego, channels, obs_len, steps = _probe(train)
    m = config.model
    if obs_len != m.obs_len or steps < m.obs_len + m.pred_len:
        raise ConfigError(
            f"samples have obs_len {obs_len} and {steps} steps but model.obs_len={m.obs_len}, "
            f"model.pred_len={m.pred_len}; set them to the dataset's protocol"
        )
    m = m.resolved(has_ego=has_ego, has_map=channels is not None)
    if channels is not None and m.features.environment:
        m = replace(m, raster_channels=channels)
    return replace(config, model=m)


def training_batches(
    train: Sequence[SceneSample] | Iterable[SceneSample], config: TrainConfig, epoch: int, skip: int
) -> Iterator[tuple[int, int, list[SceneSample]]]:
    """Yield (epoch, position in epoch, batch) forever (or until a one-shot stream ends), from epoch ``epoch``
    skipping its first ``skip`` scenes (a resumed run)."""
    bs = config.batch_size
    while True:
        rng = np.random.default_rng([config.seed, epoch])
        if isinstance(train, Sequence):
            if len(train) == 0:
                raise TrainingError("the training data is empty")
            order = rng.permutation(len(train))
            for pos in range(skip, len(order) - bs + 1 if len(order) >= bs else 1, bs):
                yield epoch, pos + bs, [train[int(i)] for i in order[pos : pos + bs]]
        else:
            buffer: list[SceneSample] = []
            batch: list[SceneSample] = []
            pos = 0
            stream = iter(train)
            exhausted = False
            while not exhausted or buffer:
                if not exhausted:
                    try:
                        buffer.append(next(stream))
                    except StopIteration:
                        exhausted = True
                    if len(buffer) < config.shuffle_buffer and not exhausted:
                        continue
                if buffer:
                    batch.append(buffer.pop(int(rng.integers(len(buffer)))))
                if len(batch) == bs:
                    pos += bs
                    yield epoch, pos, batch
                    batch = []
            if iter(train) is train:  # a one-shot iterator cannot be re-read
                return
        epoch += 1
        skip = 0
