"""Reading and parsing shared by the delimited-text adapters (Argoverse 1 CSV, ETH/UCY, ApolloScape).

The fast path parses many files in one pyarrow call; this module reads them into one batch, does the
bookkeeping that maps rows back to files and lines, and the slow, exact search for the first bad line when a
batch fails (only on the error path). The value checks on the parsed columns are in ``text_checks``.
"""

from __future__ import annotations

import hashlib
import itertools
import math
import os
import re
import stat
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path
from typing import ClassVar

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
import pyarrow.csv as pacsv

from logpipe.errors import SourceError
from logpipe.formats.base import TIME_LIMIT_NS, files_with_suffix, require_regular
from logpipe.storage.io import as_numpy
from logpipe.types import PENDING_SHA256, NDArrayByte, NDArrayInt, SourceFile

ID_LIMIT = float(2**31)
"""Largest |id| a numeric text format may hold. Ids are parsed as float64, and an id must round-trip exactly or be
refused: a fractional id is refused, but only if the float still holds its fraction. At 2^52 it holds none
(``4503599627370497.3`` parsed as ``...497``), below 2^31 every fraction down to 2^-21 (~5e-7) survives, and no
real ETH/UCY or ApolloScape id comes near (they count agents of one scene)."""
_DECIMAL = re.compile(r"^[+-]?(\d+\.?\d*|\.\d+)$")


@dataclass
class TextBatch:
    """Bodies of several files joined into one buffer, with where each file's rows start.

    Attributes:
        buffer: the joined data lines (headers removed), each file ending in exactly one newline.
        rows_per_file: data lines of each file.
        header_lines: lines skipped at the top of each file (to turn a row index into a line number).
        spans: (start, end) bytes of each file's lines in ``buffer``.
    """

    buffer: bytes | memoryview
    rows_per_file: list[int]
    header_lines: int
    spans: list[tuple[int, int]]

    def keep(self, files: Sequence[int]) -> TextBatch:
        """The batch of only ``files`` (indices), their lines copied into a new buffer."""
        view = memoryview(self.buffer)
        spans = [self.spans[i] for i in files]
        starts = np.cumsum([0] + [hi - lo for lo, hi in spans]).tolist()
        return TextBatch(b"".join(view[lo:hi] for lo, hi in spans), [self.rows_per_file[i] for i in files],
                         self.header_lines, list(itertools.pairwise(starts)))

    # Cached: every check asks for these, and a batch's rows never change.
    @cached_property
    def file_index(self) -> NDArrayInt:
        """(rows,) index of the file each row came from."""
        return np.repeat(np.arange(len(self.rows_per_file), dtype=np.int64), self.rows_per_file)

    @cached_property
    def row_starts(self) -> NDArrayInt:
        """(files + 1,) first row of each file, and the total."""
        return np.concatenate([[0], np.cumsum(self.rows_per_file, dtype=np.int64)])


def join_bodies(blobs: Sequence[bytes], header_lines: int) -> TextBatch:
    """Drop ``header_lines`` lines from each blob and join them, normalising the final newline."""
    parts: list[bytes | memoryview] = []
    counts: list[int] = []
    spans: list[tuple[int, int]] = []
    pos = 0
    for blob in blobs:
        start = _header_end(blob, header_lines)
        end = _strip_end(blob, start, len(blob))
        if end > start:
            parts += [memoryview(blob)[start:end], b"\n"]
            counts.append(_line_count(blob, start, end))
            spans.append((pos, pos + end - start + 1))
            pos += end - start + 1
        else:
            counts.append(0)
            spans.append((pos, pos))
    return TextBatch(b"".join(parts), counts, header_lines, spans)


_HEAD_BYTES = 4096
_TRAILING_SPACE = b"\r\n \t"


