"""An original MCAP's chunks read to be copied byte for byte into a prediction MCAP (``bulk.BulkMcap.copy_chunks``).

A chunk is its records compressed, and its message indexes point into it by offset: both stay valid wherever the
chunk is put, so an original whose messages all sit in indexed chunks is copied without decompressing or decoding a
message (every MCAP ingest writes is such a file). Its schema, channel and message records, sequence numbers,
times and bytes are the original's because they are the original's bytes.

What is read: the file once, its summary (schemas, channels, statistics, chunk indexes, metadata indexes: the
``mcap`` reader's own parsing), and each chunk and message index record as the byte range its chunk index gives.
Anything a chunk copy would not carry as read (no summary or chunk indexes, messages outside chunks, attachments,
a chunk without message indexes) makes ``read_chunked`` answer None, and the record-by-record copy of
``logpipe.mcap.merge`` is used.

Damage: the data section's CRC (which covers the compressed chunks) and the summary's are checked; where a file
has no data-section CRC, each chunk is decompressed and checked against its own.
"""

from __future__ import annotations

import io
import struct
import zlib
from dataclasses import dataclass
from pathlib import Path

from mcap.data_stream import ReadDataStream
from mcap.reader import make_reader
from mcap.records import Channel, Chunk, Metadata, Schema
from mcap.summary import Summary

from logpipe.errors import SourceError
from logpipe.mcap.bulk import MAGIC, CopiedChunk

_FOOTER = struct.Struct("<BQQQI")  # opcode, length, summary start, summary offset start, summary CRC
_DATA_END = 1 + 8 + 4  # opcode, length, data-section CRC


@dataclass(frozen=True)
class ChunkedOriginal:
    """What a chunk copy of one MCAP carries: its profile, schemas, channels, chunks and metadata records."""

    profile: str
    schemas: list[Schema]
    channels: list[Channel]
    chunks: list[CopiedChunk]
    metadata: list[Metadata]

    @property
    def messages(self) -> int:
        return sum(sum(c.counts.values()) for c in self.chunks)


def read_chunked(path: Path, name: str) -> ChunkedOriginal | None:
    """``path``'s chunks and what goes with them, or None when it is not copyable by chunk (see the module).

    Raises:
        SourceError: (naming ``name``) the file is damaged or not an MCAP.
    """
    try:
        data = path.read_bytes()
        return _read(data, name)
    except SourceError:
        raise
    except Exception as exc:  # mcap raises many types for a damaged file
        raise SourceError(name, f"cannot copy the original log: {exc}") from exc


def _read(data: bytes, name: str) -> ChunkedOriginal | None:
    if len(data) < 2 * len(MAGIC) + _FOOTER.size or data[-len(MAGIC):] != MAGIC:
        raise SourceError(name, "damaged MCAP: it does not end with the MCAP magic")
    opcode, _, summary_start, _, summary_crc = _FOOTER.unpack_from(data, len(data) - len(MAGIC) - _FOOTER.size)
    if opcode != 0x02 or summary_start == 0:
        return None  # no summary: nothing says where the chunks are without reading every record
    if summary_crc and zlib.crc32(memoryview(data)[summary_start : len(data) - len(MAGIC) - 4]) != summary_crc:
        raise SourceError(name, "damaged MCAP: its summary section fails its CRC")
    data_end = summary_start - _DATA_END
    if data[data_end] != 0x0F:
        return None
    (data_crc,) = struct.unpack_from("<I", data, summary_start - 4)
    if data_crc and zlib.crc32(memoryview(data)[:data_end]) != data_crc:
        raise SourceError(name, "damaged MCAP: its data section fails its CRC")
    reader = make_reader(io.BytesIO(data))
    summary = reader.get_summary()
    if summary is None or summary.statistics is None or not summary.chunk_indexes:
        return None
    chunks = _chunks(data, summary, check=not data_crc, name=name)
    metadata = list(reader.iter_metadata())
    stats = summary.statistics
    if chunks is None or stats.attachment_count or stats.metadata_count != len(metadata) or \
            stats.message_count != sum(sum(c.counts.values()) for c in chunks):
        return None  # attachments, metadata without an index, or messages outside the chunks
    return ChunkedOriginal(reader.get_header().profile, sorted(summary.schemas.values(), key=lambda s: s.id),
                           sorted(summary.channels.values(), key=lambda c: c.id), chunks, metadata)


def _chunks(data: bytes, summary: Summary, check: bool, name: str) -> list[CopiedChunk] | None:
    """Each chunk's record and message indexes as the file holds them, in file order."""
    out = []
    for ci in sorted(summary.chunk_indexes, key=lambda c: c.chunk_start_offset):
        if not ci.message_index_offsets:
            return None
        indexes, counts = [], {}
        for channel, at in sorted(ci.message_index_offsets.items(), key=lambda item: item[1]):
            opcode, length, channel_id, size = struct.unpack_from("<BQHI", data, at)
            if opcode != 0x07 or channel_id != channel or channel not in summary.channels:
                return None
            indexes.append((channel, data[at : at + 9 + length]))
            if size:
                counts[channel] = size // 16
        record = data[ci.chunk_start_offset : ci.chunk_start_offset + ci.chunk_length]
        if check and not _chunk_intact(record):
            raise SourceError(name, "damaged MCAP: a chunk fails its CRC")
        out.append(CopiedChunk(record, indexes, counts, ci.message_start_time, ci.message_end_time, ci.compression,
                               ci.compressed_size, ci.uncompressed_size))
    return out


def _chunk_intact(record: bytes) -> bool:
    chunk = Chunk.read(ReadDataStream(io.BytesIO(record[9:])))
    if not chunk.uncompressed_crc:
        return True
    if chunk.compression == "zstd":
        import zstandard

        raw = zstandard.ZstdDecompressor().decompress(chunk.data, max_output_size=chunk.uncompressed_size)
    elif chunk.compression == "lz4":
        import lz4.frame

        raw = lz4.frame.decompress(chunk.data)
    else:
        raw = chunk.data
    return bool(zlib.crc32(raw) == chunk.uncompressed_crc)
