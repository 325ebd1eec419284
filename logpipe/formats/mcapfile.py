"""Plain MCAP files through the ``mcap`` package, decoded per channel from the schema stored in the file:
``ros1msg`` (mcap-ros1-support), ``ros2msg``/CDR (mcap-ros2-support), JSON, and protobuf
(mcap-protobuf-support, when installed).

One file = one log (``log_id`` = file stem). Channels whose schema cannot be decoded (e.g. rosbag2 service
events with ``.srv`` schemas) only fail when a mapping needs them; a file that is damaged or cut short is read
as a stream up to the damage and reported.
"""

from __future__ import annotations

import contextlib
import io
import json
import os
from collections.abc import Callable, Collection, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from types import SimpleNamespace
from typing import IO, Any, ClassVar

import pyarrow as pa
from mcap.decoder import DecoderFactory
from mcap.exceptions import McapError
from mcap.reader import NonSeekingReader, SeekingReader
from mcap.records import Channel, Chunk, Schema
from mcap.stream_reader import StreamReader
from mcap_ros1.decoder import DecoderFactory as Ros1DecoderFactory
from mcap_ros2.decoder import DecoderFactory as Ros2DecoderFactory

from logpipe.errors import SourceError
from logpipe.formats.base import ParsedLogs, empty_tracks, read_each, read_head
from logpipe.formats.ros.extract import ROSBAG_PROTOCOL, ExtractOptions, extract_log
from logpipe.formats.ros.mapping import Mapping, TopicSummary
from logpipe.formats.ros.message_types import normalize_type
from logpipe.types import LogMeta, SampleProtocol, SourceFile

MCAP_MAGIC = b"\x89MCAP0\r\n"
MAX_CHUNK_BYTES = 1 << 30
"""Largest decompressed chunk accepted (1 GiB): a damaged length field must not make the reader allocate it."""


class LengthError(ValueError):
    """A record or chunk claims a length no sane file of this size has (damage, not data)."""


def _limits(size: int) -> tuple[int, int]:
    """(record length limit, decompressed chunk limit) for a file of ``size`` bytes: a record cannot be longer
    than the file; a chunk cannot inflate past MAX_CHUNK_BYTES or 1000x the file (zstd/lz4 rarely pass 100x)."""
    return max(size, 64), min(MAX_CHUNK_BYTES, max(1000 * size, 1 << 20))


def _check_chunk_sizes(stream: IO[bytes], size: int) -> None:
    """Walk the records (chunks not opened) and refuse a chunk whose decompressed size is absurd; the rest of
    the damage (a cut-short file...) is left to the reader, which reads up to it."""
    record_limit, chunk_limit = _limits(size)
    stream.seek(0)
    try:
        for record in StreamReader(stream, emit_chunks=True, record_size_limit=record_limit).records:
            if isinstance(record, Chunk) and record.uncompressed_size > chunk_limit:
                raise LengthError(f"a chunk claims {record.uncompressed_size} bytes decompressed "
                                  f"(at most {chunk_limit} for a {size}-byte file)")
            if isinstance(record, Chunk) and record.compression == "lz4":
                _check_lz4_inflation(record)
    except LengthError:
        raise
    except Exception:  # other damage: reported by the reader that reads up to it
        pass


def _check_lz4_inflation(chunk: Chunk) -> None:
    """Refuse an lz4 chunk that inflates past its declared size, decompressing at most one byte more than
    declared: the mcap reader decompresses lz4 without a bound (a chunk declaring 1 KiB reached 1.2 GB and a
    MemoryError), zstd it bounds by the declared size itself."""
    import lz4.frame

    decompressor = lz4.frame.LZ4FrameDecompressor()
    try:
        out = decompressor.decompress(chunk.data, max_length=chunk.uncompressed_size + 1)
    except RuntimeError:  # damaged lz4: the reader reports it where it reads the chunk
        return
    if len(out) > chunk.uncompressed_size:
        raise LengthError(f"an lz4 chunk inflates past the {chunk.uncompressed_size} bytes it declares")


def _factories() -> list[DecoderFactory]:
    out: list[DecoderFactory] = [Ros2DecoderFactory(), Ros1DecoderFactory()]
    try:  # optional: protobuf channels are reported as undecodable without it
        from mcap_protobuf.decoder import DecoderFactory as ProtobufDecoderFactory

        out.append(ProtobufDecoderFactory())
    except ImportError:  # pragma: no cover - depends on the environment
        pass
    return out


def _namespace(value: Any) -> Any:
    """JSON values with objects as attribute namespaces, so ROS-shaped JSON reads like a decoded message."""
    if isinstance(value, dict):
        return SimpleNamespace(**{k: _namespace(v) for k, v in value.items()})
    if isinstance(value, list):
        return [_namespace(v) for v in value]
    return value


