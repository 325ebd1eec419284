"""Building Protobuf messages from pre-serialized parts (the Foxglove messages of ``logpipe.mcap.foxglove``).

Speed: ingest writes a message per step for every log, predict one per sample with thousands of line points,
and building a Protobuf object per agent or per point costs ~30 us in Python (seconds per dataset). So each
message is built from parts the Protobuf classes serialize once (a step's timestamp, a track's id and
metadata, the fixed part of a cube or a line) plus fixed-size parts whose doubles numpy writes into
Protobuf-serialized templates (``Template``), concatenated per the wire format: a serialized message is
its fields' records in any order, the concatenation of two serializations of one type parses as their merge
(repeated fields append), and a length-delimited field is its key, the varint length and the payload. Parts
are joined in field-number order, so the bytes equal the class's own serialization except that a double
that is exactly 0 is written rather than left out (both parse to the same message).

For whole batches, ``ByteTable`` holds parts grouped by length as 2-D uint8 tables, ``varints`` and ``timestamps``
encode arrays of integers by numpy, and ``concatenated`` builds a row per message (or entity) from one part of each
table per row: rows whose parts have equal lengths form one block that numpy fills column range by column range,
and each row is cut out of its block as one bytes object in C, so no Python runs per row or per part.
"""

from __future__ import annotations

import struct
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from logpipe.types import NDArrayByte, NDArrayFloat


def varint(value: int) -> bytes:
    """Protobuf base-128 varint of a non-negative int."""
    out = bytearray()
    while value > 0x7F:
        out.append((value & 0x7F) | 0x80)
        value >>= 7
    out.append(value)
    return bytes(out)


def field_key(field_number: int) -> bytes:
    """Key of a length-delimited field (wire type 2)."""
    return varint(field_number << 3 | 2)


def serialize(message: Any) -> bytes:
    """A Protobuf message's wire-format bytes."""
    return bytes(message.SerializeToString())


def _sentinels(count: int, base: int) -> list[float]:
    # Subnormal doubles: exact, nonzero (so the field is written) and never a real size, colour or position.
    return [struct.unpack("<d", struct.pack("<Q", 0x000A_5E47_0000_0000 + base + i))[0] for i in range(count)]


_DOUBLE = np.dtype("V8")
"""8 raw bytes: doubles copied as one unit each (their places in a record are not 8-byte aligned, and copying them
as eight single bytes each is several times slower)."""


def put_doubles(target: NDArrayByte, doubles: np.ndarray) -> None:
    """Write ``doubles`` (shape ``target.shape[:-1] + (1,)``, dtype ``_DOUBLE`` or ``<f8``) into ``target``, a
    uint8 array whose last axis is 8 contiguous bytes (a view into records)."""
    target.view(_DOUBLE)[...] = doubles.view(_DOUBLE) if doubles.dtype != _DOUBLE else doubles


class Template:
    """The serialization of a message whose varying doubles hold sentinels, and where each sits.

    ``fill`` writes columns of values over the sentinels of one copy per row (doubles are fixed-size, little
    endian), so rows differing only in those doubles are built by numpy instead of one object each.
    """

    def __init__(self, build: Callable[[Sequence[float]], Any], count: int) -> None:
        self.data, self.offsets = self._locate(build, count, 0)
        self.size = len(self.data)
        # Built again with other sentinels: the same places must change and nothing else, so no byte run
        # that merely looks like a sentinel is taken for one.
        again, offsets = self._locate(build, count, 1 << 20)
        plain, other = bytearray(self.data), bytearray(again)
        for found in offsets:
            for at in found:
                plain[at : at + 8] = other[at : at + 8] = bytes(8)
        if offsets != self.offsets or plain != other:
            raise RuntimeError("template doubles are not where its sentinels are")

    @staticmethod
    def _locate(build: Callable[[Sequence[float]], Any], count: int, base: int) -> tuple[bytes, list[list[int]]]:
        marks = _sentinels(count, base)
        data = serialize(build(marks))
        offsets = []
        for mark in marks:
            pattern = struct.pack("<d", mark)
            found, at = [], data.find(pattern)
            while at >= 0:
                found.append(at)
                at = data.find(pattern, at + 1)
            if not found:
                raise RuntimeError("template lost a sentinel (a field set to a default is not serialized)")
            offsets.append(found)
        return data, offsets

    def fill(self, columns: Sequence[NDArrayFloat]) -> NDArrayByte:
        """(n, size) uint8: row i is the template with column j's value i in place of sentinel j."""
        n = len(columns[0]) if columns else 0
        out = np.tile(np.frombuffer(self.data, np.uint8), (n, 1))
        for values, offsets in zip(columns, self.offsets, strict=True):
            raw = np.ascontiguousarray(values, dtype="<f8").reshape(n, 1).view(_DOUBLE)
            for at in offsets:
                put_doubles(out[:, at : at + 8], raw)
        return out

    def rows(self, columns: Sequence[NDArrayFloat]) -> list[bytes]:
        """``fill`` as one bytes object per row."""
        return _row_bytes(self.fill(columns))


