"""Which samples of a dataset a run covers: ``SampleFilter`` (the ``--filter`` strings parsed) and the logs and
sample-index rows it selects.

Times are ns on each log's clock; a sample's time is its prediction time (``current_ns``, the last observed step).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import pyarrow as pa
import pyarrow.compute as pc

from logpipe.dataset.reader import Dataset
from logpipe.dataset.shards import log_slices
from logpipe.errors import DatasetError, LogpipeError
from logpipe.types import OBJECT_TYPES


@dataclass(frozen=True)
class SampleFilter:
    """Which samples to predict; empty fields select everything.

    Attributes:
        log_ids: only these logs.
        split: only logs of this split (``eth/test``, ``hash/val``; see ``Dataset.logs_in_split``).
        start_ns: only samples whose prediction time (current step) is >= this, ns on the log clock.
        end_ns: ... and <= this.
        object_types: only targets of these classes (``OBJECT_TYPES``); samples left without targets are dropped.
    """

    log_ids: tuple[str, ...] = ()
    split: str | None = None
    start_ns: int | None = None
    end_ns: int | None = None
    object_types: tuple[str, ...] = ()

    def to_dict(self) -> dict[str, Any]:
        """Plain dict (run settings)."""
        return dataclasses.asdict(self)


def parse_filter(items: Sequence[str]) -> SampleFilter:
    """``SampleFilter`` from ``--filter`` strings: ``log=ID[,ID..]``, ``split=eth/test``,
    ``time=START_NS:END_NS`` (either side may be empty), ``type=pedestrian[,cyclist..]``; repeatable.

    Raises:
        LogpipeError: an unknown key, a malformed time range or an unknown object type.
    """
    logs: list[str] = []
    types: list[str] = []
    split = start = end = None
    for item in items:
        key, sep, value = item.partition("=")
        if not sep:
            raise LogpipeError(f"--filter expects KEY=VALUE (log=, split=, time=, type=), got {item!r}")
        if key == "log":
            logs += [v for v in value.split(",") if v]
        elif key == "split":
            split = value
        elif key == "time":
            lo, colon, hi = value.partition(":")
            try:
                start = int(lo) if lo else None
                end = int(hi) if hi else None
            except ValueError:
                colon = ""
            if not colon:
                raise LogpipeError(f"--filter time= expects START_NS:END_NS (integers, ns), got {value!r}")
        elif key == "type":
            bad = [t for t in value.split(",") if t not in OBJECT_TYPES]
            if bad:
                raise LogpipeError(f"--filter type=: unknown object types {bad}; known: {', '.join(OBJECT_TYPES)}")
            types += value.split(",")
        else:
            raise LogpipeError(f"--filter: unknown key {key!r}; use log=, split=, time= or type=")
    return SampleFilter(tuple(logs), split, start, end, tuple(types))


def selected_logs(dataset: Dataset, f: SampleFilter) -> pa.Table:
    """The rows of the dataset's logs table that ``f`` selects (in the table's order).

    Raises:
        DatasetError: ``f`` names logs the dataset does not have.
    """
    logs = dataset.logs()
    keep = set(logs.column("log_id").to_pylist())
    if f.log_ids:
        missing = sorted(set(f.log_ids) - keep)
        if missing:
            raise DatasetError(f"{dataset.root}: no logs {missing}")
        keep &= set(f.log_ids)
    if f.split is not None:
        keep &= set(dataset.logs_in_split(f.split))
    return logs.filter(pc.is_in(logs.column("log_id"), value_set=pa.array(sorted(keep), pa.string())))


def selected_samples(dataset: Dataset, logs: pa.Table, f: SampleFilter) -> SelectedSamples:
    """The sample-index rows of the ``logs`` rows within ``f``'s time range."""
    samples = dataset.samples()
    mask = pc.is_in(samples.column("log_id"), value_set=logs.column("log_id"))
    if f.start_ns is not None:
        mask = pc.and_(mask, pc.greater_equal(samples.column("current_ns"), f.start_ns))
    if f.end_ns is not None:
        mask = pc.and_(mask, pc.less_equal(samples.column("current_ns"), f.end_ns))
    return SelectedSamples(samples.filter(mask))