def read_bodies(
    sources: Sequence[SourceFile], header_lines: int, check_header: HeaderFn, *, keep_going: bool
) -> tuple[TextBatch, list[SourceFile], list[SourceError]]:
    """Read each file once, its lines after ``header_lines`` going straight into one shared buffer.

    What ``join_bodies`` does for blobs already read, without a ``bytes`` object per file and the copy into
    the joined buffer: one ``pread`` of a file's head (checked by ``check_header``) and one ``preadv`` of
    the rest into place; ~4x less time than read-then-join for a batch of Argoverse files here. Pending
    digests are computed from those same bytes. Returns the batch, the sources that passed ``check_header``
    (digests filled in), and the failures (raised instead unless ``keep_going``).
    """
    # Uninitialised (np.empty): zero-filling a bytearray would write the whole batch once more.
    buffer = np.empty(sum(s.size for s in sources) + len(sources), dtype=np.uint8)
    pos = 0
    spans: list[tuple[int, int]] = []
    counts: list[int] = []
    good: list[SourceFile] = []
    failures: list[SourceError] = []
    for listed in sources:
        # O_NONBLOCK: opening a FIFO returns at once instead of waiting for a writer; the fstat below then
        # refuses anything but a regular file, with no extra stat per file on the fast path.
        fd = -1
        try:
            fd = os.open(listed.path, os.O_RDONLY | os.O_NONBLOCK)
            st = os.fstat(fd)
            if not stat.S_ISREG(st.st_mode):
                raise OSError("not a regular file")
        except OSError as exc:
            if fd >= 0:
                os.close(fd)
            try:
                require_regular(listed.path, listed.relpath)  # the error path: says what the input is
                refused = SourceError(listed.relpath, f"not readable: {exc.strerror or exc}")
            except SourceError as err:
                refused = err
            if not keep_going:
                raise refused from None
            failures.append(refused)
            continue
        try:
            size = st.st_size
            head = _read_head(fd, size, header_lines)
            start = _header_end(head, header_lines)
            if len(buffer) < pos + size - start + 1:  # the file grew since it was listed
                buffer = np.concatenate([buffer, np.empty(pos + size - start + 1 - len(buffer), np.uint8)])
            view = buffer.data
            got = os.preadv(fd, [view[pos:pos + size - start]], start) if size > start else 0
            source = listed if listed.sha256 != PENDING_SHA256 else SourceFile(
                listed.path, listed.relpath, _digest(head[:start], view[pos:pos + got]), listed.size,
                listed.memberships)
        finally:
            os.close(fd)
        end = _strip_end(buffer, pos, pos + got)
        error = (_check_encoding(source, head)
                 or check_header(source, head[:start] if header_lines else head, end > pos)
                 or _cut_last_line(source, buffer, pos, end, pos + got, header_lines))
        if error is not None:
            if not keep_going:
                raise error
            failures.append(error)
            continue  # its bytes are overwritten by the next file
        good.append(source)
        if end > pos:
            buffer[end] = 10  # exactly one newline after each file's last line
            counts.append(_line_count(buffer, pos, end))
            spans.append((pos, end + 1))
            pos = end + 1
        else:
            counts.append(0)
            spans.append((pos, pos))
    return TextBatch(buffer.data[:pos], counts, header_lines, spans), good, failures


_BOM = b"\xef\xbb\xbf"


def _check_encoding(source: SourceFile, head: bytes) -> SourceError | None:
    """Refuse a byte-order mark and CR-only line endings up front: pyarrow skips a BOM only at the start of
    the joined buffer and ends lines at a bare CR, so either would misalign rows with files and lines."""
    if head.startswith(_BOM):
        return SourceError(source.relpath, "starts with a UTF-8 byte-order mark (save the file without one)",
                           line=1)
    lines = head.rstrip(b"\r\n")
    if b"\r" in lines and b"\n" not in lines:
        return SourceError(source.relpath, "lines end in a bare CR (old Mac line endings); use LF or CRLF", line=1)
    return None


