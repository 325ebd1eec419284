"""``logpipe ingest``: input logs → canonical Parquet shards, logs table, sample index, MCAP per log.

Reads top-down: lock the dataset folder and clean what no commit names → find and hash inputs → skip
those already ingested (by content) → parse batches in parallel, each batch one shard written to a staging
folder → move the shards into place, write the new generation's tables → commit by the manifest swap
(``logpipe.artifact``). A crash at any point leaves the previous state, and a rerun gives the same bytes.
With ``on_error="fail"`` the first bad input stops the run and nothing becomes visible; with ``"skip"``
bad inputs are quarantined (listed in the manifest and the summary) and the rest lands.
"""

from __future__ import annotations

import json
import shutil
import time
from collections import Counter
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Literal

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc

from logpipe.artifact import FileEntry, file_entry, output_errors
from logpipe.contracts import arrow_schema, conform, tracks_schema
from logpipe.dataset import mcap_folder, shard_name, shard_number
from logpipe.dataset_writer import DatasetManifest, DatasetWriter, InputEntry, NewShard, QuarantineEntry, ShardEntry
from logpipe.errors import DatasetError, SourceError
from logpipe.executor import Backend, default_workers, run_ordered, warm_up
from logpipe.formats import detect, get_adapter
from logpipe.formats.base import FormatAdapter
from logpipe.inputs import complete_hashes, find_inputs, fingerprint_inputs, read_ahead, unhashed_inputs
from logpipe.io import as_numpy, parquet_options, read_table, sha256_file, sha256_tree, write_parquet
from logpipe.progress import report_total
from logpipe.samples import TrackCodes, build_samples, no_sample_reasons, steps_from_sorted_times
from logpipe.shards import log_runs
from logpipe.types import PENDING_SHA256, LogMeta, NDArrayBool, NDArrayInt, Role, SampleProtocol, SourceFile

OnError = Literal["fail", "skip"]


@dataclass
class IngestOptions:
    """What ``ingest`` does.

    Attributes:
        out: dataset folder (created if missing; reruns add only new inputs).
        format: adapter name, or None to detect it from the inputs.
        protocol: sample windows; None = the format's default preset.
        on_error: ``fail`` (nothing written) or ``skip`` (quarantine bad inputs).
        write_mcap: also write ``mcap/<log_id>.mcap`` per log.
        workers: processes (0 = every core); ``backend="ray"`` runs batches as Ray tasks.
        batch_files: inputs per batch (= per shard); None = the adapter's default.
        adapter_options: passed to the adapter's constructor (e.g. ``hz``, ``mapping``).
    """

    out: Path
    format: str | None = None
    protocol: SampleProtocol | None = None
    on_error: OnError = "fail"
    write_mcap: bool = True
    workers: int = 0
    backend: Backend = "local"
    batch_files: int | None = None
    adapter_options: dict[str, Any] = field(default_factory=dict)


@dataclass
class _BatchJob:
    adapter: str
    adapter_options: dict[str, Any]
    sources: list[SourceFile]
    shard_file: str
    staging: str
    protocol: SampleProtocol
    keep_going: bool
    write_mcap: bool


@dataclass
class _BatchResult:
    shard: ShardEntry | None
    logs: pa.Table
    samples: pa.Table
    ingested: list[SourceFile]
    failures: list[tuple[SourceFile, SourceError]]
    mcap_messages: int
    files: dict[str, FileEntry] = field(default_factory=dict)
    """Entries of the files written into staging (paths relative to the dataset), hashed by the worker."""
    no_samples: dict[str, str] = field(default_factory=dict)
    """Why each log of the batch that gives no sample gives none (``samples.no_sample_reasons``)."""


