"""The logs table's rows from a batch of track rows (``logpipe.dataset.log_table``): canonical order, per-log statistics
equal to a plain group-by over the bundled real samples, and the vectorised helpers against their definitions."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
import pytest

from logpipe.dataset.log_table import (
    STAT_KEYS,
    canonical_order,
    column_equals,
    distinct_per_group,
    log_metas,
    log_rows,
    median_step,
)
from logpipe.dataset.samples import TrackCodes
from logpipe.formats import get_adapter
from logpipe.formats.inputs import collect_sources
from logpipe.types import LogMeta, Role


def _parsed(bundled: Path, name: str) -> tuple[pa.Table, list[LogMeta]]:
    adapter = get_adapter(name)
    parsed = adapter.read(collect_sources([bundled / name], adapter), keep_going=False)
    return canonical_order(parsed.tracks), parsed.logs


@pytest.mark.parametrize("name", ["argoverse1", "ethucy", "apolloscape"])
def test_log_rows_equal_a_plain_group_by(bundled: Path, name: str) -> None:
    tracks, metas = _parsed(bundled, name)
    plain = tracks.cast(pa.schema([f.with_type(pa.string()) if pa.types.is_dictionary(f.type) else f
                                   for f in tracks.schema]))
    # Canonical order: each log's rows contiguous, time ascending in each (an adapter that gives ``step`` keeps
    # its own log and track order).
    log_ids = plain.column("log_id").to_pylist()
    same_log = np.array(log_ids[1:]) == np.array(log_ids[:-1])
    assert int((~same_log).sum()) + 1 == len(set(log_ids))
    ts = plain.column("timestamp_ns").to_numpy()
    assert np.all(np.diff(ts)[same_log] >= 0)
    logs, empty = log_rows(tracks, metas, "tracks/part-00000.parquet", TrackCodes.of(tracks))
    assert empty == [] and logs.column("log_id").to_pylist() == [m.log_id for m in metas]
    assert set(logs.column("shard").to_pylist()) == {"tracks/part-00000.parquet"}
    for row in logs.to_pylist():
        rows = plain.filter(pc.equal(plain.column("log_id"), row["log_id"]))
        ts = np.unique(rows.column("timestamp_ns").to_numpy())
        assert row["num_rows"] == rows.num_rows
        assert row["num_tracks"] == len(set(rows.column("track_id").to_pylist()))
        assert row["num_steps"] == len(ts) == max(rows.column("step").to_pylist()) + 1
        assert (row["start_ns"], row["end_ns"]) == (ts[0], ts[-1])
        assert row["median_dt_ns"] == (int(np.floor(np.median(np.diff(ts)))) if len(ts) > 1 else 0)
        assert row["has_ego"] == (Role.EGO.value in rows.column("role").to_pylist())
    assert all(key in logs.column_names for key in STAT_KEYS)


def test_metas_without_rows_are_returned_apart_and_metas_read_back(bundled: Path) -> None:
    tracks, metas = _parsed(bundled, "argoverse1")
    ghost = LogMeta(log_id="ghost", source_format="argoverse1", source_file="ghost.csv", source_sha256="0" * 64,
                    map_id="MIA", frame_rate_hz=10.0)
    logs, empty = log_rows(tracks, [*metas, ghost], "tracks/part-00000.parquet", TrackCodes.of(tracks))
    assert empty == [ghost] and "ghost" not in logs.column("log_id").to_pylist()
    assert log_metas(logs) == [LogMeta(m.log_id, m.source_format, m.source_file, m.source_sha256, m.map_id,
                                       m.frame_rate_hz) for m in metas]


def test_canonical_order_sorts_and_numbers_steps() -> None:
    tracks = pa.table({
        "log_id": ["b", "a", "a", "b", "a"], "track_id": ["2", "9", "1", "1", "1"],
        "timestamp_ns": [5, 30, 10, 5, 30], "object_type": ["pedestrian"] * 5, "role": ["agent"] * 5,
        "x": [0.0] * 5, "y": [0.0] * 5, "source_type": ["x"] * 5,
    })
    ordered = canonical_order(tracks)
    assert ordered.column("log_id").to_pylist() == ["a", "a", "a", "b", "b"]
    assert ordered.column("track_id").to_pylist() == ["1", "1", "9", "1", "2"]
    assert ordered.column("step").to_pylist() == [0, 1, 1, 0, 0]


def test_median_step_is_numpys_median_per_log() -> None:
    rng = np.random.default_rng(0)
    owners = np.sort(rng.integers(0, 6, 200))
    owners = owners[owners != 3]  # log 3 has no step; log 5 gets one step only
    owners = np.concatenate([owners[owners != 5], [5]])
    ts = np.concatenate([np.cumsum(rng.integers(1, 1000, int((owners == i).sum()))) for i in range(6)])
    result = median_step(owners, ts, 7)
    for i in range(7):
        gaps = np.diff(ts[owners == i])
        assert result[i] == (int(np.floor(np.median(gaps))) if len(gaps) else 0)


@pytest.mark.parametrize("n_codes", [50, 1 << 24])  # a presence table, then the sort past 16 MB of it
def test_distinct_per_group_counts_distinct_codes(n_codes: int) -> None:
    rng = np.random.default_rng(1)
    groups = rng.integers(0, 4, 500)
    codes = rng.integers(0, n_codes, 500)
    codes[0] = n_codes - 1
    expected = [len(set(codes[groups == g].tolist())) for g in range(5)]
    assert distinct_per_group(groups, codes, 5).tolist() == expected


def test_column_equals_by_codes_equals_string_compare() -> None:
    values = ["ego", "agent", None, "ego", "other"]
    plain = pa.chunked_array([pa.array(values)])
    encoded = pa.chunked_array([pa.array(values).dictionary_encode()])
    expected = [v == "ego" for v in values]
    assert column_equals(plain, "ego").tolist() == expected
    assert column_equals(encoded, "ego").tolist() == expected
