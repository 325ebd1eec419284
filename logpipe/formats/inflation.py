"""Bounded decompression of ROS 1 bag chunks, checked before ``rosbags`` decompresses them without a bound.

An 8 KB bz2 bag inflating to 677 MB took ingest to 677 MB of memory (``inspect`` to 1.1 GB): the reader trusts the
data. Each chunk record of a ``.bag`` (format 2.0) declares its decompressed ``size``; before any reader opens the
bag, every chunk is checked here:

* its declared size is at most ``LOGPIPE_MAX_INFLATION`` (default 1000) times its compressed size, with a floor
  of 16 MiB (small chunks of repetitive messages), and at most ``LOGPIPE_MAX_CHUNK_BYTES`` (default 1 GiB);
* the declared sizes of all chunks together are at most the same ratio times the file, or 16 MiB;
* it decompresses (streaming, at most declared + 1 bytes held) to no more than it declares.

The checks stream one chunk at a time and hold at most one decompressed chunk.
"""

from __future__ import annotations

import bz2
import os
import struct
from pathlib import Path
from typing import Any, BinaryIO

BAG_MAGIC = b"#ROSBAG V2.0\n"
FLOOR_BYTES = 16 << 20
_CHUNK_OP = 0x05


class InflationError(ValueError):
    """A compressed record inflates past what this file can hold (a decompression bomb or damage)."""


def limits() -> tuple[int, int]:
    """(largest ratio of decompressed to compressed bytes, largest decompressed chunk in bytes), from the
    environment (``LOGPIPE_MAX_INFLATION``, ``LOGPIPE_MAX_CHUNK_BYTES``) or the defaults."""
    try:
        ratio = int(os.environ.get("LOGPIPE_MAX_INFLATION", "1000"))
        chunk = int(os.environ.get("LOGPIPE_MAX_CHUNK_BYTES", str(1 << 30)))
    except ValueError:
        raise InflationError("LOGPIPE_MAX_INFLATION and LOGPIPE_MAX_CHUNK_BYTES must be whole numbers") from None
    return max(ratio, 1), max(chunk, 1)


def _fields(header: bytes) -> dict[str, bytes]:
    out: dict[str, bytes] = {}
    at = 0
    while at + 4 <= len(header):
        (n,) = struct.unpack_from("<I", header, at)
        name, _, value = header[at + 4: at + 4 + n].partition(b"=")
        out[name.decode("latin-1")] = value
        at += 4 + n
    return out


def _read_exact(fh: BinaryIO, n: int) -> bytes | None:
    data = fh.read(n)
    return data if len(data) == n else None


def check_ros1_bag(path: Path) -> None:
    """Refuse a ROS 1 bag whose chunks would inflate past the limits (module docstring); a file that is not a
    version 2.0 bag, or is cut short, is left to the reader, which says why.

    Raises:
        InflationError: naming the chunk (its byte offset) and the sizes.
    """
    ratio, most = limits()
    size = path.stat().st_size
    total = 0
    with path.open("rb") as fh:
        if fh.read(len(BAG_MAGIC)) != BAG_MAGIC:
            return
        while True:
            offset = fh.tell()
            raw = _read_exact(fh, 4)
            if raw is None:
                return
            (header_len,) = struct.unpack("<I", raw)
            header = _read_exact(fh, header_len) if header_len <= size else None
            raw = _read_exact(fh, 4) if header is not None else None
            if header is None or raw is None:
                return
            (data_len,) = struct.unpack("<I", raw)
            fields = _fields(header)
            if fields.get("op") != bytes([_CHUNK_OP]) or data_len > size:
                fh.seek(data_len, os.SEEK_CUR)
                continue
            declared = struct.unpack("<I", fields.get("size", b"\0\0\0\0")[:4].ljust(4, b"\0"))[0]
            total += declared
            bound = min(most, max(ratio * data_len, FLOOR_BYTES))
            if declared > bound or total > max(ratio * size, FLOOR_BYTES):
                raise InflationError(f"chunk at byte {offset} declares {declared} bytes decompressed from "
                                     f"{data_len} (at most {bound}; {total} in all for a {size}-byte file)")
            compression = fields.get("compression", b"none").decode("latin-1")
            data = fh.read(data_len)
            if compression in ("bz2", "lz4"):
                _check_inflation(data, compression, declared, offset)


