"""An MCAP file laid out whole from messages built in bulk: what ingest's per-log MCAPs and predict's are written with.

Why not a record-by-record writer: a log's MCAP is a few hundred small messages whose bytes are already built
(``logpipe.mcap.protobuf_splice``, per log); writing them through a writer's ``log`` call each (the Rust writer of
``foxglove-sdk``, ``logpipe.mcap.native``) cost as much as building them. Here a channel's messages are handed over
as one list, their 31-byte record headers are one numpy array, the chunk is one ``bytes.join``, and each chunk is
compressed once (``COMPRESSION_LEVEL``). The framing records (header, schemas, channels, chunk and message indexes,
statistics, metadata, summary offsets, footer) are the ``mcap`` library's own record classes, so the layout is the
specification's as that library writes it: schemas and channels repeated in the summary, chunk and message indexes,
statistics, a metadata index, summary offsets, the chunk, data-section and summary CRCs.

What a file written here always has (as ``logpipe.mcap.native`` did, so readers see the same fields):

* schema ids 1, 2, ... (identical schemas stored once) and channel ids in the order channels are added;
* sequence numbers 1, 2, ... per channel in the order the messages were given, publish time = log time;
* messages in log-time order (stable: ties keep channel order, then the given order), in chunks of at most
  ``CHUNK_BYTES`` uncompressed (one chunk per ingest log); the first chunk carries the schema and channel records.

``add_chunks`` copies another file's chunks and message indexes byte for byte (``logpipe.mcap.chunk_copy``).

``BulkMcap.prepare`` does the part that holds the GIL (ordering, headers, joining each chunk's body);
``Prepared.write`` the rest (zstd, CRCs, framing, the write, sha256), which ``BackgroundWrites`` runs on a thread of
the same worker while the next files are built. Chunk compression is zstd level 1 (``COMPRESSION_LEVEL``; lz4 is
there to be measured against it, ``make bench``'s ``mcap_writers``).
"""

from __future__ import annotations

import hashlib
import itertools
import struct
import threading
import zlib
from collections import deque
from collections.abc import Callable, Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field
from functools import lru_cache, partial
from pathlib import Path
from typing import Any

import numpy as np
import zstandard
from mcap.data_stream import RecordBuilder
from mcap.opcode import Opcode
from mcap.records import (
    Channel,
    Chunk,
    ChunkIndex,
    DataEnd,
    Footer,
    Header,
    Metadata,
    MetadataIndex,
    Schema,
    Statistics,
    SummaryOffset,
)
from mcap.writer import LIBRARY_IDENTIFIER

from logpipe import __version__

MAGIC = b"\x89MCAP0\r\n"
LIBRARY = f"logpipe {__version__} ({LIBRARY_IDENTIFIER})"
COMPRESSION_LEVEL = 1
"""zstd level of every chunk. Measured on the 69 real Argoverse 1 logs' MCAPs (``make bench``'s ``mcap_channels``):
level 1 compresses them to 9.2% in ~0.6x the CPU of level 3 (8.9%, the writers' default); higher levels gain
under 1% of size at 2-4x the CPU, negative levels lose a quarter of the size for little CPU."""
CHUNK_BYTES = 1 << 20
"""Largest uncompressed chunk (one chunk per ingest log; a prediction MCAP of a long log is many). zstd level 1 ran
1,189 MB/s on 1 MiB chunks of prediction messages, 1,148 on 4 MiB and 667 on 8 MiB (one process; a chunk that fits
the cache compresses faster), and a viewer seeking in the file decompresses 1 MiB, not the file."""
_HEADER = np.dtype([("op", "u1"), ("length", "<u8"), ("channel", "<u2"), ("sequence", "<u4"), ("log_time", "<u8"),
                    ("publish_time", "<u8")])
_compressors = threading.local()
_INDEX_HEAD = struct.Struct("<BQHI")


