"""The native (foxglove-sdk) MCAP writer: what it decides itself, and that ``write_merged`` copies an original
chunk by chunk where it can (``logpipe.mcap.chunk_copy``), through the native writer only when every original field
survives (ids, sequence numbers, times, bytes, metadata), and record by record otherwise."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest
from mcap.reader import make_reader
from mcap.records import Chunk, Message
from mcap.stream_reader import StreamReader
from mcap.writer import Writer

from logpipe.errors import SourceError
from logpipe.mcap.merge import NewChannel, NewMessage, Source, native_copyable, write_merged
from logpipe.mcap.native import NativeMcap


def _read(path: Path) -> tuple[str, dict[int, Any], dict[int, Any], list[tuple[int, int, int, int, bytes]]]:
    with path.open("rb") as fh:
        reader = make_reader(fh)
        summary = reader.get_summary()
        assert summary is not None and summary.chunk_indexes and summary.statistics is not None
        messages = [(m.channel_id, m.sequence, m.log_time, m.publish_time, m.data)
                    for _, _, m in reader.iter_messages(log_time_order=False)]
        return reader.get_header().library, summary.schemas, summary.channels, messages


def _records(path: Path) -> list[Any]:
    with path.open("rb") as fh:
        return list(StreamReader(fh, skip_magic=False).records)


def _native_original(path: Path) -> None:
    with NativeMcap(path, "x-test") as w:
        w.metadata("m", {"x": "1"})
        a = w.channel("/a", "json", ("a.A", "jsonschema", b'{"type":"object"}'), {"k": "v"})
        b = w.channel("/b", "protobuf", ("b.B", "protobuf", b"\x01\x02"))
        for i in range(40):
            (a if i % 3 else b).log(bytes([i]) * i, 1000 - i, None)


def test_the_native_writer_numbers_sequences_and_ids_by_first_message(tmp_path: Path) -> None:
    path = tmp_path / "n.mcap"
    _native_original(path)
    library, schemas, channels, messages = _read(path)
    assert library.startswith("foxglove-sdk-python/")
    assert {c.topic: c.id for c in channels.values()} == {"/b": 1, "/a": 2}  # /b logged first
    assert {s.name: s.id for s in schemas.values()} == {"b.B": 1, "a.A": 2}
    counts: dict[int, int] = {}
    for channel, sequence, log_time, publish_time, _ in messages:
        counts[channel] = counts.get(channel, 0) + 1
        assert (sequence, publish_time) == (counts[channel], log_time)
    assert native_copyable(_records(path))


def _chunks(path: Path) -> list[Any]:
    with path.open("rb") as fh:
        return [r for r in StreamReader(fh, skip_magic=False, emit_chunks=True).records if isinstance(r, Chunk)]


def test_chunked_originals_are_copied_chunk_by_chunk_and_unchanged(tmp_path: Path) -> None:
    src, out = tmp_path / "src.mcap", tmp_path / "out.mcap"
    _native_original(src)
    extra = NewChannel("/p", "p.P", "jsonschema", b"{}", "json", {"frame_id": "world"})
    stats = write_merged(out, [Source((src,), "mcap", "src.mcap")], [extra],
                         [NewMessage(0, 5, 5, b'{"a":1}'), NewMessage(0, 6, 6, b"{}")], metadata={"n": {"y": "2"}})
    assert (stats.messages, stats.channels, stats.schemas, stats.appended) == (40, 2, 2, 2)
    _, schemas_in, channels_in, messages_in = _read(src)
    library, schemas_out, channels_out, messages_out = _read(out)
    assert library.startswith("logpipe ")  # written by logpipe.mcap.bulk
    assert _chunks(out)[: len(_chunks(src))] == _chunks(src)  # the original's chunks, compressed bytes and all
    assert {i: schemas_out[i] for i in schemas_in} == schemas_in
    assert {i: channels_out[i] for i in channels_in} == channels_in
    assert messages_out[:40] == messages_in  # same ids, sequence numbers, times and bytes, in file order
    assert messages_out[40:] == [(3, 1, 5, 5, b'{"a":1}'), (3, 2, 6, 6, b"{}")]
    with out.open("rb") as fh:
        reader = make_reader(fh)
        assert reader.get_header().profile == "x-test"
        assert {m.name: m.metadata for m in reader.iter_metadata()} == {"m": {"x": "1"}, "n": {"y": "2"}}
    with out.open("rb") as fh:  # every CRC (chunks, data section) holds
        assert sum(isinstance(r, Message) for r in StreamReader(fh, skip_magic=False, validate_crcs=True).records) == 42


def test_an_appended_channel_reuses_the_originals_identical_schema(tmp_path: Path) -> None:
    src, out = tmp_path / "src.mcap", tmp_path / "out.mcap"
    _native_original(src)
    extra = NewChannel("/p", "a.A", "jsonschema", b'{"type":"object"}', "json")
    write_merged(out, [Source((src,), "mcap", "src.mcap")], [extra], [NewMessage(0, 5, 5, b"{}")])
    _, schemas, channels, _ = _read(out)
    assert len(schemas) == 2 and {c.topic: c.schema_id for c in channels.values()}["/p"] == 2  # a.A's id


def test_a_damaged_chunk_of_an_original_is_one_error_naming_it(tmp_path: Path) -> None:
    src = tmp_path / "src.mcap"
    _native_original(src)
    chunk = _chunks(src)[0]
    data = bytearray(src.read_bytes())
    at = data.index(chunk.data) + len(chunk.data) // 2
    data[at] ^= 0xFF
    src.write_bytes(bytes(data))
    with pytest.raises(SourceError, match=r"src\.mcap"):
        write_merged(tmp_path / "out.mcap", [Source((src,), "mcap", "src.mcap")], [], [])
    assert not (tmp_path / "out.mcap").exists()


def test_an_original_with_messages_outside_chunks_is_copied_record_by_record(tmp_path: Path) -> None:
    src, out = tmp_path / "src.mcap", tmp_path / "out.mcap"
    with src.open("wb") as fh:
        w = Writer(fh, use_chunking=False)
        w.start(profile="", library="test")
        channel = w.register_channel("/a", "json", w.register_schema("a.A", "jsonschema", b"{}"))
        for i in range(5):
            w.add_message(channel, log_time=10 - i, publish_time=i, data=b"{}", sequence=7 * i)
        w.finish()  # type: ignore[no-untyped-call]
    write_merged(out, [Source((src,), "mcap", "src.mcap")], [], [])
    assert not _chunks(src) and _read(out)[3] == [(1, 7 * i, 10 - i, i, b"{}") for i in range(5)]


def test_originals_the_native_writer_would_change_are_not_native_copyable(tmp_path: Path) -> None:
    def original(name: str, sequence_from: int = 1, publish_offset: int = 0, empty_channel: bool = False,
                 order: tuple[int, int] = (0, 1)) -> list[Any]:
        path = tmp_path / name
        with path.open("wb") as fh:
            w = Writer(fh)
            w.start(profile="", library="test")
            s = w.register_schema("a.A", "jsonschema", b"{}")
            ids = [w.register_channel("/a", "json", s), w.register_channel("/b", "json", s)]
            if empty_channel:
                w.register_channel("/empty", "json", s)
            for i in range(4):
                w.add_message(ids[order[i % 2]], log_time=i, publish_time=i + publish_offset, data=b"{}",
                              sequence=i // 2 + sequence_from)
            w.finish()  # type: ignore[no-untyped-call]
        return _records(path)

    assert native_copyable(original("ok.mcap"))
    assert not native_copyable(original("seq0.mcap", sequence_from=0))  # mcap's default sequence, ROS bags'
    assert not native_copyable(original("pub.mcap", publish_offset=1))
    assert not native_copyable(original("empty.mcap", empty_channel=True))  # the SDK would drop the channel
    assert not native_copyable(original("order.mcap", order=(1, 0)))  # the SDK would renumber the channels
