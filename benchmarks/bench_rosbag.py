"""Bag ingest throughput: ``RosbagAdapter.read`` on the real datmo bags against the floor of reading the same
bags with ``rosbags.highlevel.AnyReader`` and deserialising every message (doing nothing else), in the same run.

Figures are medians over repeats; throughput counts every message and byte in the bags for both, so the ratio
is wall time adapter / floor (target: at most 2). Run: ``python -m benchmarks.bench_rosbag`` (or ``run()``).
"""

from __future__ import annotations

import json
import statistics
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from rosbags.highlevel import AnyReader

from logpipe.formats.rosbag import RosbagAdapter
from logpipe.types import SourceFile

ROOT = Path(__file__).resolve().parents[1]
SHARED_DATMO = ROOT.parent / "shared" / "data" / "rosbags" / "datmo"
LOCAL_DATMO = ROOT / "tests" / "data" / "rosbags" / "datmo"
AUTO_MAPPED = ("intersection", "overtake_ego", "overtake_red", "overtakes", "parallel")  # ego + red, no mapping


def _bags() -> list[Path]:
    folder = SHARED_DATMO if SHARED_DATMO.is_dir() else LOCAL_DATMO
    return sorted(p for p in folder.glob("*.bag") if p.stem in AUTO_MAPPED)


def _floor(bags: list[Path], topics: frozenset[str] | None = None) -> int:
    """Read and deserialise every message (or only those of ``topics``), nothing else."""
    n = 0
    for bag in bags:
        with AnyReader([bag]) as reader:
            conns = [c for c in reader.connections if topics is None or c.topic in topics]
            for conn, _t, raw in reader.messages(connections=conns):
                reader.deserialize(raw, conn.msgtype)
                n += 1
    return n


def _adapter(bags: list[Path]) -> int:
    sources = [SourceFile(str(b), b.name, "", b.stat().st_size) for b in bags]
    parsed = RosbagAdapter().read(sources, keep_going=False)
    return int(parsed.tracks.num_rows)


def _median_time(fn: Callable[[], Any], repeats: int) -> float:
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def run(quick: bool = False) -> dict[str, Any]:
    """Adapter vs floor on the datmo bags, replicated (each pass reads every bag ``copies`` times).

    Returns messages/s, MB/s and seconds for both, ``ratio`` = adapter time / floor time, and
    ``ratio_vs_used_topics`` against a floor that deserialises only the two pose topics the adapter uses.
    """
    bags = _bags()
    copies = 1 if quick else 4
    repeats = 1 if quick else 5
    work = bags * copies
    messages = 0
    for bag in bags:
        with AnyReader([bag]) as reader:
            messages += reader.message_count
    messages *= copies
    mbytes = sum(b.stat().st_size for b in work) / 1e6
    rows = _adapter(bags)  # warm-up (imports, caches) and a sanity check
    assert rows > 0
    floor_s = _median_time(lambda: _floor(work), repeats)
    # a stricter floor: only the topics the adapter reads (the detected /ego_pose and /red_pose)
    used = frozenset({"/ego_pose", "/red_pose"})
    floor_used_s = _median_time(lambda: _floor(work, used), repeats)
    adapter_s = _median_time(lambda: _adapter(work), repeats)
    return {
        "bags": [b.name for b in bags],
        "copies": copies,
        "repeats": repeats,
        "messages": messages,
        "megabytes": round(mbytes, 3),
        "floor_s": round(floor_s, 4),
        "adapter_s": round(adapter_s, 4),
        "floor_msgs_per_s": round(messages / floor_s),
        "adapter_msgs_per_s": round(messages / adapter_s),
        "floor_mb_per_s": round(mbytes / floor_s, 2),
        "adapter_mb_per_s": round(mbytes / adapter_s, 2),
        "ratio": round(adapter_s / floor_s, 3),
        "floor_used_topics_s": round(floor_used_s, 4),
        "ratio_vs_used_topics": round(adapter_s / floor_used_s, 3),
        "target_ratio": 2.0,
        "track_rows_per_copy": rows,
    }


if __name__ == "__main__":
    print(json.dumps(run(quick="--quick" in sys.argv), indent=2))