def _compress(data: bytes, level: int, compression: str = "zstd") -> bytes:
    if compression == "lz4":  # the MCAP format's other chunk compression: an LZ4 frame
        import lz4.frame  # imported here: a measured candidate only (mcap itself depends on lz4)

        framed: bytes = lz4.frame.compress(data, compression_level=level)
        return framed
    # A compressor per thread: zstandard's are not safe to share between threads, and one per chunk costs ~50 us.
    compressors = _compressors.__dict__.setdefault("zstd", {})
    compressor = compressors.get(level)
    if compressor is None:
        compressor = compressors[level] = zstandard.ZstdCompressor(level=level)
    compressed: bytes = compressor.compress(data)
    return compressed


@dataclass(frozen=True)
class Pieces:
    """Messages as runs of byte strings: message i is the concatenation of ``objects[bounds[i]:bounds[i + 1]]``
    (what ``logpipe.mcap.protobuf_splice`` builds: references to shared parts, joined only into the chunk).

    Attributes:
        objects: (pieces,) numpy object array of bytes; ``lengths``: (pieces,) their lengths.
        bounds: (messages + 1,) int64, non-decreasing, from 0 to ``len(objects)``.
    """

    objects: np.ndarray
    lengths: np.ndarray
    bounds: np.ndarray

    @classmethod
    def of_messages(cls, messages: Sequence[bytes]) -> Pieces:
        """One piece per message."""
        objects = np.empty(len(messages), object)
        objects[:] = list(messages)
        return cls(objects, np.fromiter(map(len, messages), np.int64, len(messages)),
                   np.arange(len(messages) + 1, dtype=np.int64))

    def __len__(self) -> int:
        return len(self.bounds) - 1

    def part(self, first: int, stop: int) -> Pieces:
        """Messages ``first`` .. ``stop - 1``."""
        a, b = int(self.bounds[first]), int(self.bounds[stop])
        return Pieces(self.objects[a:b], self.lengths[a:b], self.bounds[first : stop + 1] - a)

    def sizes(self) -> np.ndarray:
        """(messages,) bytes of each message."""
        ends = np.concatenate([[0], np.cumsum(self.lengths)])
        return np.asarray(ends[self.bounds[1:]] - ends[self.bounds[:-1]], np.int64)

    def messages(self) -> list[bytes]:
        """Each message's bytes."""
        blob = b"".join(self.objects.tolist())
        ends = np.concatenate([[0], np.cumsum(self.lengths)])[self.bounds].tolist()
        return [blob[a:b] for a, b in itertools.pairwise(ends)]


@dataclass(frozen=True)
class CopiedChunk:
    """A chunk of another MCAP, copied unchanged: its record's bytes (opcode to end) and message index records,
    with what its chunk index says of it.

    Attributes:
        record: the Chunk record's bytes; ``indexes``: (channel id, MessageIndex record bytes) per channel in it;
        counts: messages per channel id in it.
        start, end: its messages' first and last log time; ``compression``, ``compressed_size``,
        ``uncompressed_size``: as its record has them.
    """

    record: bytes
    indexes: list[tuple[int, bytes]]
    counts: dict[int, int]
    start: int
    end: int
    compression: str
    compressed_size: int
    uncompressed_size: int


@dataclass
class _Channel:
    record: Channel
    times: list[Any] = field(default_factory=list)
    data: list[Pieces] = field(default_factory=list)


