"""Predictions row groups are normalised (``row_group_table``): the bytes a Parquet writer stores depend on the
rows, not on the tables or dictionaries they arrived in."""

from __future__ import annotations

import io

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
import pyarrow.parquet as pq

from logpipe.prediction.table import RowGroupWriter, _by_first_appearance


def _chunked(rng: np.random.Generator) -> pa.ChunkedArray:
    chunks = []
    for _ in range(int(rng.integers(1, 5))):
        values = pa.array([f"v{i}" for i in rng.integers(0, 20, int(rng.integers(1, 10)))])  # duplicates too
        codes = rng.integers(0, len(values), int(rng.integers(0, 30))).astype(np.int32)
        chunks.append(pa.DictionaryArray.from_arrays(codes, values))
    return pa.chunked_array(chunks, chunks[0].type)


def test_ids_are_numbered_as_dictionary_encode_numbers_the_strings() -> None:
    rng = np.random.default_rng(0)
    for _ in range(200):
        column = _chunked(rng)
        assert _by_first_appearance(column).equals(pc.dictionary_encode(column.cast(pa.string()).combine_chunks()))


def test_same_rows_cut_differently_give_the_same_file() -> None:
    rng = np.random.default_rng(1)
    ids = [f"s{i // 3}" for i in range(500)]
    table = pa.table({"sample_id": pa.array(ids).dictionary_encode(), "x": pa.array(rng.normal(size=500))})

    def written(parts: list[pa.Table]) -> bytes:
        sink = io.BytesIO()
        with pq.ParquetWriter(sink, table.schema) as parquet:
            groups = RowGroupWriter(parquet, 64)
            for part in parts:
                groups.add(part)
            groups.flush()
        return sink.getvalue()

    whole = written([table])
    cuts = sorted(rng.choice(np.arange(1, 500), 20, replace=False).tolist())
    pieces = [table.slice(a, b - a) for a, b in zip([0, *cuts], [*cuts, 500], strict=True)]
    # Each piece numbers its own dictionary: the file must not notice.
    renumbered = [pa.table({"sample_id": p.column("sample_id").cast(pa.string()).combine_chunks()
                            .dictionary_encode(), "x": p.column("x")}) for p in pieces]
    assert written(renumbered) == whole
    assert pq.ParquetFile(io.BytesIO(whole)).metadata.num_row_groups == 8