class SelectedSamples:
    """Selected sample-index rows by log, kept as one Arrow table: ~100 bytes a sample where a dict per row costs
    ~1.5 kB, so a run's memory hardly grows with the corpus; rows become dicts one log at a time, when asked.

    Args:
        table: sample-index rows (ids as strings), in index order.
    """

    def __init__(self, table: pa.Table) -> None:
        # Stable: a log's samples keep their index order.
        self._table = table.take(pc.sort_indices(table, [("log_id", "ascending")])) if table.num_rows else table
        self._slices = log_slices(self._table) if table.num_rows else {}

    def __len__(self) -> int:
        return int(self._table.num_rows)

    def count(self, log_id: str) -> int:
        """How many samples of ``log_id`` are selected."""
        lo, hi = self._slices.get(log_id, (0, 0))
        return int(hi - lo)

    def rows(self, log_id: str) -> list[dict[str, Any]]:
        """The selected rows of ``log_id`` as dicts, in index order (empty for a log without any)."""
        rows: list[dict[str, Any]] = self.table([log_id]).to_pylist()
        return rows

    def rows_by_log(self, log_ids: Sequence[str]) -> dict[str, list[dict[str, Any]]]:
        """``rows`` of each of ``log_ids`` from one conversion (per log, its fixed cost dominated one-sample
        logs such as Argoverse's)."""
        grouped: dict[str, list[dict[str, Any]]] = {log_id: [] for log_id in log_ids}
        for row in self.table(log_ids).to_pylist():
            grouped[row["log_id"]].append(row)
        return grouped

    def table(self, log_ids: Sequence[str]) -> pa.Table:
        """The selected rows of ``log_ids``, log after log in that order, each log's in index order."""
        parts = [self._table.slice(lo, hi - lo) for lo, hi in (self._slices[i] for i in log_ids if i in self._slices)]
        return pa.concat_tables(parts) if parts else self._table.slice(0, 0)

    def sample_ids(self) -> pa.ChunkedArray:
        """Every selected sample's id."""
        return self._table.column("sample_id")


class SelectedLogs(Mapping[str, dict[str, Any]]):
    """Selected logs-table rows by log id, in table order, kept as one Arrow table: a dict per row cost ~1.2 kB a
    log (58 MB of a 50k-log predict run's memory), an id and its row number ~0.1 kB; a row becomes a dict when
    asked, a column when ``column`` is.

    Args:
        table: logs-table rows (``selected_logs``), ids as strings.
    """

    def __init__(self, table: pa.Table) -> None:
        self.table = table
        self._ids: list[str] = [str(i) for i in table.column("log_id").to_pylist()]
        self._row = {log_id: i for i, log_id in enumerate(self._ids)}
        self._columns: dict[str, dict[str, Any]] = {}

    def __getitem__(self, log_id: str) -> dict[str, Any]:
        row: dict[str, Any] = self.table.slice(self._row[log_id], 1).to_pylist()[0]
        return row

    def __contains__(self, log_id: object) -> bool:
        return log_id in self._row

    def __iter__(self) -> Iterator[str]:
        return iter(self._ids)

    def __len__(self) -> int:
        return len(self._ids)

    def column(self, name: str) -> dict[str, Any]:
        """One column's value of each log by id (converted once, then kept)."""
        if name not in self._columns:
            self._columns[name] = dict(zip(self._ids, self.table.column(name).to_pylist(), strict=True))
        return self._columns[name]

    def rows(self) -> Iterator[dict[str, Any]]:
        """Every row as a dict, in table order, a few thousand at a time."""
        for batch in self.table.to_batches(max_chunksize=4096):
            yield from batch.to_pylist()
