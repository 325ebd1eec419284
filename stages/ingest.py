"""``logpipe ingest``: input logs → canonical Parquet shards, logs table, sample index, MCAP per log.

Reads top-down: lock the folder, clean what no commit names → find, hash inputs, skip those already ingested → parse
batches in parallel (canonical row order, logs rows: ``logpipe.dataset.log_table``), each one shard (and MCAPs) in
staging → move shards into place, write the new tables → commit by the manifest swap (``logpipe.storage.artifact``):
a crash leaves the previous state, a rerun the same bytes. ``on_error="fail"``: the first bad input stops the run
and nothing becomes visible; ``"skip"``: bad inputs are quarantined (manifest and summary), the rest lands.
"""

from __future__ import annotations

import shutil
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Literal

import pyarrow as pa
import pyarrow.compute as pc

from logpipe.contracts import arrow_schema, decode_dictionaries
from logpipe.dataset.locations import annotate_shared, count_shared, dataset_shared_tracks, location_counts
from logpipe.dataset.log_table import canonical_order, log_rows
from logpipe.dataset.reader import maps_folder, mcap_folder, shard_name, shard_number
from logpipe.dataset.samples import TrackCodes, build_samples, no_sample_reasons, reason_counts
from logpipe.dataset.writer import (
    DatasetManifest,
    DatasetWriter,
    InputEntry,
    NewShard,
    QuarantineEntry,
    ShardEntry,
    add_input_roots,
    known_input_digests,
    known_input_sizes,
    release_quarantined,
    write_track_shard,
)
from logpipe.errors import SourceError
from logpipe.executor import Backend, default_workers, run_ordered, warm_up
from logpipe.formats import choose_format, get_adapter, other_format_inputs
from logpipe.formats.base import FormatAdapter
from logpipe.formats.input_copies import duplicate_inputs
from logpipe.formats.inputs import complete_hashes, find_inputs, fingerprint_inputs, read_ahead, unhashed_inputs
from logpipe.progress import report_total
from logpipe.storage.artifact import FileEntry, output_errors
from logpipe.storage.io import read_table
from logpipe.types import SampleProtocol, SourceFile

OnError = Literal["fail", "skip"]


@dataclass
class IngestOptions:
    """What ``ingest`` does.

    Attributes:
        out: dataset folder (created if missing; reruns add only new inputs).
        format: adapter name, or None to detect it from the inputs.
        protocol: sample windows; None = the format's default preset.
        on_error: ``fail`` (nothing written) or ``skip`` (quarantine bad inputs); ``retry_quarantined``: read again
            the given inputs an earlier run quarantined (``release_quarantined``).
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
    retry_quarantined: bool = False


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
    """Why each log of the batch that gives no sample gives none (``dataset.samples.no_sample_reasons``)."""
    warnings: list[str] = field(default_factory=list)  # inputs whose damage could not be found (no CRCs)


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
        # Several batches likely: start the workers' imports (~0.5 s of a core each) to overlap discovery and hashing.
        warm_up(_ingest_batch, workers=options.workers, backend=options.backend)
    fmt, added = choose_format(roots, options.format)  # a folder of bags and MCAP files: one ROS dataset
    options = replace(options, adapter_options={**options.adapter_options, **added})
    adapter = get_adapter(fmt, **options.adapter_options)
    protocol = options.protocol or adapter.default_protocol
    with output_errors(), DatasetWriter(options.out) as writer:
        return _ingest_locked(writer, roots, options, fmt, adapter, protocol, progress, started)


def _ingest_locked(writer: DatasetWriter, roots: Sequence[Path], options: IngestOptions, fmt: str,
                   adapter: FormatAdapter, protocol: SampleProtocol, progress: Callable[[int], None] | None,
                   started: float) -> dict[str, Any]:
    """``ingest`` while holding the dataset folder's lock."""
    default_batch = adapter.batch_files
    manifest = writer.start(fmt, protocol)
    found = find_inputs(roots, adapter)
    known_sizes = known_input_sizes(manifest)
    # A first ingest hashes nothing up front when twins are unlikely; a run that finds some is redone below.
    optimistic = unhashed_inputs(found) if known_sizes == set() else None
    sources = optimistic or fingerprint_inputs(found, known_sizes, threads=default_workers())
    add_input_roots(manifest, roots)
    retried = release_quarantined(manifest, sources) if options.retry_quarantined else 0
    known = known_input_digests(manifest)
    new = [s for s in sources if s.sha256 not in known]
    summary: dict[str, Any] = {
        "dataset": str(options.out), "format": fmt, "protocol": protocol.to_dict(), "inputs_found": len(sources),
        "inputs_skipped_already_ingested": len(sources) - len(new), "inputs_ingested": 0, "quarantined": [],
        "logs": 0, "rows": 0, "samples": 0, "shards_written": [], "logs_without_samples": {},
        "inputs_retried": retried, "skipped_inputs": other_format_inputs(roots, [p for p, _ in found], fmt)}
    if new and not _ingest_new(writer, new, manifest, fmt, default_batch, protocol, options, summary, progress,
                               reject_twins=optimistic is not None):
        new = sources = fingerprint_inputs(found, known_sizes, threads=default_workers())  # merges the twins found
        summary["inputs_found"] = len(new)
        _ingest_new(writer, new, manifest, fmt, default_batch, protocol, options, summary, progress)
    copies = duplicate_inputs(found, sources)
    summary.update(duplicates=len(copies), duplicate_inputs=copies)
    summary["seconds"] = round(time.perf_counter() - started, 3)
    summary["totals"] = manifest["totals"]
    return summary


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
    tracks = canonical_order(parsed.tracks)
    # The adapter's codes describe its row order, which a re-sort would break.
    codes = parsed.codes if presorted and parsed.codes is not None else (
        TrackCodes.of(tracks) if tracks.num_rows else None)
    logs, empty = log_rows(tracks, parsed.logs, job.shard_file, codes)
    for meta in empty:
        error = SourceError(meta.source_file, "produced no track rows")
        if not job.keep_going:
            raise error
        failures.append((by_path[meta.source_file], error))
    failed = {s.relpath for s, _ in failures}
    ingested = [s for s in sources if s.relpath not in failed]
    if not tracks.num_rows:
        return _BatchResult(None, logs, arrow_schema("samples").empty_table(), ingested, failures, 0)
    staging = Path(job.staging)
    files = {job.shard_file: write_track_shard(tracks, staging / job.shard_file)}
    shard = ShardEntry(file=job.shard_file, rows=tracks.num_rows, sha256=files[job.shard_file]["sha256"],
                       logs=logs.num_rows)
    kept = [m for m in parsed.logs if m not in empty]
    samples = build_samples(tracks, kept, job.protocol, codes)
    no_samples = no_sample_reasons(tracks, job.protocol, samples, codes)
    messages = 0
    if job.write_mcap:
        # Imported here: the mcap writer's imports (~35 ms) are wasted on the --no-mcap path.
        from logpipe.mcap.tracks import write_log_mcap_files

        folder = mcap_folder(job.shard_file)
        written = write_log_mcap_files(tracks, kept, staging / folder, parsed.maps)
        messages = sum(n for n, _, _ in written.values())  # sizes and digests of the bytes written, not read back
        files |= {f"{folder}/{p.name}": {"bytes": b, "sha256": d} for p, (_, b, d) in sorted(written.items())}
    if parsed.maps:  # inputs that carry their map (CommonRoad): the dataset keeps it for rasterise
        from logpipe.maps.store import write_stores

        files |= write_stores({m.log_id: parsed.maps[m.log_id] for m in kept if m.log_id in parsed.maps}, staging,
                              maps_folder(job.shard_file))
    unchecked = [f"{m.source_file}: {m.attributes['unchecked']}" for m in kept if m.attributes.get("unchecked")]
    return _BatchResult(shard, logs, samples, ingested, failures, messages, files, no_samples, unchecked)