class ByteTable:
    """Byte strings grouped by length into 2-D uint8 tables, so that numpy copies whole items (``take``) instead of
    Python handling one object per use.

    Attributes:
        lengths: (items,) each item's length; ``slot``: (items,) its row in the table of its length.
    """

    def __init__(self, tables: dict[int, NDArrayByte], slot: np.ndarray, lengths: np.ndarray) -> None:
        self.tables, self.slot, self.lengths = tables, slot, lengths

    @classmethod
    def of_items(cls, items: Sequence[bytes]) -> ByteTable:
        """The table of these byte strings."""
        lengths = np.fromiter(map(len, items), np.int64, len(items))
        slot = np.zeros(len(items), np.int64)
        tables = {}
        for width in np.unique(lengths).tolist():
            which = np.flatnonzero(lengths == width)
            slot[which] = np.arange(len(which))
            tables[width] = np.frombuffer(b"".join([items[i] for i in which.tolist()]), np.uint8).reshape(
                len(which), width)
        return cls(tables, slot, lengths)

    @classmethod
    def of_rows(cls, count: int, blocks: Sequence[tuple[np.ndarray, NDArrayByte]]) -> ByteTable:
        """``count`` items given as blocks (item indexes, (len(indexes), width) uint8 rows), every item in one
        block (e.g. ``Template.fill`` per template)."""
        lengths = np.zeros(count, np.int64)
        slot = np.zeros(count, np.int64)
        parts: dict[int, list[NDArrayByte]] = {}
        for items, rows in blocks:
            width = rows.shape[1]
            lengths[items] = width
            slot[items] = sum(len(p) for p in parts.get(width, [])) + np.arange(len(items))
            parts.setdefault(width, []).append(rows)
        return cls({w: np.concatenate(p) if len(p) > 1 else p[0] for w, p in parts.items()}, slot, lengths)

    def take(self, codes: np.ndarray, width: int) -> NDArrayByte:
        """(len(codes), width) rows of items ``codes``, all ``width`` long."""
        rows: NDArrayByte = self.tables[width][self.slot[codes]]
        return rows

    def masked(self, keep: np.ndarray, empty: ByteTable) -> ByteTable:
        """These items where ``keep``, else b"" (``empty``: a table holding only b"")."""
        lengths = np.where(keep, self.lengths, 0)
        tables = dict(self.tables)
        tables.setdefault(0, empty.tables[0])
        return ByteTable(tables, np.where(keep, self.slot, 0), lengths)

    def objects(self) -> tuple[np.ndarray, np.ndarray]:
        """Each item as bytes, in an object array, and the (items,) lengths."""
        out = np.empty(len(self.lengths), object)
        for width, table in self.tables.items():
            items = np.flatnonzero(self.lengths == width)
            slots = self.slot[items]
            in_order = len(slots) == len(table) and bool((slots == np.arange(len(slots))).all())
            out[items] = _row_bytes(np.ascontiguousarray(table if in_order else table[slots]))
        return out, self.lengths


