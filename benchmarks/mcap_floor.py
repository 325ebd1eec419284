"""Writing MCAP records that were already serialized, again, through the writer a stage writes them with: the floor
of a stage's MCAP output with these libraries (what the bench rows of predict and ingest compare against).

Ingest and predict lay their MCAPs out whole (``logpipe.mcap.bulk``) and predict copies an original's chunks as they
are (``logpipe.mcap.chunk_copy``), so their floors are ``rewrite_bulk`` (every message, already serialized, handed
to that writer per channel) and ``PredictionFloor`` (the original's chunks, already read, copied, plus the appended
messages, already serialized); ``rewrite_as_stage`` is the floor of the record-by-record paths (ROS bags, MCAPs that
are not copyable by chunk)."""

from __future__ import annotations

from pathlib import Path
from typing import Any


def mcap_records(path: Path) -> list[Any]:
    """An MCAP's records in file order that a writer writes again (the summary's repeated schemas and channels
    left out)."""
    from mcap.records import Attachment, Channel, Header, Message, Metadata, Schema
    from mcap.stream_reader import StreamReader

    records, seen = [], set()
    with path.open("rb") as fh:
        for r in StreamReader(fh, skip_magic=False).records:
            if isinstance(r, Schema | Channel):
                if (type(r), r.id) in seen:
                    continue
                seen.add((type(r), r.id))
            if isinstance(r, Header | Schema | Channel | Message | Metadata | Attachment):
                records.append(r)
    return records


def rewrite_mcap(writer: Any, records: list[Any]) -> None:
    """Write already-read MCAP records again (ids kept: the writer numbers schemas and channels as the file did)."""
    from mcap.records import Attachment, Channel, Header, Message, Metadata, Schema

    for r in records:
        if isinstance(r, Header):
            writer.start(profile=r.profile, library=r.library)
        elif isinstance(r, Schema):
            writer.register_schema(name=r.name, encoding=r.encoding, data=r.data)
        elif isinstance(r, Channel):
            writer.register_channel(topic=r.topic, message_encoding=r.message_encoding, schema_id=r.schema_id,
                                    metadata=dict(r.metadata))
        elif isinstance(r, Message):
            writer.add_message(r.channel_id, log_time=r.log_time, publish_time=r.publish_time, data=r.data,
                               sequence=r.sequence)
        elif isinstance(r, Metadata):
            writer.add_metadata(r.name, dict(r.metadata))
        elif isinstance(r, Attachment):
            writer.add_attachment(create_time=r.create_time, log_time=r.log_time, name=r.name,
                                  media_type=r.media_type, data=r.data)
    writer.finish()


def rewrite_native(target: Path, records: list[Any], compression_threads: int = 0) -> None:
    """Write already-read MCAP records again through the native (``foxglove-sdk``) writer the stages use, with
    their settings: ids, sequence numbers and publish times as that writer sets them (``logpipe.mcap.native``)."""
    from mcap.records import Attachment, Channel, Header, Message, Metadata, Schema

    from logpipe.mcap.native import NativeMcap

    schemas: dict[int, tuple[str, str, bytes]] = {}
    channels: dict[int, Any] = {}
    profile = next((str(r.profile) for r in records if isinstance(r, Header)), "")
    with NativeMcap(target, profile, compression_threads) as writer:
        for r in records:
            if isinstance(r, Schema):
                schemas[r.id] = (r.name, r.encoding, bytes(r.data))
            elif isinstance(r, Channel):
                channels[r.id] = writer.channel(r.topic, r.message_encoding, schemas.get(r.schema_id),
                                                dict(r.metadata))
            elif isinstance(r, Message):
                channels[r.channel_id].log(r.data, r.log_time, None)
            elif isinstance(r, Metadata):
                writer.metadata(r.name, dict(r.metadata))
            elif isinstance(r, Attachment):
                writer.attach(log_time=r.log_time, create_time=r.create_time, name=r.name,
                              media_type=r.media_type, data=r.data)