def _commit(writer: DatasetWriter, results: list[_BatchResult], manifest: DatasetManifest, staging: Path,
            summary: dict[str, Any]) -> None:
    """Commit the batches (``DatasetWriter.commit_shards``) and count them into ``summary``."""
    shared = _flag_shared_tracks(writer, manifest, results, staging)
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
    summary["warnings"] = [w for r in results for w in r.warnings]
    summary["inputs_ingested"] = sum(len(r.ingested) for r in results)
    summary["logs"] = sum(r.logs.num_rows for r in results)
    summary["rows"] = sum(r.shard["rows"] for r in results if r.shard)
    summary["samples"] = sum(r.samples.num_rows for r in results)
    summary["mcap_messages"] = sum(r.mcap_messages for r in results)
    summary["logs_without_samples"] = reason_counts(reason for r in results for reason in r.no_samples.values())
    if shared["tracks"]:
        summary["shared_tracks"] = shared
    tables = [pa.concat_tables([getattr(r, name) for r in results]) for name in ("logs", "samples")]
    if per_location := location_counts(*tables):
        summary["by_location"] = per_location


def _flag_shared_tracks(writer: DatasetWriter, manifest: DatasetManifest, results: list[_BatchResult],
                        staging: Path) -> dict[str, int]:
    """Record in the new logs' attributes the tracks they share with an earlier log of their location
    (``logpipe.dataset.locations``); returns the counts for the summary."""
    tables = manifest["tables"]
    old = [read_table(writer.root / tables["logs"]["file"])] if "logs" in tables else []
    # Only the three columns the search reads, as strings: the tables' dictionaries and list types differ.
    logs = pa.concat_tables([pa.table({c: pc.cast(decode_dictionaries(t).column(c), pa.string())
                                       for c in ("log_id", "attributes", "shard")})
                             for t in old + [r.logs for r in results]])
    files = {s["file"]: writer.root / s["file"] for s in manifest["shards"]}
    files |= {r.shard["file"]: staging / r.shard["file"] for r in results if r.shard is not None}
    shared = dataset_shared_tracks(logs, files)
    for result in results:
        result.logs = annotate_shared(result.logs, shared)
    new = {log_id for r in results for log_id in r.logs.column("log_id").to_pylist()}
    return count_shared({k: v for k, v in shared.items() if k in new})
