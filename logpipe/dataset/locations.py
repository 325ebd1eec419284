"""Where logs were recorded: counts per location for summaries, and one agent recorded in two logs of a location.

A log's location is its ``attributes["location"]`` (CommonRoad: ``USA_US101``), else its ``map_id`` (Argoverse:
the city).

**Shared tracks.** Scenario files cut from one recording can overlap: CommonRoad's NGSIM files show some vehicles in
two files, each file in its own local frame and with its own time origin. Two tracks of two logs with the same
``attributes["location"]`` are one agent recorded twice when they have the same track id, the same box size and,
over at least ``MIN_SHARED_STEPS`` consecutive steps at the same period, positions that differ by one constant
offset (within ``OFFSET_TOLERANCE_M``) while the agent travels at least ``MIN_PATH_M`` (a parked car matches
any offset, so it is not taken as evidence). The later log (in dataset order) records them in its attributes:
``shared_tracks = {earlier_log_id: {"tracks": [ids], "offset_m": [dx, dy], "offset_s": dt}}``, where the
earlier log's frame is this log's plus ``offset_m`` and its clock this log's plus ``offset_s``. The rows stay in
both logs (each scene keeps its neighbours); splits that must keep one agent out of two sets hold out whole
locations, or drop logs that share tracks with the other side.
"""

from __future__ import annotations

import itertools
import json
from collections import Counter, defaultdict
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc

from logpipe.storage.io import as_numpy, read_table
from logpipe.types import NDArrayFloat, NDArrayInt

MIN_SHARED_STEPS = 10
"""Consecutive steps two tracks must share to count as one agent (1 s at 10 Hz)."""
OFFSET_TOLERANCE_M = 0.01
"""How far the offset between the two tracks' positions may vary over the shared steps, metres."""
MIN_PATH_M = 1.0
"""How far the agent must travel over the shared steps, metres."""
TRACK_COLUMNS = ["log_id", "track_id", "timestamp_ns", "x", "y", "length", "width"]
"""The track-table columns ``shared_tracks`` reads."""


def log_location(attributes: str | dict[str, Any] | None, map_id: str | None) -> str | None:
    """A log's location: ``attributes["location"]`` (a dict or its JSON text), else ``map_id``; a simulated log's
    (``attributes["synthetic"]``) is ``"<location> (synthetic)"``, so counts never mix it with recordings."""
    found = attributes if isinstance(attributes, dict) else json.loads(attributes or "{}")
    location = found.get("location") or map_id
    return f"{location} (synthetic)" if location and found.get("synthetic") else location


def location_counts(logs: pa.Table, samples: pa.Table) -> dict[str, dict[str, int]]:
    """Logs, tracks, windows (samples) and targets per location, locations sorted; {} when no log has one."""
    locations = [log_location(a, m) for a, m in zip(logs.column("attributes").to_pylist(),
                                                      logs.column("map_id").to_pylist(), strict=True)]
    if not any(locations):
        return {}
    where = dict(zip(logs.column("log_id").to_pylist(), locations, strict=True))
    counts: dict[str, Counter[str]] = defaultdict(Counter)
    for loc, tracks in zip(locations, logs.column("num_tracks").to_pylist(), strict=True):
        counts[str(loc)].update(logs=1, tracks=int(tracks))
    for log_id, targets in zip(samples.column("log_id").to_pylist(),
                               samples.column("target_track_ids").to_pylist(), strict=True):
        counts[str(where.get(str(log_id)))].update(windows=1, targets=len(targets))
    return {loc: {k: c[k] for k in ("logs", "tracks", "windows", "targets")} for loc, c in sorted(counts.items())}


def log_locations(logs: pa.Table) -> dict[str, str | None]:
    """Log id -> its location (``log_location``) for every log of a logs table."""
    return {str(log_id): log_location(a, m) for log_id, a, m in zip(
        logs.column("log_id").to_pylist(), logs.column("attributes").to_pylist(), logs.column("map_id").to_pylist(),
        strict=True)}


def window_locations(logs: Iterable[pa.Table], window_log_ids: Iterable[str]) -> dict[str, int]:
    """Windows per location, sorted, of windows whose logs are ``window_log_ids`` (one entry per window) in the
    logs tables ``logs``: what a model trained on them has seen; windows of a log without a location are not
    counted ({} when none has one)."""
    counts = Counter(locations_of(logs, window_log_ids))
    return {str(loc): n for loc, n in sorted(counts.items(), key=lambda item: str(item[0])) if loc}


def locations_of(logs: Iterable[pa.Table], log_ids: Iterable[str]) -> list[str | None]:
    """The location of each of ``log_ids`` (one entry per target or window) in the logs tables ``logs``."""
    where: dict[str, str | None] = {}
    for table in logs:
        where |= log_locations(table)
    return [where.get(log_id) for log_id in log_ids]


@dataclass(frozen=True)
class _Track:
    """One track's positions at a regular period (metres, world frame of its log; ns)."""

    log_id: str
    track_id: str
    t: NDArrayInt
    xy: NDArrayFloat