def ingest(roots: Sequence[Path], options: IngestOptions,
           progress: Callable[[int], None] | None = None) -> dict[str, Any]:
    """Ingest ``roots`` into ``options.out``; returns the run summary (also what ``--json`` prints).

    Args:
        roots: input files or folders.
        options: see ``IngestOptions``.
        progress: called with the number of inputs each finished batch covered.

    Raises:
        SourceError: a bad input, with ``on_error="fail"``.
        DatasetError: the output folder holds a dataset of another format/protocol/schema, or log ids clash.
    """
    started = time.perf_counter()
    if any(root.is_dir() for root in roots):
        # A folder usually means several batches. When the workers cannot fork from this process, the
        # worker server's imports (~0.5 s of one core) then overlap detection, discovery and fingerprinting
        # instead of delaying the first batch. (Started once per process; a no-op with one worker.)
        warm_up(_ingest_batch, workers=options.workers, backend=options.backend)
    fmt = options.format or detect(roots[0])
    adapter = get_adapter(fmt, **options.adapter_options)
    protocol = options.protocol or adapter.default_protocol
    with output_errors(), DatasetWriter(options.out) as writer:
        return _ingest_locked(writer, roots, options, fmt, adapter, protocol, progress, started)


def _ingest_locked(writer: DatasetWriter, roots: Sequence[Path], options: IngestOptions, fmt: str,
                   adapter: FormatAdapter, protocol: SampleProtocol, progress: Callable[[int], None] | None,
                   started: float) -> dict[str, Any]:
    """``ingest`` while holding the dataset folder's lock."""
    default_batch = adapter.batch_files
    out = options.out
    manifest = writer.start(fmt, protocol)
    found = find_inputs(roots, adapter)
    known_sizes = _known_sizes(manifest)
    # A first ingest hashes nothing up front when twins are unlikely; a run that finds some is redone below.
    optimistic = unhashed_inputs(found) if known_sizes == set() else None
    sources = optimistic or fingerprint_inputs(found, known_sizes, threads=default_workers())
    # Where the inputs were, so later stages (predict copies bag channels through) can find the originals.
    known_roots = manifest.setdefault("input_roots", [])
    for root in roots:
        if str(root.resolve()) not in known_roots:
            known_roots.append(str(root.resolve()))
    known = {i["sha256"] for i in manifest["inputs"]} | {q["sha256"] for q in manifest["quarantined"]}
    new = [s for s in sources if s.sha256 not in known]
    summary: dict[str, Any] = {
        "dataset": str(out), "format": fmt, "protocol": protocol.to_dict(), "inputs_found": len(sources),
        "inputs_skipped_already_ingested": len(sources) - len(new), "inputs_ingested": 0, "quarantined": [],
        "logs": 0, "rows": 0, "samples": 0, "shards_written": [], "logs_without_samples": {},
    }
    if new and not _ingest_new(writer, new, manifest, fmt, default_batch, protocol, options, summary, progress,
                               reject_twins=optimistic is not None):
        new = sources = fingerprint_inputs(found, known_sizes, threads=default_workers())  # merges the twins found
        summary["inputs_found"] = len(new)
        _ingest_new(writer, new, manifest, fmt, default_batch, protocol, options, summary, progress)
    copies = duplicate_inputs(found, sources)
    summary["duplicates"] = len(copies)
    summary["duplicate_inputs"] = copies
    summary["seconds"] = round(time.perf_counter() - started, 3)
    summary["totals"] = manifest["totals"]
    return summary


def duplicate_inputs(found: Sequence[tuple[Path, str]], sources: Sequence[SourceFile]) -> list[dict[str, str]]:
    """``{"path", "same_as"}`` (relative paths) for every input found that ``fingerprint_inputs`` merged into
    an identical one it kept, so a summary can say why fewer inputs than files were ingested.

    The merge keeps no record of the copies; a copy is matched to the kept input of its size, and hashed again
    only when several kept inputs have that size or when it is a folder (a bag).
    """
    kept = {s.relpath for s in sources}
    copies = [(path, rel) for path, rel in found if rel not in kept]
    if not copies:
        return []
    by_size: dict[int, list[SourceFile]] = {}
    for s in sources:
        if s.sha256 != PENDING_SHA256:  # a pending digest means no other input could equal it
            by_size.setdefault(s.size, []).append(s)
    out = []
    for path, rel in copies:
        if path.is_dir():  # a bag folder: matched by its digest, which every folder input has
            digest = sha256_tree(path)
            candidates = [s for s in sources if s.sha256 == digest]
        else:
            candidates = by_size.get(path.stat().st_size, [])
            if len(candidates) != 1:
                digest = sha256_file(path)
                candidates = [s for s in candidates if s.sha256 == digest]
        out.append({"path": rel, "same_as": candidates[0].relpath if candidates else "?"})
    return out