def _decode_json(data: bytes) -> Any:
    return _namespace(json.loads(data))



_CHUNK_CRC_AT = 1 + 8 + 8 + 8 + 8
"""Offset of a chunk record's ``uncompressed_crc`` (after opcode, record length, start, end, uncompressed size)."""


def _chunks_without_crc(stream: Any, indexes: Any) -> int:
    """How many of the indexed chunks carry CRC 0 (none computed): 4 bytes read per chunk."""
    missing = 0
    for index in indexes:
        data = os.pread(stream.fileno(), 4, index.chunk_start_offset + _CHUNK_CRC_AT)
        missing += len(data) == 4 and data == b"\0\0\0\0"
    return missing

@dataclass
class ChannelInfo:
    """One MCAP channel as the summary (or a streaming pass) describes it.

    Attributes:
        topic, message_encoding: as stored; schema_name / schema_encoding: the schema record's ('' if none).
        count: messages (None when the file has no statistics); first_ns/last_ns: log-time span when known.
    """

    id: int
    schema_id: int
    topic: str
    message_encoding: str
    schema_name: str
    schema_encoding: str
    count: int | None = None
    first_ns: int | None = None
    last_ns: int | None = None


@dataclass
class McapFile:
    """An open MCAP file: its channels, and decoded messages by topic.

    Attributes:
        path: the file. profile/library: header fields. indexed: summary + chunk indexes readable (else the
        file is read as a stream). damage: why the file could not be read to its end, when it could not.
    """

    path: Path
    stream: IO[bytes]
    profile: str = ""
    library: str = ""
    indexed: bool = True
    chunks_without_crc: int = 0
    """Chunks whose CRC field is 0 (the writer computed none): a flipped bit inside them cannot be found."""
    channels: dict[int, ChannelInfo] = field(default_factory=dict)
    schemas: dict[int, Schema] = field(default_factory=dict)
    damage: str | None = None
    start_ns: int | None = None
    end_ns: int | None = None
    _decoders: dict[int, Callable[[bytes], Any] | BaseException] = field(default_factory=dict)
    _factories: list[DecoderFactory] = field(default_factory=_factories)

    @classmethod
    def open(cls, path: Path) -> McapFile:
        """Open and index ``path``.

        Raises:
            McapError, OSError, ValueError: not an MCAP file at all (bad magic, unreadable header).
        """
        stream = path.open("rb")
        try:
            size = os.fstat(stream.fileno()).st_size
            record_limit, chunk_limit = _limits(size)
            reader = SeekingReader(stream, validate_crcs=True, record_size_limit=record_limit)
            header = reader.get_header()
            out = cls(path=path, stream=stream, profile=header.profile, library=header.library)
            try:
                summary = reader.get_summary()
            except Exception as err:  # a damaged tail: fall back to reading the file as a stream
                summary = None
                out.damage = f"summary/footer unreadable ({type(err).__name__}: {err})"
            if summary is not None:
                for index in summary.chunk_indexes:
                    if index.uncompressed_size > chunk_limit or index.compressed_size > size:
                        raise LengthError(f"a chunk index claims {index.uncompressed_size} bytes decompressed, "
                                          f"{index.compressed_size} compressed (file: {size} bytes)")
            if summary is not None:
                out.chunks_without_crc = _chunks_without_crc(stream, summary.chunk_indexes)
            if summary is not None and any(i.compression == "lz4" for i in summary.chunk_indexes):
                _check_chunk_sizes(stream, size)  # the indexes' sizes are declared, lz4's inflation is not
            if summary is None or not summary.chunk_indexes:
                _check_chunk_sizes(stream, size)
                out.indexed = False
                out._scan()
            else:
                out.schemas = dict(summary.schemas)
                counts = summary.statistics.channel_message_counts if summary.statistics else {}
                for cid, ch in summary.channels.items():
                    out.channels[cid] = out._info(ch, counts.get(cid))
                if summary.statistics:
                    out.start_ns = summary.statistics.message_start_time
                    out.end_ns = summary.statistics.message_end_time
            return out
        except BaseException:
            stream.close()
            raise

    def _size(self) -> int:
        return os.fstat(self.stream.fileno()).st_size

    def close(self) -> None:
        """Close the file."""
        self.stream.close()

    def _info(self, ch: Channel, count: int | None) -> ChannelInfo:
        schema = self.schemas.get(ch.schema_id)
        return ChannelInfo(
            ch.id,
            ch.schema_id,
            ch.topic,
            ch.message_encoding,
            schema.name if schema else "",
            schema.encoding if schema else "",
            count,
        )

    def _stream_records(self, topics: Collection[str] | None) -> Iterator[tuple[Channel, Any]]:
        """Messages in file order, read as a stream; stops at damage (recorded in ``self.damage``)."""
        self.stream.seek(0)
        reader = NonSeekingReader(self.stream, validate_crcs=True,
                                  record_size_limit=min(256 * 2**20, _limits(self._size())[0]))
        try:
            for schema, channel, message in reader.iter_messages(topics, log_time_order=False):
                if schema is not None:
                    self.schemas.setdefault(schema.id, schema)
                yield channel, message
        except Exception as err:  # truncated or damaged data ends the readable part
            self.damage = f"the file is damaged or cut short: {type(err).__name__}: {err}"

    def _scan(self) -> None:
        for channel, message in self._stream_records(None):
            info = self.channels.get(channel.id)
            if info is None:
                info = self.channels[channel.id] = self._info(channel, 0)
            info.count = (info.count or 0) + 1
            t = message.log_time
            info.first_ns = t if info.first_ns is None else min(info.first_ns, t)
            info.last_ns = t if info.last_ns is None else max(info.last_ns, t)
        starts = [c.first_ns for c in self.channels.values() if c.first_ns is not None]
        ends = [c.last_ns for c in self.channels.values() if c.last_ns is not None]
        self.start_ns = min(starts) if starts else None
        self.end_ns = max(ends) if ends else None

    def raw_messages(self, topics: Collection[str] | None) -> Iterator[tuple[Channel, int, bytes]]:
        """(channel, log_time, data) in log-time order."""
        if self.indexed:
            self.stream.seek(0)  # the reader checks the magic where the stream stands
            reader = SeekingReader(self.stream, validate_crcs=True, record_size_limit=_limits(self._size())[0])
            for _schema, channel, message in reader.iter_messages(topics, log_time_order=True):
                yield channel, message.log_time, message.data
            return
        rows = [(m.log_time, i, ch, m.data) for i, (ch, m) in enumerate(self._stream_records(topics))]
        rows.sort(key=lambda r: (r[0], r[1]))
        for t, _i, ch, data in rows:
            yield ch, t, data

    def decoder(self, channel_id: int) -> Callable[[bytes], Any]:
        """The decoder of a channel.

        Raises:
            ValueError: no decoder for its encoding, or its schema cannot be parsed.
        """
        dec = self._decoders.get(channel_id)
        if dec is None:
            dec = self._make_decoder(self.channels[channel_id])
            self._decoders[channel_id] = dec
        if isinstance(dec, BaseException):
            raise ValueError(str(dec))
        return dec

    def _make_decoder(self, info: ChannelInfo) -> Callable[[bytes], Any] | BaseException:
        if info.message_encoding == "json":
            return _decode_json
        ch_schema = self.schemas.get(info.schema_id)
        for factory in self._factories:
            try:
                # mcap-ros2-support prints parse errors itself; they are reported through the exception instead
                with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
                    dec = factory.decoder_for(info.message_encoding, ch_schema)
            except Exception as err:  # an unparsable schema makes the channel undecodable, not the file
                first = str(err).strip().splitlines()[0] if str(err).strip() else ""
                hint = " (a .srv service schema: request/response separated by '---')" if "---" in str(err) else ""
                return ValueError(f"schema {info.schema_name!r} cannot be parsed{hint}: {type(err).__name__}: {first}")
            if dec is not None:
                return dec
        return ValueError(
            f"no decoder for message encoding {info.message_encoding!r} with schema encoding "
            f"{info.schema_encoding!r}"
            + (" (install mcap-protobuf-support)" if info.message_encoding == "protobuf" else "")
        )

    def decoded(self, topics: Collection[str]) -> Iterator[tuple[str, int, Any]]:
        """(topic, log_time, decoded message or the exception) for ``topics``, in log-time order."""
        for channel, t, data in self.raw_messages(topics):
            try:
                msg = self.decoder(channel.id)(data)
            except Exception as err:  # reported per topic by extract_log
                yield channel.topic, t, err
                continue
            yield channel.topic, t, msg

    def topic_summaries(self) -> list[TopicSummary]:
        """One summary per topic (channels of the same topic merged), with ROS type names normalised."""
        out: dict[str, TopicSummary] = {}
        for info in self.channels.values():
            name = normalize_type(info.schema_name) if info.schema_encoding == "ros1msg" else info.schema_name
            prev = out.get(info.topic)
            count = info.count if prev is None else (None if prev.count is None or info.count is None
                                                     else prev.count + info.count)  # fmt: skip
            out[info.topic] = TopicSummary(info.topic, name or "?", count)
        return list(out.values())


