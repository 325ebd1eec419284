"""The numpy encoders of ``logpipe.mcap.protobuf_splice`` against the Protobuf classes' own serialization."""

from __future__ import annotations

import numpy as np
from foxglove_schemas_protobuf.SceneEntity_pb2 import SceneEntity
from google.protobuf.timestamp_pb2 import Timestamp

from logpipe.mcap.protobuf_splice import ByteTable, concatenated, timestamps, varint, varints


def test_varints_equal_the_scalar_encoder_at_every_width() -> None:
    rng = np.random.default_rng(7)
    edges = [0, 1, 127, 128, 2**14 - 1, 2**14, 2**21, 2**35 - 1, 2**56, 2**63 - 1]
    values = np.concatenate([edges, rng.integers(0, 2**63 - 1, 500, dtype=np.int64), rng.integers(0, 300, 500)])
    got, lengths = varints(values).objects()
    expected = [varint(int(v)) for v in values]
    assert got.tolist() == expected
    assert lengths.tolist() == [len(e) for e in expected]


def test_timestamps_equal_the_timestamp_class() -> None:
    rng = np.random.default_rng(8)
    ns = np.concatenate([[0, 1, 10**9, 10**9 + 1, 999_999_999, 1_700_000_000_000_000_000],
                         rng.integers(0, 2**62, 300), rng.integers(0, 10**6, 300) * 10**9])
    got, _ = timestamps(ns).objects()
    expected = [Timestamp(seconds=int(t) // 10**9, nanos=int(t) % 10**9).SerializeToString() for t in ns]
    assert got.tolist() == expected


def test_concatenated_length_delimited_rows_parse_as_the_messages() -> None:
    # Entities of ids of several lengths and a timestamp each: the rows fall in blocks of different widths.
    ids = ["a", "track-22", "x" * 200, ""]
    ns = np.array([5, 10**9, 3 * 10**9 + 7, 0, 42])
    id_items = ByteTable.of_items([SceneEntity(id=i).SerializeToString() for i in ids])
    stamp = concatenated([(timestamps(ns), np.arange(len(ns)))], key=b"\x0a")  # SceneEntity.timestamp = field 1
    codes = np.array([2, 0, 1, 3, 2])
    rows, lengths = concatenated([(stamp, np.arange(5)), (id_items, codes)], key=b"\x12").objects()
    for row, length, t, c in zip(rows.tolist(), lengths.tolist(), ns.tolist(), codes.tolist(), strict=True):
        assert len(row) == length and row[0] == 0x12
        entity = SceneEntity.FromString(_payload(row))
        assert entity.id == ids[c]
        assert entity.timestamp.seconds * 10**9 + entity.timestamp.nanos == t


def _payload(record: bytes) -> bytes:
    """The payload of one length-delimited field record (key byte, varint length, payload)."""
    at, length, shift = 1, 0, 0
    while True:
        byte = record[at]
        length |= (byte & 0x7F) << shift
        at += 1
        if byte < 0x80:
            break
        shift += 7
    assert len(record) == at + length
    return record[at:]
