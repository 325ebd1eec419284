"""Per-sample random streams: a forecast depends only on (checkpoint, settings, seed, sample), never on which
samples shared its batch, how many workers ran, or in which order (issue: predictions independent of batching)."""

from __future__ import annotations

import hashlib


def sample_seed(seed: int, sample_id: str) -> int:
    """A 63-bit seed for ``sample_id``'s random draws under run seed ``seed`` (sha256 of both; stable across
    processes and machines, unlike ``hash``)."""
    digest = hashlib.sha256(f"{seed}\x00{sample_id}".encode()).digest()
    return int.from_bytes(digest[:8], "little") >> 1