def rewrite_as_stage(target: Path, records: list[Any], compression_threads: int = 0) -> None:
    """Write the records again with the writer the stages pick for them: the native one where it keeps every
    field as read (``logpipe.mcap.merge.native_copyable``: every MCAP the stages write natively), with the
    stage's ``compression_threads`` (ingest 0, predict ``merge.NATIVE_COMPRESSION_THREADS``), else ``mcap``."""
    from mcap.writer import CompressionType, Writer

    from logpipe.mcap.merge import native_copyable

    if native_copyable(records):
        rewrite_native(target, records, compression_threads)
        return
    with target.open("wb") as fh:
        rewrite_mcap(Writer(fh, compression=CompressionType.ZSTD), records)


def rewrite_bulk(target: Path, records: list[Any], skip_channels: int = 0, level: int | None = None,
                 compression: str = "zstd") -> None:
    """Write already-read MCAP records again through ``logpipe.mcap.bulk`` as ingest does: its channels, then each
    channel's messages as one list, then its metadata (channels numbered ``skip_channels`` and below are left out)."""
    from mcap.records import Channel, Header, Message, Metadata, Schema

    from logpipe.mcap.bulk import BulkMcap

    schemas: dict[int, tuple[str, str, bytes]] = {}
    ids: dict[int, int] = {}
    times: dict[int, list[int]] = {}
    data: dict[int, list[bytes]] = {}
    metadata = []
    from logpipe.mcap.bulk import COMPRESSION_LEVEL

    writer = BulkMcap(next((str(r.profile) for r in records if isinstance(r, Header)), ""),
                      COMPRESSION_LEVEL if level is None else level, compression)
    for r in records:
        if isinstance(r, Schema):
            schemas[r.id] = (r.name, r.encoding, bytes(r.data))
        elif isinstance(r, Channel) and r.id > skip_channels and r.id not in ids:
            ids[r.id] = writer.channel(r.topic, r.message_encoding, schemas.get(r.schema_id), dict(r.metadata))
            times[r.id], data[r.id] = [], []
        elif isinstance(r, Message) and r.channel_id in ids:
            times[r.channel_id].append(r.log_time)
            data[r.channel_id].append(r.data)
        elif isinstance(r, Metadata):
            metadata.append(r)
    for channel, new_id in ids.items():
        writer.log(new_id, times[channel], data[channel])
    for r in metadata:
        writer.metadata(r.name, dict(r.metadata))
    writer.write(target)


class PredictionFloor:
    """A prediction MCAP's floor, prepared: its original's chunks (read once, here) and its appended messages
    (already serialized); ``write`` lays them out as the stage does (``merge.write_merged``'s chunk copy)."""

    def __init__(self, output: Path, original: Path) -> None:
        from mcap.records import Channel, Message, Metadata

        from logpipe.mcap.chunk_copy import read_chunked

        chunked = read_chunked(original, original.name)
        if chunked is None:
            raise ValueError(f"{original} is not copyable by chunk")
        self.original = chunked
        first_new = max((c.id for c in chunked.channels), default=0)
        records = mcap_records(output)
        self.channels = [r for r in records if isinstance(r, Channel) and r.id > first_new]
        self.schemas = {r.id: r for r in records if type(r).__name__ == "Schema"}
        self.messages: dict[int, tuple[list[int], list[bytes]]] = {c.id: ([], []) for c in self.channels}
        for r in records:
            if isinstance(r, Message) and r.channel_id in self.messages:
                self.messages[r.channel_id][0].append(r.log_time)
                self.messages[r.channel_id][1].append(r.data)
        self.metadata = [r for r in records if isinstance(r, Metadata)][len(chunked.metadata):]

    def write(self, target: Path) -> None:
        from logpipe.mcap.bulk import BulkMcap

        writer = BulkMcap(self.original.profile)
        writer.copy_chunks(self.original.schemas, self.original.channels, self.original.chunks)
        for r in self.original.metadata:
            writer.metadata(r.name, dict(r.metadata))
        for c in self.channels:
            schema = self.schemas.get(c.schema_id)
            new_id = writer.channel(c.topic, c.message_encoding, None if schema is None else (
                schema.name, schema.encoding, bytes(schema.data)), dict(c.metadata))
            writer.log(new_id, *self.messages[c.id])
        for r in self.metadata:
            writer.metadata(r.name, dict(r.metadata))
        writer.write(target)
