"""``logpipe.mcap.bulk``: a file laid out whole reads back through the ``mcap`` reader exactly as given — every
CRC (chunks, data section, summary) holds, the summary and message indexes point at the right messages, chunks
split at ``CHUNK_BYTES`` — and ingest's files written this way are what the same messages through the ``mcap``
writer would be, message for message."""

from __future__ import annotations

import zlib
from pathlib import Path

import pytest
from mcap.reader import make_reader
from mcap.records import Chunk, Message, MessageIndex
from mcap.stream_reader import StreamReader

from logpipe.mcap import bulk
from logpipe.mcap.bulk import BulkMcap, Pieces

REPO = Path(__file__).resolve().parents[2]


def _build(chunk_bytes: int, monkeypatch: pytest.MonkeyPatch) -> tuple[bytes, list[tuple[str, int, int, bytes]]]:
    monkeypatch.setattr(bulk, "CHUNK_BYTES", chunk_bytes)
    w = BulkMcap("x-test")
    a = w.channel("/a", "json", ("a.A", "jsonschema", b"{}"), {"k": "v"})
    b = w.channel("/b", "protobuf", ("b.B", "protobuf", b"\x01"))
    c = w.channel("/c", "json", ("a.A", "jsonschema", b"{}"))  # the same schema: stored once
    w.log(a, [50, 10, 30], [b"a50", b"a10", b"a30" * 100])
    w.log(a, [20], [b"a20"])  # a second call: its sequence numbers go on
    w.log(b, [10, 40], Pieces.of_messages([b"b10", b""]))
    objects = Pieces.of_messages([b"c", b"1", b"2"]).objects
    w.log(c, [5, 5], Pieces(objects, Pieces.of_messages([b"c", b"1", b"2"]).lengths, bulk.np.array([0, 2, 3])))
    w.metadata("m", {"x": "1"})
    # (topic, sequence, log time, data) in log-time order, ties in channel then call order
    expected = [("/c", 1, 5, b"c1"), ("/c", 2, 5, b"2"), ("/a", 2, 10, b"a10"), ("/b", 1, 10, b"b10"),
                ("/a", 4, 20, b"a20"), ("/a", 3, 30, b"a30" * 100), ("/b", 2, 40, b""), ("/a", 1, 50, b"a50")]
    return w.to_bytes(), expected


@pytest.mark.parametrize("chunk_bytes", [8 << 20, 64])
def test_a_bulk_file_reads_back_exactly_with_every_crc_holding(chunk_bytes: int, tmp_path: Path,
                                                                monkeypatch: pytest.MonkeyPatch) -> None:
    data, expected = _build(chunk_bytes, monkeypatch)
    path = tmp_path / "x.mcap"
    path.write_bytes(data)
    with path.open("rb") as fh:  # chunk CRCs and the data section's, as the stream reader checks them
        records = list(StreamReader(fh, skip_magic=False, validate_crcs=True).records)
    messages = [r for r in records if isinstance(r, Message)]
    assert [(m.sequence, m.log_time, m.publish_time, m.data) for m in messages] == [
        (s, t, t, d) for _, s, t, d in expected]
    with path.open("rb") as fh:
        reader = make_reader(fh)
        summary = reader.get_summary()
        assert summary is not None and summary.statistics is not None
        assert reader.get_header().profile == "x-test"
        assert [s.name for s in summary.schemas.values()] == ["a.A", "b.B"]
        assert {c.topic: (c.schema_id, c.metadata) for c in summary.channels.values()} == {
            "/a": (1, {"k": "v"}), "/b": (2, {}), "/c": (1, {})}
        assert summary.statistics.message_count == 8 and summary.statistics.channel_message_counts == {1: 4, 2: 2, 3: 2}
        assert (summary.statistics.message_start_time, summary.statistics.message_end_time) == (5, 50)
        assert len(summary.chunk_indexes) == summary.statistics.chunk_count
        assert (summary.statistics.chunk_count == 1) == (chunk_bytes > len(data))
        # A chunk ends at the first message past CHUNK_BYTES (the largest message record here is 31 + 300 bytes).
        assert all(c.uncompressed_size <= chunk_bytes + 331 + 200 for c in summary.chunk_indexes)
        # The indexes (what a seeking reader and Foxglove use) find every message, in time order.
        got = [(c.topic, m.sequence, m.log_time, m.data) for _, c, m in reader.iter_messages(log_time_order=True)]
        assert got == expected
        assert [(m.name, m.metadata) for m in reader.iter_metadata()] == [("m", {"x": "1"})]
    # The summary CRC in the footer covers the summary and the footer up to the CRC.
    summary_start = int.from_bytes(data[-8 - 20 : -8 - 12], "little")
    assert zlib.crc32(data[summary_start : -8 - 4]) == int.from_bytes(data[-8 - 4 : -8], "little")