def _read_head(fd: int, size: int, header_lines: int) -> bytes:
    """The file's first 4 KiB, or more when its header lines do not fit in them."""
    head = os.pread(fd, min(size, _HEAD_BYTES), 0)
    if header_lines and len(head) < size and _header_end(head, header_lines) == len(head):
        head = os.pread(fd, size, 0)  # a header longer than 4 KiB (only a malformed file has one)
    return head


def _header_end(head: bytes, header_lines: int) -> int:
    """Offset just past the ``header_lines``-th newline of ``head`` (its length if it has fewer)."""
    start = 0
    for _ in range(header_lines):
        newline = head.find(b"\n", start)
        if newline < 0:
            return len(head)
        start = newline + 1
    return start


def _digest(header: bytes, body: memoryview) -> str:
    digest = hashlib.sha256(header)
    digest.update(body)
    return digest.hexdigest()


def _strip_end(buffer: bytes | NDArrayByte, lo: int, hi: int) -> int:
    """``hi`` moved back over trailing whitespace (never below ``lo``)."""
    while hi > lo and int(buffer[hi - 1]) in _TRAILING_SPACE:
        hi -= 1
    return hi


def _cut_last_line(source: SourceFile, buffer: NDArrayByte, lo: int, end: int, hi: int,
                   header_lines: int) -> SourceError | None:
    """An error when the file's last record has no newline after it (``buffer[end:hi]`` is the whitespace
    after the last value): a file cut mid-record ends there, and a number cut short (10.3817 -> 10.3) still
    parses, as another value. Every real file of every text format here ends with a newline."""
    if end <= lo or 10 in buffer[end:hi].tolist():
        return None
    line = _line_count(buffer, lo, end) + header_lines
    return SourceError(source.relpath, "truncated record: the last line has no newline after it (the file was "
                       "cut short?); its values cannot be trusted", line=line)


def _line_count(buffer: bytes | NDArrayByte, lo: int, hi: int) -> int:
    """Lines in ``buffer[lo:hi]`` (no trailing newline there). A vectorised compare counts them ~3x faster
    than ``bytes.count`` (~6% of an Argoverse ingest)."""
    return int(np.count_nonzero(np.frombuffer(buffer, np.uint8, count=hi - lo, offset=lo) == 10)) + 1


def parse_batch(
    batch: TextBatch, names: list[str], types: dict[str, pa.DataType], delimiter: str
) -> pa.Table:
    """Parse the joined buffer in one call (no quoting: none of these formats quote).

    Dictionary-of-string columns are parsed as dictionary-of-binary and their dictionaries then cast to
    string: UTF-8 is checked once per distinct value instead of once per row (~15% of the parse of an
    Argoverse batch). Invalid UTF-8 raises ``pa.ArrowInvalid`` either way (the caller then finds the line).
    """
    read = pacsv.ReadOptions(column_names=names, block_size=1 << 24, use_threads=False)
    parse = pacsv.ParseOptions(
        delimiter=delimiter, quote_char=False, double_quote=False, ignore_empty_lines=False
    )
    as_binary = [n for n in names if pa.types.is_dictionary(types[n]) and pa.types.is_string(types[n].value_type)]
    parsed_types = {n: pa.dictionary(types[n].index_type, pa.binary()) if n in as_binary else types[n] for n in names}
    convert = pacsv.ConvertOptions(
        column_types=parsed_types, strings_can_be_null=False, quoted_strings_can_be_null=False
    )
    table = pacsv.read_csv(pa.py_buffer(batch.buffer), read, parse, convert)
    for name in as_binary:
        column = table.column(name)
        chunks = [pa.DictionaryArray.from_arrays(c.indices, c.dictionary.cast(pa.string())) for c in column.chunks]
        table = table.set_column(table.schema.get_field_index(name), name, pa.chunked_array(chunks, types[name]))
    return table