def _ingest_new(  # noqa: PLR0913  ingest()'s run state handed on; options already in IngestOptions
    writer: DatasetWriter, new: list[SourceFile], manifest: DatasetManifest, fmt: str, default_batch: int,
    protocol: SampleProtocol, options: IngestOptions, summary: dict[str, Any],
    progress: Callable[[int], None] | None, *, reject_twins: bool = False,
) -> bool:
    """Ingest ``new`` and commit; with ``reject_twins``, commit nothing and return False when two inputs turn
    out to have equal contents (their digests were left to the workers)."""
    per_batch = options.batch_files or default_batch
    first_shard = 1 + max((shard_number(s["file"]) for s in manifest["shards"]), default=-1)
    report_total(progress, len(new))
    staging = writer.staging()
    jobs = [
        _BatchJob(fmt, options.adapter_options, new[i:i + per_batch], shard_name(first_shard + n), str(staging),
                  protocol, options.on_error == "skip", options.write_mcap)
        for n, i in enumerate(range(0, len(new), per_batch))
    ]
    try:
        results = []
        for result in run_ordered(_ingest_batch, jobs, workers=options.workers, backend=options.backend,
                                  queued=lambda job: read_ahead(job.sources)):
            results.append(result)
            if progress:
                progress(len(result.ingested) + len(result.failures))
        if reject_twins:
            digests = [s.sha256 for r in results for s in [*r.ingested, *(f for f, _ in r.failures)]]
            if len(set(digests)) < len(digests):
                return False
        _commit(writer, results, manifest, staging, summary)
        return True
    finally:
        shutil.rmtree(staging, ignore_errors=True)


def _ingest_batch(job: _BatchJob) -> _BatchResult:
    """Parse one batch and write its shard (and MCAPs) into the staging folder. Runs in a worker."""
    from logpipe.formats.base import read_isolating, refuse_unsafe_log_ids, regular_sources, source_of

    adapter = get_adapter(job.adapter, **job.adapter_options)
    # Irregular inputs (FIFO, device, dangling link) are refused before anything opens or hashes them.
    sources, failures = regular_sources(job.sources, job.keep_going)
    sources = sources if adapter.hashes_while_reading else complete_hashes(sources)
    parsed = refuse_unsafe_log_ids(read_isolating(adapter, sources, job.keep_going), job.keep_going)
    # The digests the adapter computed; inputs it failed on before logging them are hashed here.
    digests = {m.source_file: m.source_sha256 for m in parsed.logs}
    sources = complete_hashes([replace(s, sha256=digests.get(s.relpath, s.sha256)) for s in sources])
    by_path = {s.relpath: s for s in sources}
    failures += [(source_of(e.file, by_path), e) for e in parsed.failures]
    presorted = "step" in parsed.tracks.column_names
    tracks = _canonical_order(parsed.tracks)
    # The adapter's codes describe its row order, which a re-sort would break.
    codes = parsed.codes if presorted and parsed.codes is not None else (
        TrackCodes.of(tracks) if tracks.num_rows else None)
    logs, empty = _log_rows(tracks, parsed.logs, job.shard_file, codes)
    for meta in empty:
        error = SourceError(meta.source_file, "produced no track rows")
        if not job.keep_going:
            raise error
        failures.append((by_path[meta.source_file], error))
    staging = Path(job.staging)
    shard = None
    files: dict[str, FileEntry] = {}
    samples = arrow_schema("samples").empty_table()
    no_samples: dict[str, str] = {}
    messages = 0
    if tracks.num_rows:
        path = staging / job.shard_file
        # Statistics on log_id (readers filter shards by log) but not on the other strings, and LZ4: the
        # shard is written once per input and read by every later stage; LZ4 costs ~20% less to write than
        # zstd-1 here and decodes faster, for ~4% more bytes (Argoverse shards).
        options = parquet_options(tracks.schema, string_statistics=["log_id"]) | {"compression": "lz4"}
        options.pop("compression_level", None)
        write_parquet(tracks, path, options, dictionaries_as_values=True)
        files[job.shard_file] = file_entry(path, rows=tracks.num_rows)
        shard = ShardEntry(file=job.shard_file, rows=tracks.num_rows, sha256=files[job.shard_file]["sha256"],
                           logs=logs.num_rows)
        kept = [m for m in parsed.logs if m not in empty]
        samples = build_samples(tracks, kept, job.protocol, codes)
        no_samples = no_sample_reasons(tracks, job.protocol, samples, codes)
        if job.write_mcap:
            folder = mcap_folder(job.shard_file)
            messages = _write_mcaps(tracks, kept, staging / folder)
            for mcap in sorted((staging / folder).iterdir()):
                files[f"{folder}/{mcap.name}"] = file_entry(mcap)
    failed = {s.relpath for s, _ in failures}
    ingested = [s for s in sources if s.relpath not in failed]
    return _BatchResult(shard, logs, samples, ingested, failures, messages, files, no_samples)