def check_ros1_bags(paths: list[Path]) -> None:
    """``check_ros1_bag`` on each ``.bag`` of ``paths`` (a bag's storage files)."""
    for path in paths:
        if path.suffix == ".bag":
            check_ros1_bag(path)


def _check_inflation(data: bytes, compression: str, declared: int, offset: int) -> None:
    """Decompress at most ``declared`` + 1 bytes; more means the chunk lies about its size."""
    try:
        if compression == "bz2":
            out = bz2.BZ2Decompressor().decompress(data, max_length=declared + 1)
        else:
            import lz4.frame

            out = lz4.frame.LZ4FrameDecompressor().decompress(data, max_length=declared + 1)
    except (OSError, RuntimeError, EOFError):  # damaged data: the reader reports it
        return
    if len(out) > declared:
        raise InflationError(f"{compression} chunk at byte {offset} inflates past the {declared} bytes it declares")


def _zstd() -> Any:
    """The ``zstd`` module rosbags uses: the standard library's from Python 3.14, else ``backports.zstd``."""
    try:
        from compression import zstd  # type: ignore[import-not-found,unused-ignore]
    except ImportError:
        from backports import zstd  # type: ignore[import-not-found,unused-ignore,no-redef]
    return zstd


def _message_limit(compressed: int) -> int:
    ratio, cap = limits()
    return min(cap, max(ratio * compressed, FLOOR_BYTES))


def bounded_zstd_decompress(data: bytes) -> bytes:
    """``zstd.decompress`` that holds at most the limit + 1 bytes (``limits``: ratio to the compressed size with
    the ``FLOOR_BYTES`` floor, and the chunk cap) and refuses past it: a ROS 2 message of a few KB declaring
    1 GiB otherwise took 2.25 GB (and 4 GiB a ``MemoryError``)."""
    zstd = _zstd()
    limit = _message_limit(len(data))
    out = bytearray()
    rest = bytes(data)
    while rest:
        decompressor = zstd.ZstdDecompressor()
        out += decompressor.decompress(rest, max_length=limit + 1 - len(out))
        if len(out) > limit or not decompressor.eof:
            what = "inflates past" if len(out) > limit else "is cut short before"
            raise InflationError(f"a zstd-compressed message of {len(data)} bytes {what} the {limit} bytes "
                                 "allowed (LOGPIPE_MAX_INFLATION times its size, at most LOGPIPE_MAX_CHUNK_BYTES)")
        rest = decompressor.unused_data
    return bytes(out)


class _BoundedStream:
    """A zstd stream that refuses to inflate past ``limit`` bytes in total."""

    def __init__(self, inner: BinaryIO, limit: int, compressed: int) -> None:
        self._inner, self._limit, self._compressed, self._read = inner, limit, compressed, 0

    def read(self, size: int = -1) -> bytes:
        want = self._limit + 1 - self._read if size < 0 else min(size, self._limit + 1 - self._read)
        data = self._inner.read(max(want, 1))
        self._read += len(data)
        if self._read > self._limit:
            raise InflationError(f"a zstd-compressed storage file of {self._compressed} bytes inflates past the "
                                 f"{self._limit} bytes allowed (LOGPIPE_MAX_INFLATION times its size)")
        return data

    def __enter__(self) -> _BoundedStream:
        return self

    def __exit__(self, *exc: object) -> None:
        self._inner.close()


class BoundedZstd:
    """Stands in for the ``zstd`` module inside ``rosbags.rosbag2.reader`` (its only uses: ``decompress`` per
    message, ``open`` per compressed storage file), so both are bounded like MCAP and ROS 1 chunks."""

    @staticmethod
    def decompress(data: bytes) -> bytes:
        return bounded_zstd_decompress(data)

    @staticmethod
    def open(source: BinaryIO, mode: str = "rb") -> _BoundedStream:
        zstd = _zstd()
        size = os.fstat(source.fileno()).st_size
        ratio, _cap = limits()
        return _BoundedStream(zstd.open(source, mode), max(ratio * size, FLOOR_BYTES), size)


def bound_rosbag2_zstd() -> None:
    """Make ``rosbags``' ROS 2 reader decompress through ``BoundedZstd`` (idempotent)."""
    from rosbags.rosbag2 import reader

    reader.zstd = BoundedZstd  # type: ignore[assignment,attr-defined,unused-ignore]


bound_rosbag2_zstd()  # every importer of this module reads bags through rosbags: bounded from the first read
