"""``logpipe index``: rebuild a dataset's sample index with another protocol, without re-ingesting.

Reads top-down: lock the dataset folder → (nothing to do when the protocol is unchanged) → one shard at a time,
cut the windows (``logpipe.dataset.samples.build_samples``) and say why logs give none → commit the new index
(``DatasetWriter.commit_index``: the manifest swap).
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import pyarrow as pa

from logpipe.contracts import arrow_schema
from logpipe.dataset.log_table import log_metas
from logpipe.dataset.reader import Dataset
from logpipe.dataset.samples import TrackCodes, build_samples, no_sample_reasons, reason_counts
from logpipe.dataset.writer import DatasetWriter
from logpipe.errors import DatasetError
from logpipe.progress import report_total
from logpipe.storage.artifact import output_errors
from logpipe.storage.io import read_table
from logpipe.types import SampleProtocol


def reindex(dataset_dir: Path, protocol: SampleProtocol,
            progress: Callable[[int], None] | None = None) -> dict[str, Any]:
    """Rebuild the sample index with ``protocol``, one shard in memory at a time, as one new commit;
    ``progress`` is called with the number of logs each shard held."""
    with output_errors(), DatasetWriter(dataset_dir) as writer:
        if writer.manifest is None:
            raise DatasetError(f"{dataset_dir}: not a logpipe dataset (no manifest.json); run `logpipe ingest` first")
        dataset = Dataset.open(dataset_dir)
        if dataset.manifest["protocol"] == protocol.to_dict():
            # The index is a function of the shards and the protocol: nothing to redo (a rerun after a crash
            # that happened after the commit only had leftovers to clean, done on entering the writer).
            return {"dataset": str(dataset_dir), "protocol": protocol.to_dict(),
                    "samples": dataset.manifest["totals"]["samples"], "unchanged": True}
        metas = log_metas(dataset.logs())
        report_total(progress, len(metas))
        parts = []
        reasons: list[str] = []
        for path in dataset.shard_paths:
            tracks = read_table(path)
            codes = TrackCodes.of(tracks) if tracks.num_rows else None
            parts.append(build_samples(tracks, metas, protocol, codes))
            reasons += no_sample_reasons(tracks, protocol, parts[-1], codes).values()
            if progress:
                progress(int(dataset.manifest["shards"][len(parts) - 1]["logs"]))
        samples = pa.concat_tables(parts) if parts else arrow_schema("samples").empty_table()
        writer.commit_index(samples, protocol)
    return {"dataset": str(dataset_dir), "protocol": protocol.to_dict(), "samples": samples.num_rows,
            "logs_without_samples": reason_counts(reasons)}