def locate_bad_line(
    source: SourceFile,
    blob: bytes,
    names: list[str],
    numeric: set[str],
    header_lines: int,
    splitter: str | None,
) -> SourceError:
    """Scan one file line by line and describe its first malformed line (the slow, exact error path).

    Args:
        source: the file (named in the error).
        blob: its bytes.
        names: expected columns in order.
        numeric: columns that must hold finite numbers.
        header_lines: lines before the data.
        splitter: field delimiter, or None for runs of whitespace.
    """
    try:
        text = blob.decode("utf-8")
    except UnicodeDecodeError as exc:
        line_start = blob.rfind(b"\n", 0, exc.start) + 1
        before = blob[line_start:exc.start]
        column = len(before.split(splitter.encode()) if splitter else before.split()) - 1
        column = column + 1 if not splitter and before[-1:].isspace() else column
        return SourceError(source.relpath, f"not UTF-8 text ({exc.reason} at byte {exc.start})",
                           line=blob.count(b"\n", 0, exc.start) + 1,
                           field=names[column] if 0 <= column < len(names) else None)
    lines = text.splitlines()
    for number, raw in enumerate(lines[header_lines:], start=header_lines + 1):
        line = raw.strip()
        fields = line.split(splitter) if splitter else line.split()
        if not line:
            return SourceError(source.relpath, "empty line inside the data", line=number)
        if len(fields) != len(names):
            return SourceError(
                source.relpath, f"expected {len(names)} columns ({', '.join(names)}), found {len(fields)}",
                line=number,
            )
        for name, value in zip(names, fields, strict=True):
            if name in numeric and not _DECIMAL.match(value.strip()):
                try:
                    number_value = float(value)
                except ValueError:
                    return SourceError(source.relpath, f"not a number: {value!r}", line=number, field=name)
                if not math.isfinite(number_value):
                    return SourceError(source.relpath, f"not finite: {value!r}", line=number, field=name)
                return SourceError(source.relpath, f"not a plain decimal: {value!r}", line=number, field=name)
    return SourceError(source.relpath, "could not be parsed (no single bad line found)")


def dictionary_column(values: pa.ChunkedArray | pa.Array) -> pa.DictionaryArray:
    """One dictionary array for a column parsed as dictionary (chunks may carry different dictionaries)."""
    if isinstance(values, pa.ChunkedArray):
        if values.num_chunks == 0:
            empty: pa.DictionaryArray = pa.array([], values.type)
            return empty
        if values.num_chunks == 1:
            single: pa.DictionaryArray = values.chunk(0)
            return single
        combined: pa.DictionaryArray = values.unify_dictionaries().combine_chunks()
        return combined
    return values


