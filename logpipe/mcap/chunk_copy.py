"""An original MCAP's chunks read to be copied byte for byte into a prediction MCAP (``bulk.BulkMcap.copy_chunks``).

A chunk is its records compressed, and its message indexes point into it by offset: both stay valid wherever the
chunk is put, so an original whose messages all sit in indexed chunks is copied without decompressing or decoding a
message (every MCAP ingest writes is such a file). Its schema, channel and message records, sequence numbers,
times and bytes are the original's because they are the original's bytes. Anything a chunk copy would not carry as
read (messages outside chunks, attachments, a chunk without message indexes, channels or schemas the summary does
not list) makes ``read_chunked`` answer None, and the record-by-record copy of ``logpipe.mcap.merge`` is used.

Damage: the stream reader checks the data section's CRC, which covers the compressed chunks; where a file has
none, each chunk is decompressed and checked against its own CRC.
"""

from __future__ import annotations

import zlib
from dataclasses import dataclass
from pathlib import Path

from mcap.data_stream import RecordBuilder
from mcap.records import (
    Attachment,
    Channel,
    Chunk,
    DataEnd,
    Header,
    Message,
    MessageIndex,
    Metadata,
    Schema,
)
from mcap.stream_reader import CRCValidationError, StreamReader

from logpipe.errors import SourceError
from logpipe.mcap.bulk import CopiedChunk


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
        with path.open("rb") as fh:
            return _read(StreamReader(fh, skip_magic=False, emit_chunks=True, validate_crcs=True).records)
    except CRCValidationError as err:
        raise SourceError(name, f"damaged MCAP: {err}") from None
    except SourceError:
        raise
    except Exception as exc:  # mcap raises many types for a damaged file
        raise SourceError(name, f"cannot copy the original log: {exc}") from exc


def _read(records: object) -> ChunkedOriginal | None:
    profile, crc = "", 0
    schemas: dict[int, Schema] = {}
    channels: dict[int, Channel] = {}
    chunks: list[tuple[Chunk, list[MessageIndex]]] = []
    metadata: list[Metadata] = []
    in_data = True
    for r in records:  # type: ignore[attr-defined]
        if isinstance(r, Header):
            profile = r.profile
        elif isinstance(r, Schema):
            schemas.setdefault(r.id, r)
        elif isinstance(r, Channel):
            channels.setdefault(r.id, r)
        elif isinstance(r, Message | Attachment):
            return None
        elif isinstance(r, Chunk) and in_data:
            chunks.append((r, []))
        elif isinstance(r, MessageIndex) and in_data:
            if not chunks:
                return None
            chunks[-1][1].append(r)
        elif isinstance(r, Metadata) and in_data:
            metadata.append(r)
        elif isinstance(r, DataEnd):
            in_data, crc = False, r.data_section_crc
    copied = []
    for chunk, indexes in chunks:
        if not indexes or any(i.channel_id not in channels for i in indexes):
            return None
        if crc == 0 and chunk.uncompressed_crc and not _chunk_intact(chunk):
            raise CRCValidationError(chunk.uncompressed_crc, 0, chunk)
        copied.append(CopiedChunk(chunk, _record(chunk), [(i.channel_id, _record(i)) for i in indexes],
                                  {i.channel_id: len(i.records) for i in indexes if i.records}))
    if any(c.schema_id and c.schema_id not in schemas for c in channels.values()):
        return None
    return ChunkedOriginal(profile, sorted(schemas.values(), key=lambda s: s.id),
                           sorted(channels.values(), key=lambda c: c.id), copied, metadata)


def _record(record: Chunk | MessageIndex) -> bytes:
    """A record's bytes as the file holds them (the ``mcap`` classes write the fields back unchanged)."""
    out = RecordBuilder()
    record.write(out)
    return bytes(out.end())


def _chunk_intact(chunk: Chunk) -> bool:
    if chunk.compression == "zstd":
        import zstandard

        data = zstandard.ZstdDecompressor().decompress(chunk.data, max_output_size=chunk.uncompressed_size)
    elif chunk.compression == "lz4":
        import lz4.frame

        data = lz4.frame.decompress(chunk.data)
    else:
        data = chunk.data
    return zlib.crc32(data) == chunk.uncompressed_crc