def concatenated(parts: Sequence[tuple[ByteTable, np.ndarray]], key: bytes | None = None) -> ByteTable:
    """Per row i the concatenation of each part's item ``codes[i]`` (parts as (table, (rows,) codes)); with a
    ``key``, as a length-delimited field: the key, the varint length, then that concatenation.

    Rows whose parts have the same lengths form a block that numpy fills column range by column range: no Python
    per row or per part."""
    n = len(parts[0][1]) if parts else 0
    widths_of_row = np.stack([table.lengths[codes] for table, codes in parts], axis=1) if n else np.zeros((0, 1))
    # One integer per combination of widths (np.unique over rows sorts far slower than over integers).
    combined = np.zeros(n, np.int64)
    for column in widths_of_row.T:
        combined = combined * (int(column.max(initial=0)) + 1) + column
    _, first, cls_of_row = np.unique(combined, return_index=True, return_inverse=True)
    blocks = []
    for k, widths in enumerate(widths_of_row[first].astype(np.int64).tolist()):
        rows = np.flatnonzero(cls_of_row == k)
        head = b"" if key is None else key + varint(sum(widths))
        block = np.empty((len(rows), len(head) + sum(widths)), np.uint8)
        block[:, : len(head)] = np.frombuffer(head, np.uint8)
        at = len(head)
        for (table, codes), width in zip(parts, widths, strict=True):
            block[:, at : at + width] = table.take(codes[rows], width)
            at += width
        blocks.append((rows, block))
    return ByteTable.of_rows(n, blocks)


def length_delimited_rows(key: bytes, parts: Sequence[tuple[ByteTable, np.ndarray]]) -> tuple[np.ndarray, np.ndarray]:
    """``concatenated(parts, key)`` as an object array of bytes and their (rows,) lengths."""
    return concatenated(parts, key).objects()


def varints(values: np.ndarray) -> ByteTable:
    """The base-128 varint of each non-negative integer (< 2**63), encoded by numpy."""
    values = np.asarray(values, np.uint64)
    size = np.ones(len(values), np.int64)
    for k in range(1, 10):
        size += values >= np.uint64(1 << (7 * k))
    blocks = []
    for width in np.unique(size).tolist():
        rows = np.flatnonzero(size == width)
        shifts = np.arange(width, dtype=np.uint64) * np.uint64(7)
        digits = ((values[rows, None] >> shifts) & np.uint64(0x7F)).astype(np.uint8)
        digits[:, :-1] |= 0x80
        blocks.append((rows, digits))
    return ByteTable.of_rows(len(values), blocks)


def timestamps(ns: np.ndarray) -> ByteTable:
    """Each ``google.protobuf.Timestamp`` of ns since the epoch, serialized (fields left out where 0, as the
    class does), by numpy; ``ns`` >= 0."""
    ns = np.asarray(ns, np.int64)
    if len(ns) and int(ns.min()) < 0:
        raise ValueError("timestamps before the epoch are serialized by the Timestamp class")
    seconds, nanos = np.divmod(ns, 1_000_000_000)
    empty, rows = ByteTable.of_items([b""]), np.arange(len(ns))
    return concatenated([(ByteTable.of_items([b"", b"\x08"]), (seconds > 0).astype(np.int64)),
                         (varints(seconds).masked(seconds > 0, empty), rows),
                         (ByteTable.of_items([b"", b"\x10"]), (nanos > 0).astype(np.int64)),
                         (varints(nanos).masked(nanos > 0, empty), rows)])


def _row_bytes(block: NDArrayByte) -> list[bytes]:
    """Each row of a C-contiguous (n, size) uint8 array as bytes."""
    size = block.shape[1]
    if size == 0:
        return [b""] * len(block)
    if len(block) and (block[:, -1] != 0).all():
        # numpy's fixed-width bytes make the objects in C; they drop trailing NUL bytes, hence the check.
        rows: list[bytes] = block.view(f"S{size}").ravel().tolist()
        return rows
    blob = block.tobytes()
    return [blob[i : i + size] for i in range(0, len(blob), size)]