def _canonical_order(tracks: pa.Table) -> pa.Table:
    """Rows sorted by log, time, track with ``step`` filled in, in the track-table schema.

    Adapters that return ``step`` promise this order already (the text adapters keep file order, which is
    by time), which saves a sort of millions of rows.
    """
    if "step" not in tracks.column_names:
        tracks = tracks.sort_by([("log_id", "ascending"), ("timestamp_ns", "ascending"),
                                 ("track_id", "ascending")])
        log_ids = as_numpy(pc.dictionary_encode(tracks.column("log_id")).combine_chunks().indices)

        steps = steps_from_sorted_times(as_numpy(tracks.column("timestamp_ns")), log_ids.astype(np.int64))
        tracks = tracks.append_column("step", pa.array(steps.astype(np.int32)))
    return conform(tracks, tracks_schema(), keep_dictionaries=True)


def _log_rows(
    tracks: pa.Table, metas: list[LogMeta], shard: str, codes: TrackCodes | None
) -> tuple[pa.Table, list[LogMeta]]:
    """The logs-table rows for ``metas`` (stats from ``tracks``), and the metas that have no rows.

    ``tracks`` is in canonical order (logs contiguous, time ascending), so every statistic is a slice
    boundary or a reduction over contiguous runs: no hashing group-by.
    """
    stats = _log_stats(tracks, codes) if codes is not None else {}
    kept = [m for m in metas if m.log_id in stats]
    empty = [m for m in metas if m.log_id not in stats]
    rows = [stats[m.log_id] for m in kept]
    # Column by column (one comprehension each): a per-log loop of appends costs as much as the statistics.
    columns: dict[str, list[Any]] = {
        "log_id": [m.log_id for m in kept],
        "source_format": [m.source_format for m in kept],
        "source_file": [m.source_file for m in kept],
        "source_sha256": [m.source_sha256 for m in kept],
        "map_id": [m.map_id for m in kept],
        "frame_rate_hz": [m.frame_rate_hz for m in kept],
        "memberships": [list(m.memberships) for m in kept],
        "attributes": [json.dumps(m.attributes, sort_keys=True) for m in kept],
        "shard": [shard] * len(kept),
    }
    for key in _STAT_KEYS:
        columns[key] = [row[key] for row in rows]
    return conform(pa.table({name: columns[name] for name in arrow_schema("logs").names}), arrow_schema("logs")), \
        empty


_STAT_KEYS = ("num_rows", "num_tracks", "num_steps", "start_ns", "end_ns", "median_dt_ns", "has_ego")


