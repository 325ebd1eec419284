"""``ShardTracks`` (columnar windowing, issue 35 item 3) cuts the targets ``LogWindows`` + ``SampleCutter`` cut
sample by sample: same targets in the same order, classes, observed positions and future step times, on real
shards and on a hand-made one with the awkward cases (duplicate rows, gaps, repeated or absent target ids,
windows past the log's end, several logs sharing track ids)."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import pytest

from logpipe.dataset.reader import Dataset
from logpipe.dataset.target_tracks import ShardTracks
from logpipe.prediction.model_inputs import SampleCutter, log_windows
from logpipe.prediction.output import future_times
from logpipe.stages.ingest import IngestOptions, ingest
from logpipe.storage.io import read_table
from logpipe.types import OBJECT_TYPES, PROTOCOLS


def _reference(tracks: pa.Table, rows: list[dict[str, Any]], obs_len: int, pred_len: int, dt_ns: list[int],
               types: tuple[str, ...]) -> list[dict[str, Any] | None]:
    """Each row's targets as the per-sample path cuts them (None: no target left)."""
    cutter = SampleCutter(obs_len, types)
    windows = dict(log_windows(tracks, list(dict.fromkeys(r["log_id"] for r in rows))))
    out: list[dict[str, Any] | None] = []
    for row, dt in zip(rows, dt_ns, strict=True):
        sample = cutter.cut(windows[row["log_id"]], row) if row["log_id"] in windows else None
        if sample is None:
            out.append(None)
            continue
        idx = np.flatnonzero(sample.target_mask)
        out.append({"tracks": [sample.track_ids[i] for i in idx], "types": sample.object_types[idx].tolist(),
                    "observed": sample.positions[idx, :obs_len],
                    "step_ns": future_times(sample, obs_len, pred_len, dt)})
    return out


def _check(tracks: pa.Table, rows: list[dict[str, Any]], obs_len: int, pred_len: int,
           types: tuple[str, ...] = ()) -> int:
    dt_ns = [1_000 + 7 * i for i in range(len(rows))]
    want = _reference(tracks, rows, obs_len, pred_len, dt_ns, types)
    got = ShardTracks(tracks).targets(pa.Table.from_pylist(rows), obs_len, pred_len, np.array(dt_ns), types)
    assert got.per_sample.tolist() == [0 if w is None else len(w["tracks"]) for w in want]
    starts = np.concatenate([[0], np.cumsum(got.per_sample)])
    for i, w in enumerate(want):
        if w is None:
            continue
        lo, hi = starts[i], starts[i + 1]
        assert (got.sample_of[lo:hi] == i).all()
        assert got.track_ids[lo:hi].tolist() == w["tracks"], rows[i]["sample_id"]
        assert got.object_types[lo:hi].tolist() == w["types"]
        np.testing.assert_array_equal(got.observed[lo:hi], w["observed"])  # NaN where unobserved, bit for bit
        assert got.step_ns[i].tolist() == w["step_ns"].tolist()
    return int(got.per_sample.sum())


@pytest.mark.parametrize("name", ["ethucy", "argoverse1"])
def test_real_shards_cut_as_sample_by_sample(bundled: Path, tmp_path: Path, name: str) -> None:
    ingest([bundled / name], IngestOptions(out=tmp_path / "d", workers=1, write_mcap=False))
    dataset = Dataset.open(tmp_path / "d")
    rows = dataset.samples().to_pylist()
    proto = dataset.protocol
    checked = 0
    for path in dataset.shard_paths:
        tracks = read_table(path)
        in_shard = set(tracks.column("log_id").to_pylist())
        mine = [r for r in rows if r["log_id"] in in_shard]
        checked += _check(tracks, mine, proto.obs_len, proto.pred_len)
        checked += _check(tracks, mine[::-1], proto.obs_len, proto.pred_len)  # any sample order
    assert checked >= 2 * len(rows) > 0  # every sample has a target


def test_sliding_windows_and_a_type_filter(bundled: Path, tmp_path: Path) -> None:
    proto = replace(PROTOCOLS["rosbag"], name="custom", stride=3, targets="fully_observed")
    ingest([bundled / "argoverse1"], IngestOptions(out=tmp_path / "s", workers=1, write_mcap=False, protocol=proto))
    dataset = Dataset.open(tmp_path / "s")
    rows = dataset.samples().to_pylist()
    tracks = dataset.tracks()
    assert _check(tracks, rows, proto.obs_len, proto.pred_len) > 0
    assert _check(tracks, rows, proto.obs_len, proto.pred_len, ("vehicle",)) > 0
    assert _check(tracks, rows, proto.obs_len, proto.pred_len, ("pedestrian", "cyclist")) == 0


def _row(log: str, track: str, step: int, x: float, kind: str = "vehicle", role: str = "other",
         ts: int | None = None) -> dict[str, Any]:
    return {"log_id": log, "step": step, "track_id": track, "x": x, "y": -x, "object_type": kind, "role": role,
            "timestamp_ns": 100 * step if ts is None else ts}


def test_awkward_rows_cut_as_sample_by_sample() -> None:
    rows = [
        # log a: "p" has a gap and a duplicate row at step 3 (the later one counts); "q" appears at step 2 and
        # changes class; "r" is seen only after the current step; steps 6-7 have no rows at all.
        _row("a", "p", 0, 0.0), _row("a", "p", 1, 1.0), _row("a", "q", 2, 5.0, "pedestrian"),
        _row("a", "p", 3, 3.0), _row("a", "p", 3, 3.5), _row("a", "q", 3, 6.0, "cyclist"),
        _row("a", "r", 4, 9.0), _row("a", "p", 5, 5.0, ts=0), _row("a", "q", 8, 7.0),
        # log b reuses the track id "p" and starts at step 10.
        _row("b", "p", 10, 10.0), _row("b", "s", 10, 20.0, "pedestrian"), _row("b", "p", 11, 11.0),
        _row("b", "s", 12, 22.0, "pedestrian"), _row("b", "p", 13, 13.0, role="ego"),
    ]
    tracks = pa.Table.from_pylist(rows)
    samples = [
        {"log_id": "a", "sample_id": "a:0", "start_step": 0, "end_step": 6, "target_track_ids": ["q", "p", "p"]},
        {"log_id": "a", "sample_id": "a:2", "start_step": 2, "end_step": 9, "target_track_ids": ["r", "q", "zz", "p"]},
        {"log_id": "a", "sample_id": "a:5", "start_step": 5, "end_step": 12, "target_track_ids": ["p", "q"]},
        {"log_id": "b", "sample_id": "b:10", "start_step": 10, "end_step": 14, "target_track_ids": ["s", "p"]},
        {"log_id": "b", "sample_id": "b:9", "start_step": 9, "end_step": 13, "target_track_ids": []},
        {"log_id": "c", "sample_id": "c:0", "start_step": 0, "end_step": 4, "target_track_ids": ["p"]},
    ]
    assert _check(tracks, samples, 3, 4) == 9
    assert _check(tracks, samples, 2, 5, ("pedestrian", "cyclist")) > 0
    assert OBJECT_TYPES.index("cyclist") in ShardTracks(tracks).targets(
        pa.Table.from_pylist(samples[:1]), 3, 4, np.array([1]), ()).object_types.tolist()  # last row's class
