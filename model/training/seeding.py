"""Per-sample random streams: a forecast's random draws depend only on (seed, sample), never on which samples
shared its batch, how many workers ran, or in which order (issue 35 item 2; the arithmetic's half is
``row_blocks``)."""

from __future__ import annotations

import hashlib


def sample_seed(seed: int, sample_id: str) -> int:
    """A 63-bit seed for ``sample_id``'s random draws under run seed ``seed`` (sha256 of both; stable across
    processes and machines, unlike ``hash``)."""
    digest = hashlib.sha256(f"{seed}\x00{sample_id}".encode()).digest()
    return int.from_bytes(digest[:8], "little") >> 1
