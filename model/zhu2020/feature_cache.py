"""Opt-in in-memory cache of a frozen backbone's feature maps (``train.cache_backbone_features``).

With ``model.freeze_backbone`` the backbone (ResNet18 stages 1-2, ``backbone.py``) is a fixed function of the
raster, so a training sample's feature map is the same in every epoch: the cache computes it once and later epochs
skip the backbone's forward (1 core, Argoverse-shaped scenes: 9.2 against 6.3 samples/s frozen without the cache,
4.4 trained, 15.2 for v4 without the environment net; ``benchmarks/bench_model.py``, ``train_env_cost``).

Key: (sample id, BLAKE2b digest of the raster the backbone reads, i.e. the collated float32 (C, H, W) image and its
shape), so a sample whose raster changed (re-rasterised, or any augmentation that alters pixels) is a miss and is
never served a stale map. Scenes without a raster (an all-zero image whose environment feature is masked to 0) share
one entry per raster size. Rotation augmentation (``train.augment_rotate``) rotates the model frame and the
frame-to-pixel affine only, not the raster's pixels, so it keeps hitting the cache and stays exact (tested).

Exactness: a step with any scene not in the cache runs the backbone on its whole batch, the very call an uncached
step makes, and stores the new maps; only a step whose scenes all hit skips the backbone. Entries are the backbone's
own float32 output (no fp16/bf16 down-cast), so a hit is bit for bit the uncached map provided an image's map does
not depend on which other images share a batch of the same size. That holds for the oneDNN CPU convolutions here
(checked at 1 and 2 threads; ``tests/model/test_backbone_cache.py`` trains bit-identically with and without the
cache), but not across batch sizes: a batch of ONE 64 x 64 image took another kernel (2e-6 off), hence whole
batches rather than the misses alone. On CUDA cuDNN may choose algorithms per call, so there hits match to float
rounding only.

Memory: 4 B x 128 x (H/8) x (W/8) per sample, 401,408 B for a 224 x 224 raster (any channel count): Argoverse's
16k training windows take 6.4 GB (6.0 GiB). ``max_bytes`` (``train.cache_backbone_max_mb``) bounds it; once it is
full, further samples are not stored (``CacheStats.unstored``) and every step drawing one of them runs the
backbone on its whole batch: a cache holding a fraction f of the samples skips ~f^B of the later steps, so size it
to the training set. Nothing is evicted: in a shuffled epoch every sample is read once, so an LRU would miss on
every read. Kept in memory rather than in a memory-mapped file under the run folder: no scratch artifact to commit
or clean up, and a resumed run refills it in its first epoch.

Validation and prediction do not use it: they run the backbone as before (their samples are not the training
samples, and a checkpoint carries no cache).
"""

from __future__ import annotations

import hashlib
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from logpipe.types import SceneSample

from .batching import Batch
from .environment import EnvironmentNet

CacheKey = tuple[str, bytes]
"""(sample id, or "" for a scene without a raster; BLAKE2b-128 digest of the collated raster and its shape)."""


@dataclass
class CacheStats:
    """Counts over the cache's life, per scene looked up.

    Attributes:
        hits: maps served from the cache (in steps that skipped the backbone).
        misses: scenes whose key was not stored (first sight, or not stored because the cache was full).
        computed: maps the backbone computed (every scene of a step with a miss).
        stored: entries held.
        stored_bytes: bytes the entries hold.
        unstored: misses not stored because ``max_bytes`` was reached.
    """

    hits: int = 0
    misses: int = 0
    computed: int = 0
    stored: int = 0
    stored_bytes: int = 0
    unstored: int = 0


def scene_keys(samples: Sequence[SceneSample], batch: Batch) -> list[CacheKey] | None:
    """Cache key of each scene of ``batch`` (collated from ``samples``, still on the CPU); None when the batch
    has no raster (the environment net is off or no scene has a map: nothing to cache)."""
    if batch.raster is None:
        return None
    raster = batch.raster.detach().cpu().contiguous().numpy()
    b = batch.size
    # Scenes are the samples unless ModelConfig.context_radius_m cut each target into its own scene; those scenes
    # always hold a row (their target), so the first row says which sample a scene came from.
    of_scene = np.arange(b) if b == len(samples) else batch.sample[batch.offsets[:-1]]
    has_raster = batch.has_raster.cpu().numpy()
    keys: list[CacheKey] = []
    for i in range(b):
        digest = hashlib.blake2b(repr(raster.shape[1:]).encode(), digest_size=16)
        digest.update(raster[i])
        sample_id = samples[int(of_scene[i])].sample_id if has_raster[i] else ""
        keys.append((sample_id, digest.digest()))
    return keys


class BackboneFeatureCache:
    """Feature maps of a frozen ``EnvironmentNet`` backbone by ``CacheKey``, held on the CPU in float32.

    Attributes:
        max_bytes: bound on the bytes of the stored maps.
        stats: hit/miss counts.
    """

    def __init__(self, max_bytes: int) -> None:
        self.max_bytes = max_bytes
        self.stats = CacheStats()
        self._maps: dict[CacheKey, Tensor] = {}

    def feature_maps(self, env: EnvironmentNet, raster: Tensor, keys: Sequence[CacheKey]) -> Tensor:
        """``env.feature_map(raster)`` (B, 128, H/8, W/8) for rasters (B, C, H, W) whose scenes have ``keys``:
        from the cache when every key is stored, else from the backbone on the whole batch (storing the new maps)."""
        if not env.frozen:
            raise ValueError("the backbone feature cache needs a frozen backbone (model.freeze_backbone)")
        if len(keys) != raster.shape[0]:
            raise ValueError(f"{len(keys)} cache keys for {raster.shape[0]} rasters")
        missing = [i for i, key in enumerate(keys) if key not in self._maps]
        if not missing:
            self.stats.hits += len(keys)
            return torch.stack([self._maps[k] for k in keys]).to(raster.device)
        with torch.no_grad():  # frozen weights: no graph either way, the same arithmetic
            fmap = env.feature_map(raster)
        self.stats.misses += len(missing)
        self.stats.computed += len(keys)
        for i in missing:
            if keys[i] not in self._maps:  # a key twice in one batch (context scenes of one sample) is stored once
                self._store(keys[i], fmap[i])
        return fmap

    def _store(self, key: CacheKey, fmap: Tensor) -> None:
        size = fmap.numel() * fmap.element_size()
        if self.stats.stored_bytes + size > self.max_bytes:
            self.stats.unstored += 1
            return
        # clone: a slice of the batch's map would keep the whole batch's storage alive.
        self._maps[key] = fmap.detach().to("cpu", copy=True)
        self.stats.stored += 1
        self.stats.stored_bytes += size
