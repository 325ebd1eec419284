"""A split's logs in each of several datasets, and the sample filter of those logs (no torch: a baseline's
``logpipe predict`` imports the modules that use this)."""

from __future__ import annotations

from collections.abc import Sequence

import pyarrow as pa
import pyarrow.compute as pc

from logpipe.dataset.reader import Dataset
from logpipe.errors import DatasetError


def split_logs(datasets: Sequence[Dataset], split: str) -> list[list[str]]:
    """The logs of ``split`` in each dataset, in order: one a split selects nothing of adds none (an unknown split
    is an error only in a lone dataset), and a split that selects no log in any is an error."""
    logs: list[list[str]] = []
    for ds in datasets:
        try:
            logs.append(ds.logs_in_split(split))
        except DatasetError:
            if len(datasets) == 1:
                raise
            logs.append([])
    if not any(logs):
        raise DatasetError(f"no log of split {split!r} in {', '.join(str(d.root) for d in datasets)}")
    return logs


def logs_filter(ids: Sequence[str]) -> pc.Expression:
    """The sample filter of these logs."""
    return pc.is_in(pc.field("log_id"), value_set=pa.array(ids))
