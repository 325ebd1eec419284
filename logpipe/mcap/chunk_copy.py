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
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

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


def _read(records: Iterable[Any]) -> ChunkedOriginal | None:
    found = _Found()
    for r in records:
        if not found.add(r):
            return None
    copied = []
    for chunk, indexes in found.chunks:
        if not indexes or any(i.channel_id not in found.channels for i in indexes):
            return None
        if found.crc == 0 and chunk.uncompressed_crc and not _chunk_intact(chunk):
            raise CRCValidationError(chunk.uncompressed_crc, 0, chunk)
        copied.append(CopiedChunk(chunk, _record(chunk), [(i.channel_id, _record(i)) for i in indexes],
                                  {i.channel_id: len(i.records) for i in indexes if i.records}))
    if any(c.schema_id and c.schema_id not in found.schemas for c in found.channels.values()):
        return None
    return ChunkedOriginal(found.profile, sorted(found.schemas.values(), key=lambda s: s.id),
                           sorted(found.channels.values(), key=lambda c: c.id), copied, found.metadata)


@dataclass
class _Found:
    """The records of a file as a chunk copy needs them, gathered in file order."""

    profile: str = ""
    crc: int = 0
    in_data: bool = True
    schemas: dict[int, Schema] = field(default_factory=dict)
    channels: dict[int, Channel] = field(default_factory=dict)
    chunks: list[tuple[Chunk, list[MessageIndex]]] = field(default_factory=list)
    metadata: list[Metadata] = field(default_factory=list)

    def add(self, r: Any) -> bool:
        """Take one record; False when the file holds what a chunk copy would not carry as read."""
        if isinstance(r, Message | Attachment) or (isinstance(r, MessageIndex) and self.in_data and not self.chunks):
            return False
        if isinstance(r, Header):
            self.profile = r.profile
        elif isinstance(r, Schema):
            self.schemas.setdefault(r.id, r)
        elif isinstance(r, Channel):
            self.channels.setdefault(r.id, r)
        elif self.in_data and isinstance(r, Chunk):
            self.chunks.append((r, []))
        elif self.in_data and isinstance(r, MessageIndex):
            self.chunks[-1][1].append(r)
        elif self.in_data and isinstance(r, Metadata):
            self.metadata.append(r)
        elif isinstance(r, DataEnd):
            self.in_data, self.crc = False, r.data_section_crc
        return True


def _record(record: Chunk | MessageIndex) -> bytes:
    """A record's bytes as the file holds them (the ``mcap`` classes write the fields back unchanged)."""
    out = RecordBuilder()
    record.write(out)
    return bytes(out.end())  # type: ignore[no-untyped-call]


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