def test_message_indexes_point_at_their_messages(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    import zstandard

    data, _ = _build(64, monkeypatch)
    path = tmp_path / "x.mcap"
    path.write_bytes(data)
    with path.open("rb") as fh:
        records = list(StreamReader(fh, skip_magic=False, emit_chunks=True).records)
    chunk: Chunk | None = None
    checked = 0
    for r in records:
        if isinstance(r, Chunk):
            chunk = r
            body = zstandard.ZstdDecompressor().decompress(r.data, max_output_size=r.uncompressed_size)
        elif isinstance(r, MessageIndex):
            assert chunk is not None
            for log_time, offset in r.records:
                assert body[offset] == 0x05  # a message record's opcode
                assert int.from_bytes(body[offset + 9 : offset + 11], "little") == r.channel_id
                assert int.from_bytes(body[offset + 15 : offset + 23], "little") == log_time
                checked += 1
    assert checked == 8


def test_pieces_messages_join_each_run() -> None:
    p = Pieces(bulk.np.array([b"ab", b"c", b"", b"de"], object), bulk.np.array([2, 1, 0, 2]),
               bulk.np.array([0, 2, 2, 4]))
    assert p.messages() == [b"abc", b"", b"de"] and p.sizes().tolist() == [3, 0, 2]
    assert p.part(1, 3).messages() == [b"", b"de"]


def test_lz4_chunks_read_back_through_the_mcap_reader(tmp_path: Path) -> None:
    # The bench's lz4 candidate must be a file a reader opens: chunks record "lz4" and decompress to the messages.
    w = BulkMcap("x-test", compression_level=0, compression="lz4")
    a = w.channel("/a", "json", ("a.A", "jsonschema", b"{}"))
    w.log(a, [1, 2, 3], [b"x" * 500, b"y", b"z" * 70])
    path = tmp_path / "x.mcap"
    size, _ = w.write(path)
    assert size == path.stat().st_size
    with path.open("rb") as fh:
        records = list(StreamReader(fh, skip_magic=False, validate_crcs=True, emit_chunks=True).records)
    assert {r.compression for r in records if isinstance(r, Chunk)} == {"lz4"}
    with path.open("rb") as fh:
        got = [(m.log_time, m.data) for _, _, m in make_reader(fh).iter_messages()]
    assert got == [(1, b"x" * 500), (2, b"y"), (3, b"z" * 70)]
    with pytest.raises(ValueError, match="brotli"):
        BulkMcap(compression="brotli")


def test_background_writes_write_every_file_and_report_its_digest(tmp_path: Path) -> None:
    import hashlib

    journal: list[Path] = []
    with bulk.BackgroundWrites(journal.append, queued=2) as files:
        for i in range(5):
            w = BulkMcap()
            w.log(w.channel("/a", "json", None), [i], [str(i).encode()])
            files.submit(w.prepare(), tmp_path / f"{i}.mcap")
        written = files.finish()
    assert journal == [tmp_path / f"{i}.mcap" for i in range(5)]  # in the order given, once each
    for path, (size, digest) in written.items():
        assert (size, digest) == (path.stat().st_size, hashlib.sha256(path.read_bytes()).hexdigest())
