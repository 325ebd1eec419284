"""``SelectedSamples`` keeps the selected sample-index rows as Arrow and hands them out per log, in index order;
``SelectedLogs`` keeps the selected logs-table rows as Arrow and reads like the dict of rows by id it replaced."""

from __future__ import annotations

from pathlib import Path

import pyarrow as pa

from logpipe.dataset.reader import Dataset
from logpipe.dataset.sample_filter import (
    SelectedLogs,
    SelectedSamples,
    parse_filter,
    selected_logs,
    selected_samples,
)
from logpipe.stages.ingest import IngestOptions, ingest


def test_rows_come_per_log_in_index_order_even_when_logs_interleave() -> None:
    index = pa.table({"log_id": ["b", "a", "b", "c", "a"], "sample_id": ["b:0", "a:0", "b:5", "c:0", "a:5"]})
    samples = SelectedSamples(index)
    assert len(samples) == 5 and samples.count("a") == 2 and samples.count("zz") == 0
    assert [r["sample_id"] for r in samples.rows("b")] == ["b:0", "b:5"]
    assert samples.rows("zz") == []
    assert samples.rows_by_log(["c", "b", "zz"]) == {"c": samples.rows("c"), "b": samples.rows("b"), "zz": []}
    assert samples.table(["c", "a", "zz", "b"]).column("sample_id").to_pylist() == ["c:0", "a:0", "a:5", "b:0", "b:5"]
    assert sorted(samples.sample_ids().to_pylist()) == sorted(index.column("sample_id").to_pylist())
    assert len(SelectedSamples(index.slice(0, 0))) == 0


def test_a_split_selects_the_index_rows_of_its_logs(bundled: Path, tmp_path: Path) -> None:
    ingest([bundled / "ethucy"], IngestOptions(out=tmp_path / "eth", workers=1, write_mcap=False))
    dataset = Dataset.open(tmp_path / "eth")
    chosen = parse_filter(["split=eth/test"])
    logs = selected_logs(dataset, chosen)
    samples = selected_samples(dataset, logs, chosen)
    index = dataset.samples().to_pylist()
    wanted = set(logs.column("log_id").to_pylist())
    assert 0 < len(samples) < len(index)
    for log_id in wanted:
        assert samples.rows(log_id) == [r for r in index if r["log_id"] == log_id]


def test_selected_logs_read_like_the_dict_of_their_rows(bundled: Path, tmp_path: Path) -> None:
    ingest([bundled / "argoverse1"], IngestOptions(out=tmp_path / "av1", workers=1, write_mcap=False))
    dataset = Dataset.open(tmp_path / "av1")
    table = selected_logs(dataset, parse_filter([]))
    as_dicts = {str(r["log_id"]): r for r in table.to_pylist()}
    logs = SelectedLogs(table)
    assert len(as_dicts) > 2 and dict(logs) == as_dicts and list(logs) == list(as_dicts)  # table order
    assert list(logs.rows()) == list(as_dicts.values())
    first = next(iter(as_dicts))
    assert first in logs and "no such log" not in logs and len(logs) == len(as_dicts)
    assert logs.column("median_dt_ns") == {i: r["median_dt_ns"] for i, r in as_dicts.items()}
    assert logs.column("shard") is logs.column("shard")  # converted once
    assert dict(SelectedLogs(table.slice(0, 0))) == {}