class McapAdapter:
    """Standalone MCAP files → tracks (see the module docstring). Same options as ``RosbagAdapter``.

    Args:
        mapping: ego/agent topics (a ``Mapping`` or a TOML/YAML path); None = detect from the schema names.
        hz: output rate (Hz); 0/None keeps the source timestamps.
        allow_empty: a file that yields no track rows is returned empty instead of an error.
        gap_periods: source gaps longer than this many output periods are not interpolated across.
        mapping_overrides: CLI ``key=value`` overrides merged over the mapping file.
    """

    name: ClassVar[str] = "mcap"
    default_protocol: ClassVar[SampleProtocol] = ROSBAG_PROTOCOL
    batch_files: ClassVar[int] = 1
    hashes_while_reading: ClassVar[bool] = False

    def __init__(
        self,
        mapping: Mapping | str | Path | None = None,
        hz: float | None = 10.0,
        allow_empty: bool = False,
        gap_periods: float = 2.0,
        mapping_overrides: Sequence[str] = (),
    ) -> None:
        self.options = ExtractOptions.from_settings(mapping, mapping_overrides, hz, gap_periods, allow_empty)

    def sniff(self, path: Path) -> bool:
        """A file that starts with the MCAP magic (or an ``.mcap`` name), unless it is the storage of a rosbag2
        folder (``metadata.yaml`` beside it: the rosbag adapter reads the folder)."""
        if not path.is_file() or (path.parent / "metadata.yaml").exists():
            return False
        head = read_head(path, len(MCAP_MAGIC))
        return head is not None and (head == MCAP_MAGIC or path.suffix == ".mcap")

    def discover(self, root: Path) -> list[Path]:
        """``.mcap`` files under ``root``, except the storage files of rosbag2 folders (metadata.yaml beside)."""
        if root.is_file():
            return [root] if self.sniff(root) else []
        # Anything named .mcap but a folder: a FIFO, device or dangling link is quarantined saying what it is.
        return sorted(p for p in root.rglob("*.mcap") if not p.is_dir() and not (p.parent / "metadata.yaml").exists())

    def read(self, sources: Sequence[SourceFile], *, keep_going: bool) -> ParsedLogs:
        """Parse MCAP files into track rows (see ``FormatAdapter.read``)."""
        return read_each(sources, lambda src: self.read_one(src, keep_going=keep_going), keep_going=keep_going,
                         empty=empty_tracks())

    def read_one(
        self, src: SourceFile, *, keep_going: bool, log_id: str | None = None
    ) -> tuple[pa.Table, LogMeta, list[SourceError]]:
        """One MCAP file → (rows, LogMeta, problems kept when ``keep_going``); ``log_id`` defaults to the stem."""
        path = Path(src.path)
        log_id = log_id or path.stem
        rel = src.relpath
        try:
            f = McapFile.open(path)
        except (McapError, OSError, ValueError, EOFError) as err:
            raise SourceError(rel, f"not a readable MCAP file: {type(err).__name__}: {err}") from None
        try:
            problems: list[SourceError] = []
            if f.damage and not f.channels:
                raise SourceError(rel, f"no message could be read: {f.damage}")
            if f.damage:
                damaged = SourceError(rel, f"{f.damage}; only the messages before the damage are used")
                if not keep_going:
                    raise damaged
                problems.append(damaged)
            topics = f.topic_summaries()
            if not any(t.count for t in topics) and not self.options.allow_empty:
                raise SourceError(
                    rel,
                    f"the file holds no messages (channels: {', '.join(sorted(t.topic for t in topics)) or 'none'})",
                )
            result = extract_log(rel, topics, f.decoded, self.options, log_id, keep_going=keep_going)
            attributes = {
                **({"unchecked": f"{f.chunks_without_crc} chunks carry no CRC: corruption inside them cannot be "
                    "detected"} if f.chunks_without_crc else {}),
                "storage": "mcap",
                "profile": f.profile,
                "library": f.library,
                "indexed": f.indexed,
                "start_ns": f.start_ns,
                "end_ns": f.end_ns,
                **result.attributes,
                "message_types": {t.topic: t.msgtype for t in topics},
            }
            meta = LogMeta(
                log_id=log_id,
                source_format=self.name,
                source_file=rel,
                source_sha256=src.sha256,
                map_id=result.map_id,
                frame_rate_hz=float(self.options.hz or 0.0),
                memberships=src.memberships,
                attributes=attributes,
            )
            return result.tracks, meta, problems + result.failures
        finally:
            f.close()
