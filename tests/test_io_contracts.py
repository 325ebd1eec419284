"""Core IO helpers: dictionary-encoded columns written as their values, line counts of joined text files."""

from __future__ import annotations

from pathlib import Path

import pyarrow as pa
import pyarrow.parquet as pq

from logpipe.contracts import conform, tracks_schema
from logpipe.formats._text import join_bodies, relabel
from logpipe.io import write_parquet


def _tracks(encoded: bool) -> pa.Table:
    ids = pa.array(["a", "b", "a", "c"])
    role = pa.array(["ego", "other", "ego", "focal"])
    columns = {
        "log_id": pa.array(["L1"] * 4), "timestamp_ns": pa.array([1, 1, 2, 2], pa.int64()),
        "step": pa.array([0, 0, 1, 1], pa.int32()), "track_id": ids.dictionary_encode() if encoded else ids,
        "object_type": pa.array(["vehicle"] * 4), "role": role.dictionary_encode() if encoded else role,
        "x": pa.array([0.5, 1.0, 1.5, 2.0]), "y": pa.array([0.0, 0.0, 0.0, 0.25]), "source_type": pa.array(["AV"] * 4),
    }
    return conform(pa.table(columns), tracks_schema(), keep_dictionaries=encoded)


def test_dictionary_columns_read_back_as_the_schema_types(tmp_path: Path) -> None:
    encoded, plain = _tracks(True), _tracks(False)
    assert pa.types.is_dictionary(encoded.schema.field("track_id").type)
    write_parquet(encoded, tmp_path / "encoded.parquet", dictionaries_as_values=True)
    write_parquet(plain, tmp_path / "plain.parquet")
    back = pq.read_table(tmp_path / "encoded.parquet")
    assert back.schema == tracks_schema()
    assert back.schema.metadata == tracks_schema().metadata
    assert back.equals(pq.read_table(tmp_path / "plain.parquet"))


def test_dictionary_columns_stay_encoded_by_default(tmp_path: Path) -> None:
    write_parquet(_tracks(True), tmp_path / "kept.parquet")
    assert pa.types.is_dictionary(pq.read_table(tmp_path / "kept.parquet").schema.field("track_id").type)


def test_conform_decodes_dictionaries_unless_asked_to_keep_them() -> None:
    table = _tracks(True)
    assert conform(table, tracks_schema()).schema == tracks_schema()


def test_relabel_keeps_codes_and_distinct_values() -> None:
    kinds = pa.array(["AV", "AGENT", "OTHERS", "AGENT"]).dictionary_encode()
    labels = relabel(kinds, {"AV": "vehicle", "AGENT": "vehicle", "OTHERS": "unknown"})
    assert labels.to_pylist() == ["vehicle", "vehicle", "unknown", "vehicle"]
    assert sorted(labels.dictionary.to_pylist()) == ["unknown", "vehicle"]


def test_join_bodies_counts_lines_per_file() -> None:
    blobs = [b"h\na\nb", b"h\n", b"h\n\n", b"h\nc\r\n", b"", b"h\nx\ny\n\n"]
    batch = join_bodies(blobs, 1)
    assert batch.rows_per_file == [2, 0, 0, 1, 0, 2]
    assert batch.buffer == b"a\nb\nc\nx\ny\n"