def decimal_seconds_to_ns(values: pa.Array, scale_ns: int = 1_000_000_000) -> tuple[pa.Array, pa.Array]:
    """Exact conversion of decimal strings (``"315968203.70296454"``) to int64 nanoseconds.

    Floats lose ~30 ns at Argoverse's 3e8 s; splitting integer and fraction keeps the written digits.
    Works on the distinct values only (a few dozen per log). Returns (nanoseconds, valid mask); invalid
    entries hold 0 and are reported by the caller.
    """
    encoded = pc.dictionary_encode(values) if not pa.types.is_dictionary(values.type) else values
    chunk = encoded.combine_chunks() if isinstance(encoded, pa.ChunkedArray) else encoded
    dictionary = chunk.dictionary
    # At most 18 integer digits (cast to int64 cannot fail), then a bound so that x scale_ns cannot wrap.
    valid = pc.match_substring_regex(dictionary, r"^[+]?\d{1,18}(\.\d*)?$")
    safe = pc.if_else(valid, dictionary, "0")
    # A trailing "." guarantees two parts ("123" -> "123." -> ["123", ""]) so no branch needs a guard.
    parts = pc.split_pattern(pc.binary_join_element_wise(safe, "", "."), ".", max_splits=1)
    whole = pc.cast(pc.list_element(parts, 0), pa.int64())
    in_range = pc.less(whole, TIME_LIMIT_NS // scale_ns)
    valid = pc.and_(valid, in_range)
    whole = pc.if_else(in_range, whole, 0)
    fraction_text = pc.utf8_rtrim(pc.list_element(parts, 1), ".")
    digits = len(str(scale_ns)) - 1
    padded = pc.utf8_rpad(pc.utf8_slice_codeunits(fraction_text, 0, digits), digits, "0")
    ns = pc.add(pc.multiply(whole, scale_ns), pc.cast(padded, pa.int64()))
    return pc.take(ns, chunk.indices), pc.take(valid, chunk.indices)


ValidateFn = Callable[[pa.Table, TextBatch, Sequence[SourceFile]], tuple[pa.Table, list[SourceError]]]
"""Checks a parsed batch; returns the table (optionally with derived columns it computed anyway) and errors."""
HeaderFn = Callable[[SourceFile, bytes, bool], SourceError | None]
"""Checks a file before parsing: (source, its header lines (its first 4 KiB for a header-less format),
whether anything but whitespace follows them)."""


def _empty_check(source: SourceFile, head: bytes, has_rows: bool) -> SourceError | None:
    if not has_rows:
        return SourceError(source.relpath, "empty file (no rows)", line=1)
    return None


def parse_files(
    sources: Sequence[SourceFile],
    *,
    keep_going: bool,
    names: list[str],
    types: dict[str, pa.DataType],
    delimiter: str,
    header_lines: int,
    validate: ValidateFn,
    check_header: HeaderFn = _empty_check,
) -> tuple[pa.Table, TextBatch, list[SourceFile], list[SourceError]]:
    """Read, join, parse and validate a batch of text files of one format.

    Returns the parsed table, its ``TextBatch`` bookkeeping, the sources that made it in, and failures.
    A failing file raises its ``SourceError`` unless ``keep_going``; then it is dropped and the rest retried.
    """
    numeric = {n for n, t in types.items() if pa.types.is_floating(t) or pa.types.is_integer(t)}
    batch, good, failures = read_bodies(sources, header_lines, check_header, keep_going=keep_going)
    while True:
        if not good:  # every file failed: an empty table, so callers need no special case
            empty, _ = validate(pa.schema([(n, types[n]) for n in names]).empty_table(), batch, good)
            return empty, batch, good, failures
        try:
            table = parse_batch(batch, names, types, delimiter)
            if table.num_rows != int(batch.row_starts[-1]):  # a bare CR or stray quote split lines differently
                raise pa.ArrowInvalid("rows parsed do not match the lines read")
        except pa.ArrowException:
            errors = _locate_parse_errors(good, names, types, delimiter, header_lines, numeric)
        else:
            table, found = validate(table, batch, good)
            errors = _first_per_file(found, good)
            if not errors:
                return table, batch, good, failures
        if not keep_going:
            raise errors[0]
        failures.extend(errors)
        bad = {e.file for e in errors}
        keep = [i for i, s in enumerate(good) if s.relpath not in bad]
        good = [good[i] for i in keep]
        batch = batch.keep(keep)


def _locate_parse_errors(
    sources: Sequence[SourceFile],
    names: list[str],
    types: dict[str, pa.DataType],
    delimiter: str,
    header_lines: int,
    numeric: set[str],
) -> list[SourceError]:
    """Slow path after a failed batch parse: every file that fails alone, with its first bad line."""
    errors = []
    splitter = None if delimiter == " " else delimiter
    blobs = []
    for source in sources:
        with open(source.path, "rb") as fh:  # read again: the error path only
            blob = fh.read()
        blobs.append(blob)
        if not _parses(blob, names, types, delimiter, header_lines):
            errors.append(locate_bad_line(source, blob, names, numeric, header_lines, splitter))
    if errors:
        return errors
    # Every file parses alone but not together: blame the first file whose addition breaks the batch (never
    # a neighbour that is fine), found by parsing growing prefixes.
    for k in range(1, len(blobs)):
        if not _parses(b"".join(_with_newline(b) for b in blobs[:k + 1]), names, types, delimiter, header_lines,
                       files=[_with_newline(b) for b in blobs[:k + 1]]):
            return [SourceError(sources[k].relpath, "parses alone but not after the files before it in its batch "
                                "(an odd first line or encoding)", line=1)]
    return [SourceError(sources[0].relpath, "batch failed to parse but no file or prefix of files does")]


def _with_newline(blob: bytes) -> bytes:
    return blob if blob.endswith(b"\n") else blob + b"\n"


def _parses(blob: bytes, names: list[str], types: dict[str, pa.DataType], delimiter: str, header_lines: int,
            files: list[bytes] | None = None) -> bool:
    """Whether ``blob`` (or the files ``files`` joined) parses, with one row per line."""
    batch = join_bodies(files if files is not None else [blob], header_lines)
    try:
        table = parse_batch(batch, names, types, delimiter)
    except pa.ArrowException:
        return False
    return bool(table.num_rows == int(batch.row_starts[-1]))


def _first_per_file(errors: list[SourceError], sources: Sequence[SourceFile]) -> list[SourceError]:
    first: dict[str, SourceError] = {}
    for e in errors:
        first.setdefault(e.file, e)
    order = {s.relpath: i for i, s in enumerate(sources)}
    return sorted(first.values(), key=lambda e: order[e.file])


def stem(relpath: str) -> str:
    """``Path(relpath).stem`` of a POSIX relpath, without building a ``Path`` (~20 us each, once per file)."""
    name = relpath.rsplit("/", 1)[-1]
    dot = name.rfind(".")
    return name[:dot] if 0 < dot < len(name) - 1 else name


def log_ids_column(batch: TextBatch, sources: Sequence[SourceFile]) -> pa.Array:
    """(rows,) log id of each row: the stem of its file, dictionary-encoded by file when the stems are
    distinct (the Parquet writer then takes the dictionary as it is instead of hashing every row)."""
    names = [stem(s.relpath) for s in sources]
    stems = pa.array(names, pa.string())
    if len(set(names)) < len(names):  # a clash, reported at commit: keep one value per row
        return pc.take(stems, pa.array(batch.file_index))
    return pa.DictionaryArray.from_arrays(pa.array(batch.file_index.astype(np.int32)), stems)


def relabel(codes: pa.DictionaryArray, mapping: dict[str, str]) -> pa.DictionaryArray:
    """``codes`` with every dictionary value replaced by ``mapping[value]``, still dictionary-encoded with
    distinct values (no per-row strings)."""
    labels = [mapping[v] for v in codes.dictionary.to_pylist()]
    values, inverse = np.unique(np.array(labels, dtype=object), return_inverse=True)
    indices = inverse.astype(np.int32)[as_numpy(codes.indices)]
    return pa.DictionaryArray.from_arrays(pa.array(indices), pa.array(values.tolist(), pa.string()))


class NumericTextFormat:
    """Shared discovery and sniffing of header-less, all-numeric ``.txt`` formats (ETH/UCY, ApolloScape).

    Subclasses set ``columns`` and ``delimiter`` (``" "`` means runs of spaces, as ApolloScape writes them).
    """

    columns: ClassVar[list[str]]
    delimiter: ClassVar[str]
    hashes_while_reading: ClassVar[bool] = True  # parse_files hashes each blob it reads

    def discover(self, root: Path) -> list[Path]:
        """``*.txt`` files under ``root`` (or ``root`` itself)."""
        return files_with_suffix(root, (".txt",))

    def sniff(self, path: Path) -> bool:
        """True for a ``.txt`` whose first line has exactly ``len(columns)`` numbers split by ``delimiter``."""
        if path.suffix.lower() != ".txt" or not path.is_file():
            return False
        with path.open("rb") as fh:
            line = fh.readline()
        fields = line.split() if self.delimiter == " " else line.split(self.delimiter.encode())
        try:
            return len(fields) == len(self.columns) and all(float(f) == float(f) for f in fields)
        except ValueError:
            return False
