"""Core IO helpers: dictionary-encoded columns written as their values or kept encoded, contract types with
parameters, line counts of joined text files."""

from __future__ import annotations

from pathlib import Path

import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from logpipe.contracts import arrow_schema, conform, decode_dictionaries, encode_dictionaries, tracks_schema
from logpipe.errors import DatasetError
from logpipe.formats._text import join_bodies, relabel
from logpipe.storage.io import write_parquet


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


def test_fixed_size_lists_take_their_length_from_a_table_parameter() -> None:
    schema = arrow_schema("predictions", pred_len=12)
    assert schema.field("x").type == pa.list_(pa.float64(), 12)
    assert schema.field("timestamp_ns").type == pa.list_(pa.int64(), 12)
    assert schema.field("track_id").type == pa.string()  # ids are plain strings in every table
    with pytest.raises(DatasetError, match="needs pred_len"):
        arrow_schema("predictions")
    with pytest.raises(DatasetError, match="expected >= 1"):
        arrow_schema("predictions", pred_len=0)


def _samples(log_ids: list[str], first: int) -> pa.Table:
    n = len(log_ids)
    steps = range(first, first + n)
    return conform(pa.table({
        "sample_id": [f"{log}:{i}" for i, log in zip(steps, log_ids, strict=True)], "log_id": log_ids,
        "start_step": pa.array(steps, pa.int32()), "current_step": pa.array(steps, pa.int32()),
        "end_step": pa.array(steps, pa.int32()), "start_ns": pa.array(steps, pa.int64()),
        "current_ns": pa.array(steps, pa.int64()), "end_ns": pa.array(steps, pa.int64()),
        "focal_track_id": [None] * n, "target_track_ids": [["a"]] * n, "regular": [True] * n,
    }), arrow_schema("samples"))


def test_encoded_tables_are_written_alike_however_they_were_chunked(tmp_path: Path) -> None:
    """What ``DatasetWriter`` writes for the logs and samples tables depends on the values only: an appended
    ingest (the committed file's table + each batch's, each with its own dictionaries, or plain strings from an
    older writer) writes the bytes a whole one would."""
    whole = _samples(["L1", "L2", "L1", "L3"], 0)
    parts = pa.concat_tables([decode_dictionaries(_samples(["L1", "L2"], 0)),
                              decode_dictionaries(_samples(["L1", "L3"], 2))])
    assert parts.column("log_id").num_chunks == 2 and not pa.types.is_dictionary(parts.schema.field("log_id").type)
    write_parquet(encode_dictionaries(whole, arrow_schema("samples")), tmp_path / "whole.parquet")
    write_parquet(encode_dictionaries(parts, arrow_schema("samples")), tmp_path / "parts.parquet")
    assert (tmp_path / "whole.parquet").read_bytes() == (tmp_path / "parts.parquet").read_bytes()
    back = pq.read_table(tmp_path / "parts.parquet")
    assert back.schema.field("log_id").type == pa.string()  # ids are plain strings (Parquet encodes the pages)
    assert back.column("log_id").to_pylist() == ["L1", "L2", "L1", "L3"]
    assert back.column("sample_id").to_pylist() == ["L1:0", "L2:1", "L1:2", "L3:3"]
    assert decode_dictionaries(back).schema.field("focal_track_id").type == pa.string()


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
