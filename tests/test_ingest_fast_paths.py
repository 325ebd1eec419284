"""The shortcuts that make ingest fast keep its results: vectorised checks, Parquet encodings, detection, codes."""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from logpipe.formats import detect
from logpipe.formats._text import stem, times_sorted_and_unique
from logpipe.formats.argoverse1 import Argoverse1Adapter
from logpipe.inputs import collect_sources
from logpipe.io import parquet_options
from logpipe.samples import TrackCodes
from logpipe.stages.ingest import _canonical_order


@pytest.mark.parametrize(
    ("ts", "tracks", "files", "expected"),
    [
        ([1, 1, 2, 2], [0, 1, 0, 1], [0, 0, 0, 0], True),
        ([1, 1, 2, 1], [0, 1, 0, 1], [0, 0, 0, 0], False),  # time goes backwards inside a file
        ([5, 6, 1, 2], [0, 0, 0, 0], [0, 0, 1, 1], True),  # ... but may restart in the next file
        ([1, 1, 2, 2], [0, 0, 0, 1], [0, 0, 0, 0], False),  # the same (track, time) twice
        ([1, 1], [0, 0], [0, 1], True),  # the same (track, time) in two files is fine
        ([1, 2, 2, 2], [3, 0, 1, 0], [0, 0, 0, 0], False),  # duplicate not adjacent within its time
    ],
)
def test_time_and_duplicate_fast_check(ts: list[int], tracks: list[int], files: list[int], expected: bool) -> None:
    as_int = [np.array(v, dtype=np.int64) for v in (ts, tracks, files)]
    assert times_sorted_and_unique(*as_int) is expected


@pytest.mark.parametrize("relpath", ["a/b.csv", "x.tar.gz", ".hidden", "a/.b", "noext", "dir.x/file", "a/b."])
def test_stem_matches_pathlib(relpath: str) -> None:
    assert stem(relpath) == Path(relpath).stem


def test_parquet_options_split_floats_and_choose_statistics() -> None:
    table = pa.table({
        "log_id": ["a", "b"], "track_id": ["t", "u"], "x": [1.5, 2.5],
        "ids": pa.array([["p"], ["q"]], pa.list_(pa.string())), "xs": pa.array([[1.0], [2.0]], pa.list_(pa.float64())),
    })
    options = parquet_options(table.schema, string_statistics=["log_id"])
    buffer = io.BytesIO()
    pq.write_table(table, buffer, **options)
    meta = pq.ParquetFile(io.BytesIO(buffer.getvalue())).metadata.row_group(0)
    columns = {meta.column(i).path_in_schema: meta.column(i) for i in range(meta.num_columns)}
    assert "BYTE_STREAM_SPLIT" in columns["x"].encodings and "BYTE_STREAM_SPLIT" in columns["xs.list.element"].encodings
    assert "RLE_DICTIONARY" in columns["log_id"].encodings and "RLE_DICTIONARY" in columns["ids.list.element"].encodings
    assert columns["log_id"].is_stats_set and columns["x"].is_stats_set and not columns["track_id"].is_stats_set
    assert pq.read_table(io.BytesIO(buffer.getvalue())).equals(table)


def test_fast_detect_agrees_with_detect(bundled: Path, tmp_path: Path) -> None:
    from logpipe.formats import _first_files

    for name in ("argoverse1", "ethucy", "apolloscape", "rosbags"):  # one os.walk = the sorted rglob it replaced
        assert _first_files(bundled / name, 200) == sorted(p for p in (bundled / name).rglob("*") if p.is_file())
    for name in ("argoverse1", "ethucy", "apolloscape"):
        assert detect(bundled / name) == name
    mixed = tmp_path / "mixed"
    mixed.mkdir()
    (mixed / "0_readme.md").write_text("not data\n")  # first file unrecognised: the next ones decide
    for p in sorted((bundled / "argoverse1").glob("*.csv"))[:2]:
        (mixed / p.name).write_bytes(p.read_bytes())
    assert detect(mixed) == "argoverse1"


def test_adapter_codes_equal_recomputed_codes(bundled: Path) -> None:
    adapter = Argoverse1Adapter()
    parsed = adapter.read(collect_sources([bundled / "argoverse1"], adapter), keep_going=False)
    assert parsed.codes is not None
    tracks = _canonical_order(parsed.tracks)
    fresh = TrackCodes.of(tracks)
    assert np.array_equal(parsed.codes.log_code, fresh.log_code) and parsed.codes.log_names == fresh.log_names
    ours = parsed.codes.track_names[parsed.codes.track_code]
    assert np.array_equal(ours, fresh.track_names[fresh.track_code])
    assert tracks.column("track_id").to_pylist() == ours.tolist()