def _log_stats(tracks: pa.Table, codes: TrackCodes) -> dict[str, dict[str, Any]]:
    """Per-log row count, distinct tracks and steps, time span, median step and whether an ego exists."""
    logs, names, tracks_code = codes.log_code, codes.log_names, codes.track_code
    steps = as_numpy(tracks.column("step"))
    ts = as_numpy(tracks.column("timestamp_ns"))
    ego = _equals(tracks.column("role"), Role.EGO.value)
    starts, ends = log_runs(logs)
    distinct = _distinct_per_group(logs, tracks_code, len(names))
    egos = np.zeros(len(names), dtype=bool)
    egos[logs[ego]] = True
    first_of_step = np.flatnonzero(np.concatenate([[True], (steps[1:] != steps[:-1]) | (logs[1:] != logs[:-1])]))
    median_dt = _median_step(logs[first_of_step], ts[first_of_step], len(names))
    stats = {}
    for i, lo, hi in zip(logs[starts].tolist(), starts.tolist(), ends.tolist(), strict=True):
        stats[names[i]] = {
            "num_rows": hi - lo,
            "num_tracks": int(distinct[i]),
            "num_steps": int(steps[hi - 1]) + 1,
            "start_ns": int(ts[lo]),
            "end_ns": int(ts[hi - 1]),
            "median_dt_ns": int(median_dt[i]),
            "has_ego": bool(egos[i]),
        }
    return stats


def _equals(column: pa.ChunkedArray, value: str) -> NDArrayBool:
    """``column == value`` as numpy; for a dictionary column by its codes (no string compare per row)."""
    if pa.types.is_dictionary(column.type) and column.num_chunks == 1:
        encoded = column.chunk(0)
        matches = np.flatnonzero(as_numpy(pc.equal(encoded.dictionary, value)))
        found: NDArrayBool = np.isin(as_numpy(encoded.indices), matches)
        return found
    plain: NDArrayBool = as_numpy(pc.equal(column, value)).astype(bool)
    return plain