class BulkMcap:
    """One MCAP built in memory: add schemas and channels, then each channel's messages as lists, then ``write``."""

    def __init__(self, profile: str = "", compression_level: int = COMPRESSION_LEVEL,
                 compression: str = "zstd") -> None:
        if compression not in ("zstd", "lz4"):
            raise ValueError(f"chunk compression {compression!r} is not zstd or lz4")
        self.profile = profile
        self.compression_level = compression_level
        self.compression = compression
        self._schemas: dict[tuple[str, str, bytes], Schema] = {}
        self._channels: list[_Channel] = []
        self._metadata: list[Metadata] = []
        self._copied: list[CopiedChunk] = []
        self._copied_counts: dict[int, int] = {}
        self._copied_schemas: list[Schema] = []
        self._copied_channels: list[Channel] = []
        self._copied_schema_ids: dict[tuple[str, str, bytes], int] = {}
        self._first_id = 1

    def channel(self, topic: str, message_encoding: str, schema: tuple[str, str, bytes] | None,
                metadata: dict[str, str] | None = None) -> int:
        """A new channel's id; ``schema`` is (name, encoding, data), None for a schemaless channel."""
        schema_id = 0
        if schema is not None:
            key = (schema[0], schema[1], bytes(schema[2]))
            known = self._copied_schema_ids.get(key)
            if known is None and key not in self._schemas:
                self._schemas[key] = Schema(id=self._first_schema + len(self._schemas), name=key[0],
                                            encoding=key[1], data=key[2])
            schema_id = known if known is not None else self._schemas[key].id
        channel_id = self._first_id + len(self._channels)
        self._channels.append(_Channel(Channel(id=channel_id, topic=topic, message_encoding=message_encoding,
                                               metadata=dict(metadata or {}), schema_id=schema_id)))
        return channel_id

    def log(self, channel: int, log_times: Sequence[int] | np.ndarray, data: Sequence[bytes] | Pieces) -> None:
        """Messages of ``channel`` (after any given before), message ``i`` of ``data`` at ``log_times[i]`` (ns)."""
        pieces = data if isinstance(data, Pieces) else Pieces.of_messages(data)
        if len(log_times) != len(pieces):
            raise ValueError(f"{len(log_times)} times for {len(pieces)} messages")
        target = self._channels[channel - self._first_id]
        target.times.append(np.asarray(log_times, np.uint64))
        target.data.append(pieces)

    def metadata(self, name: str, values: dict[str, str]) -> None:
        """A metadata record."""
        self._metadata.append(Metadata(name=name, metadata=dict(values)))

    def copy_chunks(self, schemas: Sequence[Schema], channels: Sequence[Channel],
                    chunks: Sequence[CopiedChunk]) -> None:
        """Carry another MCAP's schemas, channels and chunks unchanged (before any ``channel`` call): its ids
        stay, and the channels added next are numbered after them."""
        if self._channels or self._schemas:
            raise RuntimeError("copy the original's chunks before adding channels")
        self._copied_schemas = list(schemas)
        self._copied_channels = list(channels)
        # An appended channel whose schema the original has uses the original's (as a writer deduplicates).
        self._copied_schema_ids = {(s.name, s.encoding, bytes(s.data)): s.id for s in reversed(schemas)}
        self._copied = list(chunks)
        for c in chunks:
            for channel_id, count in c.counts.items():
                self._copied_counts[channel_id] = self._copied_counts.get(channel_id, 0) + count
        self._first_id = max((c.id for c in channels), default=0) + 1

    @property
    def _first_schema(self) -> int:
        return max((s.id for s in self._copied_schemas), default=0) + 1

    def write(self, target: Path) -> tuple[int, str]:
        """Write the file (``target`` in a folder nobody reads yet, or a temp path); its size and sha256. A file
        written in place is the caller's to record in the write journal (``atomic_path`` records its own)."""
        return self.prepare().write(target)

    def to_bytes(self) -> bytes:
        """The whole file."""
        return self.prepare().to_bytes()

    def prepare(self) -> Prepared:
        """The messages ordered and joined into their chunks' bodies: the part of laying the file out that holds
        the GIL. What is left (``Prepared.write``: compressing, CRCs, the framing records, the write, the digest)
        is mostly native work that releases it, so it can run on a thread while the next file is built."""
        times, order, pieces, channel_of = self._ordered()
        counts = dict(self._copied_counts)
        for ch in self._channels:
            n = sum(len(t) for t in ch.times)
            if n:
                counts[ch.record.id] = n
        prefix = b"".join([*map(_record_bytes, self._schemas.values()),
                           *(_record_bytes(c.record) for c in self._channels)])
        return Prepared(partial(self._finish, _bodies(prefix, times, order, pieces, channel_of), counts))

    def _finish(self, bodies: list[_Body], counts: dict[int, int]) -> bytes:
        """The whole file, of its joined chunk bodies and its message count per channel."""
        out = RecordBuilder()
        out.write(MAGIC)
        Header(profile=self.profile, library=LIBRARY).write(out)
        chunk_indexes: list[ChunkIndex] = []
        for c in self._copied:
            chunk_indexes.append(_place(out, c.record, c.indexes, (c.start, c.end, c.compression, c.compressed_size,
                                                                  c.uncompressed_size)))
        for body in bodies:
            chunk = Chunk(compression=self.compression, data=_compress(body.data, self.compression_level,
                                                                       self.compression),
                          message_start_time=body.start, message_end_time=body.end,
                          uncompressed_crc=zlib.crc32(body.data), uncompressed_size=len(body.data))
            record = RecordBuilder()
            chunk.write(record)
            chunk_indexes.append(_place(out, _end(record), _message_indexes(body.headers, body.offsets), (
                body.start, body.end, chunk.compression, len(chunk.data), chunk.uncompressed_size)))
        metadata_indexes = []
        for metadata in self._metadata:
            start = out.count
            metadata.write(out)
            metadata_indexes.append(MetadataIndex(offset=start, length=out.count - start, name=metadata.name))
        data = _end(out)
        data_end = RecordBuilder()
        DataEnd(zlib.crc32(data)).write(data_end)
        data += _end(data_end)
        return data + self._summary(len(data), chunk_indexes, metadata_indexes, counts)

    def _ordered(self) -> tuple[np.ndarray, np.ndarray, Pieces, np.ndarray]:
        """Every added message's time, the log-time order, the messages, and (channel id, sequence) per message."""
        parts = [(ch.record.id, t, p) for ch in self._channels for t, p in zip(ch.times, ch.data, strict=True)]
        if not parts:
            empty = np.zeros(0, np.int64)
            return empty.astype(np.uint64), empty, Pieces(np.empty(0, object), empty, np.zeros(1, np.int64)), \
                np.zeros((2, 0), np.int64)
        times = np.concatenate([t for _, t, _ in parts])
        counts = [len(t) for _, t, _ in parts]
        ids = np.repeat(np.array([i for i, _, _ in parts], np.int64), counts)
        # Sequence numbers run on across a channel's calls: 1-based rank within the channel, in call order.
        first = np.flatnonzero(np.concatenate([[True], ids[1:] != ids[:-1]]))
        sequences = np.arange(len(ids)) - np.repeat(first, np.diff(np.append(first, len(ids)))) + 1
        offsets = np.cumsum([0, *(len(p.objects) for _, _, p in parts)])
        bounds = np.concatenate([p.bounds[:-1] + o for (_, _, p), o in zip(parts, offsets[:-1], strict=True)]
                                + [offsets[-1:]])
        pieces = Pieces(np.concatenate([p.objects for _, _, p in parts]),
                        np.concatenate([p.lengths for _, _, p in parts]), bounds.astype(np.int64))
        return times, np.argsort(times, kind="stable"), pieces, np.stack([ids, sequences])

    def _summary(self, start: int, chunk_indexes: list[ChunkIndex], metadata_indexes: list[MetadataIndex],
                 counts: dict[int, int]) -> bytes:
        """Summary section and footer, for a summary starting at file offset ``start``."""
        summary = RecordBuilder()
        offsets = []
        schemas = [*self._copied_schemas, *self._schemas.values()]
        channels = [*self._copied_channels, *(c.record for c in self._channels)]
        all_chunks = chunk_indexes
        times = [(c.message_start_time, c.message_end_time) for c in all_chunks]
        statistics = Statistics(
            message_count=sum(counts.values()), schema_count=len(schemas), channel_count=len(channels),
            attachment_count=0, metadata_count=len(self._metadata), chunk_count=len(all_chunks),
            message_start_time=min((t[0] for t in times), default=0),
            message_end_time=max((t[1] for t in times), default=0),
            channel_message_counts={c.id: counts[c.id] for c in channels if c.id in counts})
        groups: list[tuple[Opcode, Sequence[Any]]] = [
            (Opcode.SCHEMA, schemas), (Opcode.CHANNEL, channels), (Opcode.STATISTICS, [statistics]),
            (Opcode.CHUNK_INDEX, all_chunks), (Opcode.METADATA_INDEX, metadata_indexes)]
        for opcode, records in groups:
            if not records:
                continue
            group_start = summary.count
            for record in records:
                if isinstance(record, Schema | Channel):
                    summary.write(_record_bytes(record))
                else:
                    record.write(summary)
            offsets.append(SummaryOffset(group_opcode=opcode, group_start=start + group_start,
                                         group_length=summary.count - group_start))
        offset_start = start + summary.count
        for offset in offsets:
            offset.write(summary)
        footer = RecordBuilder()
        Footer(summary_start=start, summary_offset_start=offset_start, summary_crc=0).write(footer)
        head = _end(footer)[:-4]  # the CRC covers the summary and the footer up to the CRC itself
        body = _end(summary)
        crc = zlib.crc32(head, zlib.crc32(body))
        return body + head + crc.to_bytes(4, "little") + MAGIC


