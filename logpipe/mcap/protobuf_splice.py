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
            raw = np.ascontiguousarray(values, dtype="<f8").view(np.uint8).reshape(n, 8)
            for at in offsets:
                out[:, at : at + 8] = raw
        return out

    def rows(self, columns: Sequence[NDArrayFloat]) -> list[bytes]:
        """``fill`` as one bytes object per row."""
        filled, size = self.fill(columns), self.size
        if len(filled) and (filled[:, -1] != 0).all():
            # numpy's fixed-width bytes make the objects in C; they drop trailing NUL bytes, hence the check.
            rows: list[bytes] = filled.view(f"S{size}").ravel().tolist()
            return rows
        blob = filled.tobytes()
        return [blob[i : i + size] for i in range(0, len(blob), size)]
