"""Writing MCAP records that were already serialized, again, through the ``mcap`` writer: the floor of a stage's
MCAP output with this library (what the bench rows of predict and ingest compare against)."""

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