@dataclass(frozen=True)
class _Body:
    """A chunk's uncompressed bytes, its messages' headers and offsets in it, and its first and last log time."""

    data: bytes
    headers: np.ndarray
    offsets: np.ndarray
    start: int
    end: int


def _bodies(prefix: bytes, times: np.ndarray, order: np.ndarray, pieces: Pieces,
            channel_of: np.ndarray) -> list[_Body]:
    """The added messages as chunk bodies of at most ``CHUNK_BYTES`` (the first led by ``prefix``)."""
    n = len(order)
    if n == 0:
        return []
    sizes = pieces.sizes()[order]
    headers = np.empty(n, _HEADER)
    headers["op"] = int(Opcode.MESSAGE)
    headers["length"] = sizes + 22
    headers["channel"] = channel_of[0][order]
    headers["sequence"] = channel_of[1][order]
    headers["log_time"] = headers["publish_time"] = times[order]
    raw = headers.tobytes()
    heads = np.empty(n, object)
    heads[:] = [raw[i : i + 31] for i in range(0, 31 * n, 31)]
    # Each message's header, then its pieces, in log-time order: one index array, one join per chunk.
    counts = np.diff(pieces.bounds)[order]
    block = np.cumsum(counts + 1)
    objects = np.concatenate([pieces.objects, heads])
    index = np.empty(int(block[-1]), np.int64)
    index[block - counts - 1] = len(pieces.objects) + np.arange(n)
    is_piece = np.ones(len(index), bool)
    is_piece[block - counts - 1] = False
    index[is_piece] = np.arange(int(counts.sum())) + np.repeat(pieces.bounds[:-1][order] - (np.cumsum(counts)
                                                                                            - counts), counts)
    ends = np.cumsum(sizes + 31)
    cut = np.searchsorted(ends, np.arange(1, int(ends[-1]) // CHUNK_BYTES + 1) * CHUNK_BYTES, side="right")
    bounds = [0, *sorted({int(c) for c in cut if 0 < c < n}), n]
    out = []
    for lo, hi in itertools.pairwise(bounds):
        lead = prefix if lo == 0 else b""
        first_piece = int(block[lo - 1]) if lo else 0
        body = lead + b"".join(objects[index[first_piece : int(block[hi - 1])]].tolist())
        offsets = len(lead) + np.concatenate([[0], ends[lo : hi - 1] - (ends[lo - 1] if lo else 0)])
        out.append(_Body(body, headers[lo:hi], offsets, int(times[order[lo]]), int(times[order[hi - 1]])))
    return out


class Prepared:
    """A ``BulkMcap`` whose chunk bodies are joined (``BulkMcap.prepare``): ``write`` or ``to_bytes`` finish it."""

    def __init__(self, finish: Callable[[], bytes]) -> None:
        self._finish = finish

    def to_bytes(self) -> bytes:
        """The whole file."""
        return self._finish()

    def write(self, target: Path) -> tuple[int, str]:
        """``BulkMcap.write``."""
        blob = self._finish()
        target.parent.mkdir(parents=True, exist_ok=True)
        try:
            target.write_bytes(blob)
        except OSError as err:  # a failed write() names no file (a full disk): say which one
            raise OSError(err.errno, err.strerror, str(target)) from None
        return len(blob), hashlib.sha256(blob).hexdigest()


class BackgroundWrites:
    """Prepared files finished and written on one thread, in the order given, while the caller builds the next:
    zstd, the CRCs, the write and sha256 release the GIL, so on a machine with a core to spare the writing
    overlaps the building within one worker process. At most ``queued`` files wait (bounded memory); an error
    of a write is raised here, in the caller's thread, by the next ``submit`` or by ``finish``.

    ``on_written(target)`` runs in the caller's thread for each file once it is written (the write journal)."""

    def __init__(self, on_written: Callable[[Path], None] = lambda target: None, queued: int = 8) -> None:
        self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="logpipe-mcap-write")
        self._pending: deque[tuple[Path, Future[tuple[int, str]]]] = deque()
        self._on_written, self._queued = on_written, queued
        self.written: dict[Path, tuple[int, str]] = {}

    def submit(self, prepared: Prepared, target: Path) -> None:
        """Queue ``prepared`` to be written to ``target``."""
        while len(self._pending) >= self._queued:
            self._collect()
        self._pending.append((target, self._pool.submit(prepared.write, target)))

    def finish(self) -> dict[Path, tuple[int, str]]:
        """Wait for every queued file; (bytes, sha256) per file written."""
        while self._pending:
            self._collect()
        self._pool.shutdown()
        return self.written

    def _collect(self) -> None:
        target, future = self._pending.popleft()
        self.written[target] = future.result()
        self._on_written(target)

    def __enter__(self) -> BackgroundWrites:
        return self

    def __exit__(self, *exc: object) -> None:
        # On an error, the queued files are not wanted (their folder is staging): stop without writing them.
        self._pool.shutdown(wait=True, cancel_futures=True)


def _record_bytes(record: Schema | Channel) -> bytes:
    """A schema or channel record's bytes: the same few recur in every file of a run, so each is encoded once."""
    if isinstance(record, Schema):
        return _encoded(record.id, record.name, record.encoding, record.data)
    return _encoded(record.id, record.topic, record.message_encoding, record.schema_id,
                    tuple(record.metadata.items()))


@lru_cache(maxsize=256)
def _encoded(*fields: Any) -> bytes:
    if len(fields) == 4:
        record: Schema | Channel = Schema(id=fields[0], name=fields[1], encoding=fields[2], data=fields[3])
    else:
        record = Channel(id=fields[0], topic=fields[1], message_encoding=fields[2], schema_id=fields[3],
                         metadata=dict(fields[4]))
    out = RecordBuilder()
    record.write(out)
    return _end(out)


def _end(builder: RecordBuilder) -> bytes:
    """The bytes a ``RecordBuilder`` holds (the ``mcap`` package is untyped)."""
    return bytes(builder.end())  # type: ignore[no-untyped-call]


def _message_indexes(headers: np.ndarray, offsets: np.ndarray) -> list[tuple[int, bytes]]:
    """(channel id, MessageIndex record) per channel of a chunk's messages (``headers``) at ``offsets``."""
    channels = headers["channel"]
    order = np.argsort(channels, kind="stable")
    pairs = np.empty((len(order), 2), "<u8")
    pairs[:, 0], pairs[:, 1] = headers["log_time"][order], offsets[order]
    blob = pairs.tobytes()
    ids, first, counts = np.unique(channels[order], return_index=True, return_counts=True)
    out = []
    for channel, at, count in zip(ids.tolist(), first.tolist(), counts.tolist(), strict=True):
        body = blob[16 * at : 16 * (at + count)]
        out.append((channel, _INDEX_HEAD.pack(int(Opcode.MESSAGE_INDEX), 6 + len(body), channel, len(body)) + body))
    return out


def _place(out: RecordBuilder, record: bytes, indexes: list[tuple[int, bytes]],
           chunk: tuple[int, int, str, int, int]) -> ChunkIndex:
    """Write a chunk's record and message indexes to ``out``; its chunk index (``chunk``: its first and last log
    time, compression, compressed and uncompressed size)."""
    start = out.count
    out.write(record)
    index_start = out.count
    offsets = {}
    for channel, index in indexes:
        offsets[channel] = out.count
        out.write(index)
    return ChunkIndex(message_start_time=chunk[0], message_end_time=chunk[1], chunk_start_offset=start,
                      chunk_length=len(record), message_index_offsets=offsets,
                      message_index_length=out.count - index_start, compression=chunk[2], compressed_size=chunk[3],
                      uncompressed_size=chunk[4])
