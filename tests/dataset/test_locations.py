"""Shared tracks across logs of one location, and per-location counts, on small synthetic tables."""

from __future__ import annotations

import json

import numpy as np
import pyarrow as pa

from logpipe.dataset.locations import MIN_SHARED_STEPS, count_shared, location_counts, shared_tracks


def _rows(log_id: str, track_id: str, xy: np.ndarray, first_step: int, size: tuple[float, float] = (4.5, 1.8)
          ) -> dict[str, list[object]]:
    n = len(xy)
    return {"log_id": [log_id] * n, "track_id": [track_id] * n,
            "timestamp_ns": [(first_step + i) * 100_000_000 for i in range(n)], "x": xy[:, 0].tolist(),
            "y": xy[:, 1].tolist(), "length": [size[0]] * n, "width": [size[1]] * n}


def _table(*parts: dict[str, list[object]]) -> pa.Table:
    merged: dict[str, list[object]] = {k: [] for k in parts[0]}
    for part in parts:
        for k, v in part.items():
            merged[k] += v
    return pa.table(merged)


def _drive(n: int, seed: int) -> np.ndarray:
    """A car's path: speed-varying, curving (not constant velocity, so a shift of the index cannot fit it)."""
    rng = np.random.default_rng(seed)
    speed = 8 + np.cumsum(rng.normal(0, 0.3, n))
    heading = np.cumsum(rng.normal(0, 0.02, n))
    return np.cumsum(np.stack([speed * np.cos(heading), speed * np.sin(heading)], axis=1) * 0.1, axis=0)


def test_one_car_in_two_frames_is_found_with_its_offset() -> None:
    path = _drive(80, 0)
    a = _rows("a", "7", path[:60], first_step=0)
    b = _rows("b", "7", path[30:] + np.array([50.0, -3.0]), first_step=5)  # the same car, another frame and clock
    found = shared_tracks(_table(a, b), ["a", "b"], {"a": "X", "b": "X"})
    assert found == {"b": {"a": {"tracks": ["7"], "offset_m": [-50.0, 3.0], "offset_s": 2.5}}}
    assert count_shared(found) == {"tracks": 1, "logs": 1, "pairs": 1}


def test_look_alikes_are_not_the_same_car() -> None:
    path = _drive(80, 1)
    parked = np.zeros((40, 2)) + np.array([3.0, 4.0])
    tables = [
        (_rows("a", "7", path, 0), _rows("b", "8", path + 1.0, 0)),  # another id
        (_rows("a", "7", path, 0), _rows("b", "7", path + 1.0, 0, size=(5.0, 1.8))),  # another size
        (_rows("a", "7", parked, 0), _rows("b", "7", parked + 9.0, 0)),  # parked: any offset fits
        (_rows("a", "7", path[:MIN_SHARED_STEPS - 1], 0), _rows("b", "7", path[:MIN_SHARED_STEPS - 1] + 1, 0)),
        (_rows("a", "7", path, 0), _rows("b", "7", _drive(80, 2), 0)),  # another path
    ]
    for first, second in tables:
        assert shared_tracks(_table(first, second), ["a", "b"], {"a": "X", "b": "X"}) == {}
    # the same car, but the logs are of different locations (or have none): not compared
    same = _table(_rows("a", "7", path, 0), _rows("b", "7", path + 1.0, 0))
    assert shared_tracks(same, ["a", "b"], {"a": "X", "b": "Y"}) == {}
    assert shared_tracks(same, ["a", "b"], {"a": "X"}) == {}


def test_counts_per_location() -> None:
    logs = pa.table({"log_id": ["a", "b", "c"], "map_id": ["a", "b", "MIA"], "num_tracks": [3, 4, 5],
                     "attributes": [json.dumps({"location": "X"}), json.dumps({"location": "X"}), "{}"]})
    samples = pa.table({"log_id": ["a", "a", "c"], "target_track_ids": [["1", "2"], ["1"], ["9"]]})
    assert location_counts(logs, samples) == {"MIA": {"logs": 1, "tracks": 5, "windows": 1, "targets": 1},
                                              "X": {"logs": 2, "tracks": 7, "windows": 2, "targets": 3}}
