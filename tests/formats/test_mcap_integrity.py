"""Issue 56, items 5 and 8 for MCAP inputs: chunk CRCs are checked on read (the mcap reader's own option), and an
lz4 chunk that inflates past the size it declares is refused before the reader decompresses it unbounded."""

from __future__ import annotations

import io
import json
import struct
from pathlib import Path

import pytest
from mcap.stream_reader import CRCValidationError
from mcap.writer import CompressionType, Writer

from logpipe.formats.mcapfile import LengthError, McapFile


def _mcap(path: Path, compression: CompressionType, payload: bytes = b"") -> bytes:
    buf = io.BytesIO()
    writer = Writer(buf, compression=compression)
    writer.start(profile="", library="test")
    schema = writer.register_schema("Point", "jsonschema", b"{}")
    channel = writer.register_channel("/points", "json", schema)
    for i in range(50):
        writer.add_message(channel, log_time=i * 1000, publish_time=i * 1000,
                           data=json.dumps({"x": i, "pad": payload.decode() or "p" * 40}).encode())
    writer.finish()
    path.write_bytes(buf.getvalue())
    return buf.getvalue()


def test_a_flipped_byte_in_an_uncompressed_chunk_fails_its_crc(tmp_path: Path) -> None:
    data = bytearray(_mcap(tmp_path / "a.mcap", CompressionType.NONE))
    at = data.index(b'"x": 7')  # inside a chunk's message: only the chunk CRC can tell
    data[at + 5] = ord("8")
    (tmp_path / "a.mcap").write_bytes(bytes(data))
    mcap = McapFile.open(tmp_path / "a.mcap")
    try:
        with pytest.raises(CRCValidationError):
            list(mcap.raw_messages(None))
    finally:
        mcap.close()


def test_an_intact_file_reads_every_message(tmp_path: Path) -> None:
    _mcap(tmp_path / "a.mcap", CompressionType.LZ4)
    mcap = McapFile.open(tmp_path / "a.mcap")
    try:
        assert len(list(mcap.raw_messages(None))) == 50
    finally:
        mcap.close()


def test_an_lz4_chunk_inflating_past_its_declared_size_is_refused(tmp_path: Path) -> None:
    """The red-team report: an lz4 chunk declaring 1 KiB reached 1.2 GB and a MemoryError. Here one declaring
    its real size minus one byte (~1 MB real): refused after decompressing at most the declared size + 1."""
    data = bytearray(_mcap(tmp_path / "a.mcap", CompressionType.LZ4, payload=b"z" * 160_000))
    # The chunk record: opcode 0x06, length, start, end, uncompressed_size (u64), crc, compression...
    at = data.index(b"\x06")
    while data[at + 9 + 16 + 8 + 4: at + 9 + 16 + 8 + 4 + 4] != struct.pack("<I", 3) or \
            data[at + 9 + 16 + 8 + 8: at + 9 + 16 + 8 + 11] != b"lz4":
        at = data.index(b"\x06", at + 1)
    size_at = at + 9 + 16
    declared = struct.unpack_from("<Q", data, size_at)[0]
    assert declared > 1_000_000
    struct.pack_into("<Q", data, size_at, declared - 1)
    (tmp_path / "a.mcap").write_bytes(bytes(data))
    with pytest.raises(LengthError, match="inflates past"):
        McapFile.open(tmp_path / "a.mcap").close()