def shared_tracks(tracks: pa.Table, log_order: list[str],
                  locations: dict[str, str]) -> dict[str, dict[str, dict[str, Any]]]:
    """The shared tracks of the logs in ``log_order`` (see the module docstring), by later log.

    Candidates come from hashing every run of ``MIN_SHARED_STEPS`` steps of each track's motion (displacements to
    the centimetre, keyed by location, id and size): two tracks share a run only where their offset is constant
    over it, and each candidate alignment is then checked over the whole overlap at ``OFFSET_TOLERANCE_M``.

    Args:
        tracks: ``TRACK_COLUMNS`` of those logs' rows.
        log_order: the logs, earlier first (dataset order).
        locations: ``attributes["location"]`` of each log that has one; other logs are not compared.
    """
    rank = {log_id: i for i, log_id in enumerate(log_order)}
    seen: dict[bytes, list[tuple[int, int]]] = defaultdict(list)  # run hash -> (track, first step)
    located = list(_tracks(tracks, locations))
    candidates: set[tuple[int, int, int]] = set()
    for number, (track, key) in enumerate(located):
        for start, run in _runs(track, key):
            for other, other_start in seen[run]:
                if located[other][0].log_id != track.log_id:
                    candidates.add((other, number, start - other_start))
            seen[run].append((number, start))
    found: dict[tuple[str, str], list[tuple[str, tuple[float, float], float]]] = defaultdict(list)
    for first, second, step_shift in sorted(candidates):
        a, b = located[first][0], located[second][0]
        flip = rank.get(a.log_id, len(rank)) > rank.get(b.log_id, len(rank))
        if flip:
            a, b = b, a
        match = _offset(a, b, -step_shift if flip else step_shift)
        if match is not None:
            found[(b.log_id, a.log_id)].append((b.track_id, *match))
    out: dict[str, dict[str, dict[str, Any]]] = defaultdict(dict)
    for (later_id, earlier_id), matches in sorted(found.items()):
        kept = _agreeing(sorted(set(matches)))
        offset_m, offset_s = kept[0][1], kept[0][2]
        out[later_id][earlier_id] = {"tracks": sorted({m[0] for m in kept}), "offset_m": list(offset_m),
                                     "offset_s": offset_s}
    return dict(out)


def _tracks(tracks: pa.Table, locations: dict[str, str]) -> Iterable[tuple[_Track, tuple[Any, ...]]]:
    """Each track of a located log with its grouping key (location, id, length, width)."""
    located = tracks.filter(pc.is_in(tracks.column("log_id"), pa.array(sorted(locations), pa.string())))
    if not located.num_rows:
        return
    located = located.sort_by([("log_id", "ascending"), ("track_id", "ascending"), ("timestamp_ns", "ascending")])
    logs, ids = located.column("log_id").to_pylist(), located.column("track_id").to_pylist()
    t = as_numpy(located.column("timestamp_ns")).astype(np.int64)
    xy = np.stack([as_numpy(located.column("x")), as_numpy(located.column("y"))], axis=1).astype(np.float64)
    sizes = list(zip(located.column("length").to_pylist(), located.column("width").to_pylist(), strict=True))
    codes = [as_numpy(pc.dictionary_encode(located.column(c).combine_chunks()).indices) for c in ("log_id", "track_id")]
    starts = np.flatnonzero((np.diff(codes[0]) != 0) | (np.diff(codes[1]) != 0)) + 1
    bounds = [0, *starts.tolist(), located.num_rows]
    for start, end in itertools.pairwise(bounds):
        yield (_Track(logs[start], ids[start], t[start:end], xy[start:end]),
               (locations[logs[start]], ids[start], *sizes[start]))


def _runs(track: _Track, key: tuple[Any, ...]) -> Iterable[tuple[int, bytes]]:
    """(first step, hash key) of each run of ``MIN_SHARED_STEPS`` steps in which the track moves ``MIN_PATH_M``."""
    if len(track.t) < MIN_SHARED_STEPS:
        return
    steps = np.diff(track.xy, axis=0)
    moved = np.concatenate([[0.0], np.cumsum(np.linalg.norm(steps, axis=1))])
    cm = np.round(steps * 100).astype(np.int64)
    period = np.diff(track.t)
    prefix = repr(key).encode()
    for start in range(len(track.t) - MIN_SHARED_STEPS + 1):
        stop = start + MIN_SHARED_STEPS - 1
        if moved[stop] - moved[start] < MIN_PATH_M:
            continue
        yield start, prefix + period[start:stop].tobytes() + cm[start:stop].tobytes()


