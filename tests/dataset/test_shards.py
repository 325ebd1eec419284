"""``logpipe.dataset.shards`` on the track shards ingest writes from the bundled Argoverse 1 CSVs (real files)."""

from __future__ import annotations

import itertools
from pathlib import Path

import numpy as np
import pyarrow.compute as pc
import pytest

from logpipe.dataset.reader import Dataset
from logpipe.dataset.shards import log_runs, log_slices
from logpipe.stages.ingest import IngestOptions, ingest
from logpipe.storage.io import as_numpy, read_table

BUNDLED = Path(__file__).resolve().parents[1] / "data"


@pytest.fixture(scope="module")
def dataset(tmp_path_factory: pytest.TempPathFactory) -> Dataset:
    out = tmp_path_factory.mktemp("shards") / "av1"
    ingest([BUNDLED / "argoverse1"], IngestOptions(out=out, format="argoverse1", write_mcap=False, workers=1))
    return Dataset.open(out)


def test_slices_tile_each_shard_and_hold_exactly_each_logs_rows(dataset: Dataset) -> None:
    seen: list[str] = []
    for path in dataset.shard_paths:
        table = read_table(path)
        slices = log_slices(table)
        assert len(slices) > 0
        # In row order, back to back, covering every row once.
        bounds = list(slices.values())
        assert bounds[0][0] == 0 and bounds[-1][1] == table.num_rows
        assert all(lo < hi for lo, hi in bounds) and all(a[1] == b[0] for a, b in itertools.pairwise(bounds))
        for log_id, (lo, hi) in slices.items():
            rows = table.slice(lo, hi - lo)
            assert set(rows.column("log_id").to_pylist()) == {log_id}
            assert rows.equals(dataset.log_tracks(log_id))  # the same rows a filtered read gives
        seen += slices
    assert sorted(seen) == sorted(dataset.logs().column("log_id").to_pylist())


def test_integer_codes_give_the_same_runs_as_the_ids(dataset: Dataset) -> None:
    table = read_table(dataset.shard_paths[0])
    codes = as_numpy(pc.dictionary_encode(table.column("log_id")).combine_chunks().indices)
    starts, ends = log_runs(codes)
    assert starts.dtype == ends.dtype == np.int64
    assert list(zip(starts.tolist(), ends.tolist(), strict=True)) == list(log_slices(table).values())
    empty_starts, empty_ends = log_runs(codes[:0])
    assert len(empty_starts) == len(empty_ends) == 0