def _distinct_per_group(groups: NDArrayInt, codes: NDArrayInt, n_groups: int) -> NDArrayInt:
    """Number of distinct ``codes`` in each group: a presence table when it is small, else a sort."""
    n_codes = int(codes.max()) + 1 if len(codes) else 1
    if n_groups * n_codes <= 1 << 24:  # 16 MB of booleans: a scatter beats sorting every row
        seen = np.zeros((n_groups, n_codes), dtype=bool)
        seen[groups, codes] = True
        counts: NDArrayInt = seen.sum(axis=1)
        return counts
    pairs = np.unique(groups * n_codes + codes)
    return np.bincount(pairs // n_codes, minlength=n_groups)


def _median_step(step_logs: NDArrayInt, step_ts: NDArrayInt, n_logs: int) -> NDArrayInt:
    """Median gap between consecutive step timestamps of each log (0 for a one-step log), vectorised."""
    same = step_logs[1:] == step_logs[:-1]
    gaps, owners = np.diff(step_ts)[same], step_logs[1:][same]
    order = np.lexsort((gaps, owners))
    gaps, owners = gaps[order], owners[order]
    counts = np.bincount(owners, minlength=n_logs)
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    result = np.zeros(n_logs, dtype=np.int64)
    has = counts > 0
    lower = gaps[starts[has] + (counts[has] - 1) // 2]
    upper = gaps[starts[has] + counts[has] // 2]
    result[has] = (lower + upper) // 2  # the mean of the middle two for an even count, as np.median
    return result


def _write_mcaps(tracks: pa.Table, metas: list[LogMeta], folder: Path) -> int:
    # Log boundaries from the log codes (no string per row), every column converted once for the batch.
    logs = pc.dictionary_encode(tracks.column("log_id")).combine_chunks()
    codes, names = as_numpy(logs.indices), logs.dictionary.to_pylist()
    maps = {m.log_id: m.map_id for m in metas}
    # Imported here: the mcap writer's imports (~35 ms) are wasted on the --no-mcap path.
    from logpipe.mcapio import LogRows, write_log_mcap

    rows = LogRows.of(tracks)
    messages = 0
    starts, ends = log_runs(codes)
    for lo, hi in zip(starts.tolist(), ends.tolist(), strict=True):
        log_id = names[codes[lo]]
        messages += write_log_mcap(log_id, rows.slice(lo, hi), folder / f"{log_id}.mcap", maps.get(log_id))
    return messages


def _known_sizes(manifest: DatasetManifest) -> set[int] | None:
    """Sizes of every input the dataset already holds or quarantined; None when a quarantine entry predates
    recording sizes (then every new input is hashed before the skip check)."""
    entries = [*manifest["inputs"], *manifest["quarantined"]]
    if any("bytes" not in e for e in entries):
        return None
    return {int(e["bytes"]) for e in entries}


def _commit(writer: DatasetWriter, results: list[_BatchResult], manifest: DatasetManifest, staging: Path,
            summary: dict[str, Any]) -> None:
    """Commit the batches (``DatasetWriter.commit_shards``) and count them into ``summary``."""
    batches = [
        NewShard(
            shard=r.shard, logs=r.logs, samples=r.samples, files=r.files,
            inputs=[InputEntry(path=s.relpath, sha256=s.sha256, bytes=s.size, memberships=list(s.memberships))
                    for s in r.ingested],
            quarantined=[QuarantineEntry(path=s.relpath, sha256=s.sha256, bytes=s.size, error=e.to_dict())
                         for s, e in r.failures],
        )
        for r in results
    ]
    writer.commit_shards(manifest, batches, staging)
    summary["shards_written"] = [b.shard["file"] for b in batches if b.shard is not None]
    summary["quarantined"] = [q for b in batches for q in b.quarantined]
    summary["inputs_ingested"] = sum(len(r.ingested) for r in results)
    summary["logs"] = sum(r.logs.num_rows for r in results)
    summary["rows"] = sum(r.shard["rows"] for r in results if r.shard)
    summary["samples"] = sum(r.samples.num_rows for r in results)
    summary["mcap_messages"] = sum(r.mcap_messages for r in results)
    summary["logs_without_samples"] = _reason_counts(reason for r in results for reason in r.no_samples.values())


def _reason_counts(reasons: Iterable[str]) -> dict[str, int]:
    """How many logs give no sample for each reason, the most frequent first."""
    return dict(Counter(reasons).most_common())


def reindex(dataset_dir: Path, protocol: SampleProtocol,
            progress: Callable[[int], None] | None = None) -> dict[str, Any]:
    """Rebuild the sample index with ``protocol``, one shard in memory at a time, as one new commit;
    ``progress`` is called with the number of logs each shard held."""
    from logpipe.dataset import Dataset

    with output_errors(), DatasetWriter(dataset_dir) as writer:
        if writer.manifest is None:
            raise DatasetError(f"{dataset_dir}: not a logpipe dataset (no manifest.json); run `logpipe ingest` first")
        dataset = Dataset.open(dataset_dir)
        if dataset.manifest["protocol"] == protocol.to_dict():
            # The index is a function of the shards and the protocol: nothing to redo (a rerun after a crash
            # that happened after the commit only had leftovers to clean, done on entering the writer).
            return {"dataset": str(dataset_dir), "protocol": protocol.to_dict(),
                    "samples": dataset.manifest["totals"]["samples"], "unchanged": True}
        logs = dataset.logs()
        metas = [
            LogMeta(log_id=r["log_id"], source_format=r["source_format"], source_file=r["source_file"],
                    source_sha256=r["source_sha256"], map_id=r["map_id"], frame_rate_hz=r["frame_rate_hz"])
            for r in logs.select(["log_id", "source_format", "source_file", "source_sha256", "map_id",
                                  "frame_rate_hz"]).to_pylist()
        ]
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
            "logs_without_samples": _reason_counts(reasons)}