def _offset(a: _Track, b: _Track, shift: int) -> tuple[tuple[float, float], float] | None:
    """(offset_m, offset_s) taking ``b``'s frame and clock to ``a``'s when ``b``'s step ``i + shift`` is ``a``'s
    step ``i`` over their whole overlap (positions at one constant offset), else None."""
    i0, j0 = max(0, -shift), max(0, shift)
    n = min(len(a.t) - i0, len(b.t) - j0)
    if n < MIN_SHARED_STEPS:
        return None
    ends = a.xy[[i0, i0 + n - 1]] - b.xy[[j0, j0 + n - 1]]
    if np.abs(ends[1] - ends[0]).max() > 2 * OFFSET_TOLERANCE_M:  # cheap first: most candidates fail here
        return None
    diff = a.xy[i0:i0 + n] - b.xy[j0:j0 + n]
    if np.abs(diff - diff[0]).max() > 2 * OFFSET_TOLERANCE_M:
        return None
    if (np.diff(a.t[i0:i0 + n]) != np.diff(b.t[j0:j0 + n])).any():
        return None  # the two sample the shared stretch at different times
    offset = np.median(diff, axis=0)
    if np.abs(diff - offset).max() > OFFSET_TOLERANCE_M:
        return None
    return (round(float(offset[0]), 4), round(float(offset[1]), 4)), round(float(a.t[i0] - b.t[j0]) / 1e9, 6)


def _agreeing(matches: list[tuple[str, tuple[float, float], float]]) -> list[tuple[str, tuple[float, float], float]]:
    """The matches of a pair of logs that agree with their most common (offset, time shift): one pair of files
    has one frame offset, so a track that disagrees is a coincidence, not the same agent."""
    def key(m: tuple[str, tuple[float, float], float]) -> tuple[float, float, float]:
        return (round(m[1][0], 1), round(m[1][1], 1), m[2])

    common = Counter(key(m) for m in matches).most_common(1)[0][0]
    return [m for m in matches if key(m) == common]


def annotate_shared(logs: pa.Table, shared: dict[str, dict[str, dict[str, Any]]]) -> pa.Table:
    """``logs`` with ``shared_tracks`` added to the attributes of the logs ``shared`` names."""
    if not shared:
        return logs
    texts = logs.column("attributes").to_pylist()
    for i, log_id in enumerate(logs.column("log_id").to_pylist()):
        if log_id in shared:
            attributes = json.loads(texts[i] or "{}")
            attributes["shared_tracks"] = shared[log_id]
            texts[i] = json.dumps(attributes, sort_keys=True)
    index = logs.schema.get_field_index("attributes")
    return logs.set_column(index, logs.schema.field(index), pa.array(texts, logs.schema.field(index).type))


def count_shared(shared: dict[str, dict[str, dict[str, Any]]]) -> dict[str, int]:
    """How many tracks, logs and log pairs ``shared`` names (the later log's side)."""
    return {"tracks": sum(len(info["tracks"]) for pairs in shared.values() for info in pairs.values()),
            "logs": len(shared), "pairs": sum(len(pairs) for pairs in shared.values())}


def dataset_shared_tracks(logs: pa.Table, shard_files: dict[str, Path]) -> dict[str, dict[str, dict[str, Any]]]:
    """``shared_tracks`` of a dataset's logs (``logs``: its logs table in order, ids as strings), reading the located
    logs' rows from their shards (``shard_files``: shard name in the ``shard`` column → file). Logs without an
    ``attributes["location"]`` are not compared, and nothing is read when no log has one."""
    texts = logs.column("attributes").to_pylist()
    ids = logs.column("log_id").to_pylist()
    locations = {log_id: loc for log_id, text in zip(ids, texts, strict=True)
                 if text and '"location"' in text and (loc := json.loads(text).get("location"))}
    if not locations:
        return {}
    wanted = pa.array(sorted(locations), pa.string())
    shards = sorted({s for s, log_id in zip(logs.column("shard").to_pylist(), ids, strict=True) if log_id in locations})
    parts = [read_table(shard_files[s], columns=TRACK_COLUMNS) for s in shards]
    rows = pa.concat_tables([p.filter(pc.is_in(pc.cast(p.column("log_id"), pa.string()), wanted)) for p in parts])
    rows = rows.set_column(0, "log_id", pc.cast(rows.column("log_id"), pa.string()))
    return shared_tracks(rows.set_column(1, "track_id", pc.cast(rows.column("track_id"), pa.string())), ids,
                         locations)


def track_sharing_groups(log_ids: Sequence[str], attributes: Sequence[str | None]) -> dict[str, str]:
    """Log id → the first log (in ``log_ids`` order) of its group: logs joined, transitively, by the pairs their
    ``attributes["shared_tracks"]`` name; a log that shares no track is its own group. One agent is never on both
    sides of a split made by group (``Dataset.logs_in_split``'s ``hash/...``, ``logpipe.dataset.holdout``)."""
    first = {log_id: log_id for log_id in log_ids}

    def root(log_id: str) -> str:
        while first[log_id] != log_id:
            first[log_id] = first[first[log_id]]
            log_id = first[log_id]
        return log_id

    order = {log_id: i for i, log_id in enumerate(log_ids)}
    for log_id, text in zip(log_ids, attributes, strict=True):
        if not text or "shared_tracks" not in text:
            continue
        for other in json.loads(text).get("shared_tracks", {}):
            if str(other) in first:
                a, b = root(log_id), root(str(other))
                if a != b:  # the earlier root stays the group's name
                    first[max(a, b, key=order.__getitem__)] = min(a, b, key=order.__getitem__)
    return {log_id: root(log_id) for log_id in log_ids}
