"""The columnar predict path (issue 35 item 3: constant velocity to Parquet, ``logpipe.prediction.columnar``)
writes the files the per-sample path writes, byte for byte, with the same counts; on real data, with row groups
and chunks cut mid-log so that every boundary is exercised."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest

import logpipe.stages.predict as stage
from logpipe.dataset.sample_filter import parse_filter
from logpipe.prediction import columnar, output
from logpipe.stages.ingest import IngestOptions, ingest

COUNTS = ("samples", "rows", "targets", "targets_unobserved", "samples_without_targets", "shards", "logs_selected")


@pytest.mark.parametrize(("name", "filters", "mcap", "predictor"), [
    ("ethucy", [], False, "cv"), ("argoverse1", [], False, "cv"), ("ethucy", ["type=pedestrian"], False, "cv"),
    ("argoverse1", ["type=cyclist"], False, "cv"), ("ethucy", [], True, "cv"), ("argoverse1", [], True, "cv"),
    ("argoverse1", [], False, "kalman"),
])
def test_columnar_path_writes_the_per_sample_bytes(folder_digests: Callable[[Path], dict[str, str]], bundled: Path,
                                                   tmp_path: Path, monkeypatch: pytest.MonkeyPatch, name: str,
                                                   filters: list[str], mcap: bool, predictor: str) -> None:
    ingest([bundled / name], IngestOptions(out=tmp_path / "d", workers=1, write_mcap=mcap))
    monkeypatch.setattr(output, "ROW_GROUP_ROWS", 1000)  # several row groups, cut inside samples
    monkeypatch.setattr(columnar, "CHUNK_SAMPLES", 7)
    chunks = 0
    real_chunk_rows = columnar.chunk_rows

    def counted(*args: Any, **kwargs: Any) -> Any:
        nonlocal chunks
        for chunk in real_chunk_rows(*args, **kwargs):
            chunks += 1
            yield chunk

    monkeypatch.setattr(columnar, "chunk_rows", counted)
    settings: dict[str, Any] = {"predictor": predictor, "write_mcap": mcap, "sample_filter": parse_filter(filters),
                                "batch_size": 5}
    fast = stage.predict_dataset(tmp_path / "d", tmp_path / "columnar", **settings)
    assert chunks > 0
    monkeypatch.setattr(stage, "track_predictor", lambda model: None)
    slow = stage.predict_dataset(tmp_path / "d", tmp_path / "per_sample", **settings)
    assert {k: fast[k] for k in COUNTS} == {k: slow[k] for k in COUNTS}
    assert folder_digests(tmp_path / "columnar") == folder_digests(tmp_path / "per_sample")
    if not filters or name == "ethucy":
        assert fast["rows"] > 0
    if mcap:  # every selected log has its MCAP, with the original copied
        assert fast["mcap_files"] == fast["logs_selected"] > 0 and fast["original_messages"] > 0


@pytest.mark.parametrize("mcap", [False, True])
def test_parallel_shard_jobs_write_the_sequential_bytes(folder_digests: Callable[[Path], dict[str, str]],
                                                        bundled: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                        mcap: bool) -> None:
    # One input file per shard: several shards, predicted by a process pool of two, then inline, then per sample.
    ingest([bundled / "ethucy"], IngestOptions(out=tmp_path / "d", workers=1, write_mcap=mcap, batch_files=1))
    settings: dict[str, Any] = {"predictor": "cv", "write_mcap": mcap}
    pooled = stage.predict_dataset(tmp_path / "d", tmp_path / "pooled", workers=2, **settings)
    assert pooled["shards"] >= 2 and pooled["rows"] > 0
    inline = stage.predict_dataset(tmp_path / "d", tmp_path / "inline", workers=1, **settings)
    monkeypatch.setattr(stage, "track_predictor", lambda model: None)
    slow = stage.predict_dataset(tmp_path / "d", tmp_path / "per_sample", **settings)
    assert {k: pooled[k] for k in COUNTS} == {k: inline[k] for k in COUNTS} == {k: slow[k] for k in COUNTS}
    assert (folder_digests(tmp_path / "pooled") == folder_digests(tmp_path / "inline")
            == folder_digests(tmp_path / "per_sample"))


@pytest.mark.parametrize("columnar_path", [True, False])
def test_a_log_filter_cuts_only_its_logs_rows_and_predicts_the_same(bundled: Path, tmp_path: Path,
                                                                    monkeypatch: pytest.MonkeyPatch,
                                                                    columnar_path: bool) -> None:
    """A run filtered to one log of a multi-log shard indexes only that log's track rows (on the columnar path, of
    only the columns it cuts from), and predicts that log exactly as the unfiltered run does."""
    import pyarrow.compute as pc
    import pyarrow.parquet as pq

    from logpipe.dataset.target_tracks import ShardTracks
    from logpipe.prediction import shard_jobs

    ingest([bundled / "ethucy"], IngestOptions(out=tmp_path / "d", workers=1, write_mcap=False))
    shard = next((tmp_path / "d" / "tracks").glob("*.parquet"))
    logs = pq.read_table(shard, columns=["log_id"]).column("log_id")
    assert len(pc.unique(logs)) >= 2  # the case worth testing: other logs share the shard
    chosen = pc.unique(logs)[0].as_py()
    started: list[tuple[tuple[str, ...], set[str], int]] = []  # per job: its logs, the logs of its rows, rows
    read_columns: list[list[str]] = []
    real_start = shard_jobs.ShardJob.start

    def spied(job: Any, *args: Any) -> Any:
        entry, tracks = real_start(job, *args)
        started.append((job.log_ids, set(tracks.column("log_id").to_pylist()), tracks.num_rows))
        read_columns.append(tracks.column_names)
        return entry, tracks

    monkeypatch.setattr(shard_jobs.ShardJob, "start", spied)
    if not columnar_path:
        monkeypatch.setattr(stage, "track_predictor", lambda model: None)
    settings: dict[str, Any] = {"predictor": "cv", "write_mcap": False}
    one = stage.predict_dataset(tmp_path / "d", tmp_path / "one", sample_filter=parse_filter([f"log={chosen}"]),
                                **settings)
    assert started == [((chosen,), {chosen}, int(pc.sum(pc.equal(logs, chosen)).as_py()))]
    # the columnar path reads only the columns it cuts from; the per-sample path's windows read them all
    assert read_columns[0] == (list(ShardTracks.COLUMNS) if columnar_path else pq.read_schema(shard).names)
    every = stage.predict_dataset(tmp_path / "d", tmp_path / "every", **settings)
    assert started[1][2] == len(logs)  # every log selected: the whole shard
    assert 0 < one["rows"] < every["rows"]

    def rows_of(run: Path) -> Any:
        table = pq.read_table(sorted((run / "predictions").glob("*.parquet")))
        return table.filter(pc.equal(table.column("log_id"), chosen)).to_pylist()

    assert rows_of(tmp_path / "one") == rows_of(tmp_path / "every")
