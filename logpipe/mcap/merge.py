"""Copy a recorded log into a new MCAP unchanged and append channels to it.

Sources (``Source``):

* **MCAP** (plain MCAP, ROS2 bags stored as MCAP, the MCAP ingest wrote): every schema, channel, message,
  metadata record and attachment is copied, in file order — same bytes, encodings, schemas, channel metadata,
  sequence numbers and timestamps (by chunk where the file allows, else record by record, below). Only the
  file-level framing (indexes, and the chunking and compression of what is copied record by record) is the
  writer's own.
* **ROS bags** (ROS1 ``.bag``, ROS2 ``.db3`` bags) read with ``rosbags``: converted the way the MCAP ROS
  profiles define it — a ``ros1msg``/``ros2msg`` schema per message type (the bag's own message
  definition, generated from the type store when a ROS2 bag stores none), one channel per bag connection,
  and the raw serialized message bytes (``ros1``/``cdr``) at the bag's record time.

Schema and channel ids of an MCAP source are kept when they are numbered 1, 2, ... in order of first
appearance (as writers number them); otherwise they are renumbered consistently.

Three ways to copy, the first that applies:

* **by chunk** (``logpipe.mcap.chunk_copy``): one MCAP source whose messages all sit in indexed chunks and that has
  no attachments (every MCAP ingest writes, and most recorders' files): its chunk and message-index records are
  copied byte for byte (so every original record, id, sequence number and time is the original's, nothing is
  decompressed), and the appended channels are laid out after them by ``logpipe.mcap.bulk``;
* **natively**: the Rust writer of ``foxglove-sdk`` (``logpipe.mcap.native``) whenever the output it would write
  keeps every original field — one MCAP source of at most ``NATIVE_MAX_BYTES``, no attachments, every channel with
  messages and numbered 1, 2, ... in order of its first message (schemas likewise), every message's sequence number
  its 1-based count on its channel and its publish time its log time (``native_copyable``);
* the ``mcap`` writer for every other source (ROS bags, other MCAPs), which sets each field as read.

The appended channels are numbered after the original's; their sequence numbers start at 1 with the first two
ways and 0 with the third, and an appended channel that gets no message is left out by the first two. Appended
channels come after every original one, and their messages after the original messages (in their own chunks), so
the originals keep their ids and order; readers that want time order (``iter_messages(log_time_order=True)``,
Foxglove) sort by the chunk indexes.
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any, Literal

from mcap.records import Attachment, Channel, Header, Message, Metadata, Schema
from mcap.stream_reader import CRCValidationError, StreamReader
from mcap.writer import CompressionType, Writer

from logpipe import __version__
from logpipe.errors import SourceError
from logpipe.mcap.bulk import BulkMcap
from logpipe.mcap.chunk_copy import ChunkedOriginal, read_chunked
from logpipe.mcap.native import NativeMcap
from logpipe.storage.io import atomic_path

SourceKind = Literal["mcap", "rosbag"]


@dataclass(frozen=True)
class Source:
    """One original recording.

    Attributes:
        paths: the file(s): one MCAP or ROS1 bag, or the storage files / folder of one ROS2 bag.
        kind: ``mcap`` (copied record by record) or ``rosbag`` (converted with rosbags).
        name: how errors name it (the input's relative path).
    """

    paths: tuple[Path, ...]
    kind: SourceKind
    name: str


@dataclass(frozen=True)
class NewChannel:
    """A channel to append.

    Attributes:
        topic: channel topic.
        schema_name: e.g. ``foxglove.SceneUpdate`` (``logpipe.mcap.foxglove.new_channel`` makes Foxglove channels).
        schema_encoding: e.g. ``protobuf`` (a ``FileDescriptorSet``) or ``jsonschema``.
        schema_data: the schema document (bytes).
        message_encoding: e.g. ``protobuf`` or ``json``.
        metadata: channel metadata.
    """

    topic: str
    schema_name: str
    schema_encoding: str
    schema_data: bytes
    message_encoding: str = "json"
    metadata: dict[str, str] = field(default_factory=dict)


@dataclass(frozen=True)
class NewMessage:
    """A message on an appended channel: ``channel`` indexes the ``channels`` given to ``write_merged``;
    times are ns on the log's clock."""

    channel: int
    log_time: int
    publish_time: int
    data: bytes


@dataclass
class MergeStats:
    """What ``write_merged`` wrote: original schemas, channels and messages copied, messages appended."""

    schemas: int = 0
    channels: int = 0
    messages: int = 0
    metadata: int = 0
    attachments: int = 0
    appended: int = 0


class _Copier:
    """Registers original schemas/channels in the writer once each and maps their ids."""

    def __init__(self, writer: Writer, stats: MergeStats) -> None:
        self.writer = writer
        self.stats = stats
        self.schema_ids: dict[tuple[Any, ...], int] = {}
        self.channel_ids: dict[tuple[Any, ...], int] = {}

    def schema(self, name: str, encoding: str, data: bytes) -> int:
        key = (name, encoding, bytes(data))
        if key not in self.schema_ids:
            self.schema_ids[key] = self.writer.register_schema(name=name, encoding=encoding, data=bytes(data))
            self.stats.schemas += 1
        return self.schema_ids[key]

    def channel(self, topic: str, encoding: str, schema_id: int, metadata: dict[str, str]) -> int:
        key = (topic, encoding, schema_id, tuple(sorted(metadata.items())))
        if key not in self.channel_ids:
            self.channel_ids[key] = self.writer.register_channel(
                topic=topic, message_encoding=encoding, schema_id=schema_id, metadata=dict(metadata)
            )
            self.stats.channels += 1
        return self.channel_ids[key]


def write_merged(
    target: Path,
    sources: Sequence[Source],
    channels: Sequence[NewChannel],
    messages: Iterable[NewMessage],
    *,
    metadata: dict[str, dict[str, str]] | None = None,
) -> MergeStats:
    """Write ``target`` (atomically): every record of ``sources`` copied unchanged, then ``channels`` and
    ``messages`` appended, then ``metadata`` records.

    Raises:
        SourceError: a source cannot be read.
    """
    chunked = _chunked_original(sources)
    if chunked is not None:
        return _write_chunked(target, chunked, channels, messages, metadata or {})
    records = _native_records(sources)
    if records is not None:
        return _write_native(target, records, channels, messages, metadata or {})
    stats = MergeStats()
    with atomic_path(target) as tmp, tmp.open("wb") as fh:
        writer = Writer(fh, compression=CompressionType.ZSTD)
        writer.start(profile=_profile(sources), library=f"logpipe {__version__}")
        copier = _Copier(writer, stats)
        for source in sources:
            try:
                if source.kind == "mcap":
                    for path in source.paths:
                        _copy_mcap(path, copier)
                else:
                    _copy_rosbag(source, copier)
            except SourceError:
                raise
            except Exception as exc:  # mcap/rosbags raise many types for a damaged file
                raise SourceError(source.name, f"cannot copy the original log: {exc}") from exc
        ids = [
            writer.register_channel(
                topic=c.topic,
                message_encoding=c.message_encoding,
                schema_id=writer.register_schema(name=c.schema_name, encoding=c.schema_encoding, data=c.schema_data),
                metadata=dict(c.metadata),
            )
            for c in channels
        ]
        sequence = [0] * len(ids)
        for m in messages:
            writer.add_message(ids[m.channel], log_time=m.log_time, publish_time=m.publish_time, data=m.data,
                               sequence=sequence[m.channel])
            sequence[m.channel] += 1
            stats.appended += 1
        for name, values in (metadata or {}).items():
            writer.add_metadata(name, values)
        writer.finish()  # type: ignore[no-untyped-call]
    return stats


NATIVE_COMPRESSION_THREADS = 1
"""A prediction MCAP's chunks are compressed on one SDK thread while predict builds the next messages: constant
velocity on all of ETH/UCY with MCAP ran in 11.7 and 21.8 s against 17.6 and 31.8 s compressing in the logging
call, at the same CPU (two runs of 3 interleaved rounds each, 2 cores shared with other jobs). Ingest's MCAPs are
one chunk each, written at ``close``: nothing to overlap there."""

NATIVE_MAX_BYTES = 64 << 20
"""Largest original read whole to check it for the native writer (ingest's MCAPs are a few hundred KB)."""


def _chunked_original(sources: Sequence[Source]) -> ChunkedOriginal | None:
    """The one MCAP source read for a chunk copy (``logpipe.mcap.chunk_copy``), None where that does not apply."""
    if len(sources) != 1 or sources[0].kind != "mcap" or len(sources[0].paths) != 1:
        return None
    return read_chunked(sources[0].paths[0], sources[0].name)


def _write_chunked(target: Path, original: ChunkedOriginal, channels: Sequence[NewChannel],
                   messages: Iterable[NewMessage], metadata: dict[str, dict[str, str]]) -> MergeStats:
    """``write_merged`` of an original copied by chunk, the appended messages laid out whole (``BulkMcap``)."""
    writer = BulkMcap(original.profile)
    writer.copy_chunks(original.schemas, original.channels, original.chunks)
    for record in original.metadata:
        writer.metadata(record.name, dict(record.metadata))
    times: list[list[int]] = [[] for _ in channels]
    data: list[list[bytes]] = [[] for _ in channels]
    for m in messages:
        if m.publish_time != m.log_time:
            raise ValueError("appended messages are written with publish time = log time")
        times[m.channel].append(m.log_time)
        data[m.channel].append(m.data)
    for c, channel_times, channel_data in zip(channels, times, data, strict=True):
        if channel_times:  # as the native writer did: no record for a channel without messages
            writer.log(writer.channel(c.topic, c.message_encoding, (c.schema_name, c.schema_encoding, c.schema_data),
                                      dict(c.metadata)), channel_times, channel_data)
    for name, values in metadata.items():
        writer.metadata(name, values)
    with atomic_path(target) as tmp:
        writer.write(tmp)
    return MergeStats(schemas=len(original.schemas), channels=len(original.channels), messages=original.messages,
                      metadata=len(original.metadata), appended=sum(map(len, times)))


def _native_records(sources: Sequence[Source]) -> list[Any] | None:
    """The records of the one MCAP source if the native writer can copy it unchanged (``native_copyable``)."""
    if len(sources) != 1 or sources[0].kind != "mcap" or len(sources[0].paths) != 1:
        return None
    path = sources[0].paths[0]
    try:
        if path.stat().st_size > NATIVE_MAX_BYTES:
            return None
        with path.open("rb") as fh:
            records = list(StreamReader(fh, skip_magic=False).records)
    except Exception as exc:  # mcap raises many types for a damaged file
        raise SourceError(sources[0].name, f"cannot copy the original log: {exc}") from exc
    return records if native_copyable(records) else None


def native_copyable(records: Sequence[Any]) -> bool:
    """Whether the native writer, given these records' schemas, channels, messages and metadata in file order,
    writes every one of them with the same fields and ids (see the module's docstring)."""
    schemas: dict[int, tuple[str, str, bytes]] = {}
    channels: dict[int, Channel] = {}
    counts: dict[int, int] = {}
    schema_order: list[int] = []
    for r in records:
        if isinstance(r, Attachment) or (isinstance(r, Metadata) and not r.metadata):  # neither kept as read
            return False
        if isinstance(r, Schema):
            schemas.setdefault(r.id, (r.name, r.encoding, bytes(r.data)))
        elif isinstance(r, Channel):
            channels.setdefault(r.id, r)
        elif isinstance(r, Message):
            n = counts.get(r.channel_id, 0) + 1
            if r.sequence != n or r.publish_time != r.log_time:
                return False
            if n == 1:  # the channel's first message: the writer numbers it (and its schema) now
                channel = channels.get(r.channel_id)
                if channel is None or r.channel_id != len(counts) + 1 or channel.schema_id == 0:
                    return False
                if channel.schema_id not in schema_order:
                    if channel.schema_id != len(schema_order) + 1:
                        return False
                    schema_order.append(channel.schema_id)
            counts[r.channel_id] = n
    distinct = len(set(schemas.values())) == len(schemas) and len(
        {(c.topic, c.message_encoding, c.schema_id, tuple(sorted(c.metadata.items()))) for c in channels.values()}
    ) == len(channels)
    return distinct and set(counts) == set(channels) and set(schema_order) == set(schemas)


def _write_native(target: Path, records: Sequence[Any], channels: Sequence[NewChannel],
                  messages: Iterable[NewMessage], metadata: dict[str, dict[str, str]]) -> MergeStats:
    """``write_merged`` through the native writer, for records ``native_copyable`` accepted."""
    stats = MergeStats()
    profile = next((str(r.profile) for r in records if isinstance(r, Header)), "")
    schemas: dict[int, tuple[str, str, bytes]] = {}
    with atomic_path(target) as tmp, NativeMcap(tmp, profile, NATIVE_COMPRESSION_THREADS) as writer:
        copied: dict[int, Any] = {}
        for r in records:
            if isinstance(r, Schema):
                schemas.setdefault(r.id, (r.name, r.encoding, bytes(r.data)))
            elif isinstance(r, Channel):
                if r.id not in copied:
                    copied[r.id] = writer.channel(r.topic, r.message_encoding, schemas[r.schema_id],
                                                  dict(r.metadata))
            elif isinstance(r, Message):
                copied[r.channel_id].log(r.data, r.log_time, None)
                stats.messages += 1
            elif isinstance(r, Metadata):
                writer.metadata(r.name, dict(r.metadata))
                stats.metadata += 1
        stats.schemas, stats.channels = len(schemas), len(copied)
        ids = [writer.channel(c.topic, c.message_encoding, (c.schema_name, c.schema_encoding, c.schema_data),
                              dict(c.metadata)) for c in channels]
        for m in messages:
            if m.publish_time != m.log_time:
                raise ValueError("the native MCAP writer writes publish time = log time")
            ids[m.channel].log(m.data, m.log_time, None)
            stats.appended += 1
        for name, values in metadata.items():
            writer.metadata(name, values)
    return stats


def _profile(sources: Sequence[Source]) -> str:
    """The MCAP profile of the output: the first MCAP source's own, ``ros1``/``ros2`` for bags."""
    for source in sources:
        if source.kind == "mcap":
            with source.paths[0].open("rb") as fh:
                for record in StreamReader(fh, skip_magic=False).records:
                    return str(getattr(record, "profile", ""))
        else:
            return "ros1" if source.paths[0].suffix == ".bag" else "ros2"
    return ""


def _copy_mcap(path: Path, copier: _Copier) -> None:
    """Stream every record of one MCAP file into the writer, in file order."""
    schemas: dict[int, Schema] = {}
    channel_map: dict[int, int] = {}
    writer, stats = copier.writer, copier.stats
    with path.open("rb") as fh:
        for record in _checked_records(fh, path):
            if isinstance(record, Schema):
                schemas.setdefault(record.id, record)
            elif isinstance(record, Channel):
                if record.id in channel_map:
                    continue  # repeated in the summary section
                schema_id = 0
                if record.schema_id != 0:
                    s = schemas[record.schema_id]
                    schema_id = copier.schema(s.name, s.encoding, s.data)
                channel_map[record.id] = copier.channel(record.topic, record.message_encoding, schema_id,
                                                        dict(record.metadata))
            elif isinstance(record, Message):
                writer.add_message(channel_map[record.channel_id], log_time=record.log_time,
                                   publish_time=record.publish_time, data=record.data, sequence=record.sequence)
                stats.messages += 1
            elif isinstance(record, Metadata):
                writer.add_metadata(record.name, dict(record.metadata))
                stats.metadata += 1
            elif isinstance(record, Attachment):
                writer.add_attachment(create_time=record.create_time, log_time=record.log_time, name=record.name,
                                      media_type=record.media_type, data=record.data)
                stats.attachments += 1


def _checked_records(fh: IO[bytes], path: Path) -> Iterator[Any]:
    """The records of an MCAP file with every chunk and data-section CRC checked (the reader's own option): a
    flipped bit in an original is one error naming it, not silently other bytes copied into a prediction MCAP."""
    try:
        yield from StreamReader(fh, skip_magic=False, validate_crcs=True).records
    except CRCValidationError as err:
        raise SourceError(str(path), f"damaged MCAP: {err}") from None


def ros1_schema_name(msgtype: str) -> str:
    """``geometry_msgs/msg/PoseStamped`` (rosbags' normalised name) -> ``geometry_msgs/PoseStamped`` (ROS1)."""
    pkg, _, name = msgtype.rpartition("/")
    return f"{pkg.removesuffix('/msg')}/{name}"


def _copy_rosbag(source: Source, copier: _Copier) -> None:
    """Convert one bag's connections and raw messages (MCAP ROS1/ROS2 profiles)."""
    from rosbags.highlevel import AnyReader
    from rosbags.interfaces import MessageDefinitionFormat

    import logpipe.formats.inflation  # noqa: F401  bounds rosbags' ROS 2 zstd decompression

    writer, stats = copier.writer, copier.stats
    with AnyReader(list(source.paths)) as reader:
        ros1 = reader.is2 is False
        channel_of: dict[int, int] = {}
        for conn in reader.connections:
            msgdef = conn.msgdef
            if ros1:
                schema_id = copier.schema(ros1_schema_name(conn.msgtype), "ros1msg", msgdef.data.encode())
                ext: Any = conn.ext
                meta = {"md5sum": conn.digest, "callerid": str(getattr(ext, "callerid", "") or ""),
                        "latching": str(int(getattr(ext, "latching", 0) or 0))}
                encoding = "ros1"
            else:
                schema_id = _ros2_schema(copier, reader, conn.msgtype, msgdef.format, msgdef.data,
                                         MessageDefinitionFormat)
                ext = conn.ext
                meta = {"offered_qos_profiles": _qos_text(getattr(ext, "offered_qos_profiles", ""))}
                encoding = str(getattr(ext, "serialization_format", "cdr") or "cdr")
            channel_of[conn.id] = copier.channel(conn.topic, encoding, schema_id, meta)
        for conn, timestamp, raw in reader.messages():
            writer.add_message(channel_of[conn.id], log_time=timestamp, publish_time=timestamp, data=bytes(raw),
                               sequence=0)
            stats.messages += 1


def _qos_text(value: Any) -> str:
    """rosbag2 stores QoS profiles as YAML text; newer rosbags parse them into objects."""
    if isinstance(value, str):
        return value
    if not value:
        return ""
    import yaml

    def plain(obj: Any) -> Any:
        if hasattr(obj, "__dataclass_fields__"):
            return {k: plain(getattr(obj, k)) for k in obj.__dataclass_fields__}
        if isinstance(obj, list | tuple):
            return [plain(v) for v in obj]
        return getattr(obj, "value", obj)

    return str(yaml.safe_dump(plain(value), sort_keys=False))


def _ros2_schema(copier: _Copier, reader: Any, msgtype: str, fmt: Any, data: str, formats: Any) -> int:
    """``ros2msg``/``ros2idl`` schema from the bag's definition, else generated from the type store."""
    if fmt == formats.MSG and data:
        return copier.schema(msgtype, "ros2msg", data.encode())
    if fmt == formats.IDL and data:
        return copier.schema(msgtype, "ros2idl", data.encode())
    try:
        text, _ = reader.typestore.generate_msgdef(msgtype, ros_version=2)
    except Exception:  # a type the store does not know: the channel keeps no schema
        return 0
    return copier.schema(msgtype, "ros2msg", str(text).encode())
