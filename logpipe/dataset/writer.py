"""The write side of a dataset folder (the read side is ``logpipe.dataset.reader.Dataset``): its manifest as typed
records, and the two commits a dataset knows: new shards (``logpipe ingest``) and a new sample index
(``logpipe index``). Both go through ``logpipe.storage.artifact``: locked folder, new generation's files, one
manifest swap.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TypedDict, cast

import pyarrow as pa
import pyarrow.compute as pc

from logpipe import __version__
from logpipe.contracts import arrow_schema, decode_dictionaries, encode_dictionaries, schema_version, value_schema
from logpipe.dataset.reader import (
    DATASET_ARTIFACT,
    DATASET_LEGACY_KEYS,
    DATASET_OWNED,
    MAPS_DIR,
    MCAP_DIR,
    SAMPLES_DIR,
    table_file,
)
from logpipe.errors import DatasetError
from logpipe.storage.artifact import FileEntry, FolderWriter, file_entry
from logpipe.storage.durability import crash_point
from logpipe.storage.io import parquet_options, read_table, write_parquet
from logpipe.storage.safe_paths import real_folder
from logpipe.types import SampleProtocol, SourceFile

SCHEMAS = ("tracks", "logs", "samples")
"""The contracts a dataset's tables follow; their versions are part of the manifest."""


class ShardEntry(TypedDict):
    """A track shard: its file (relative to the dataset), rows, sha256 and number of logs."""

    file: str
    rows: int
    sha256: str
    logs: int


class TableEntry(TypedDict):
    """The current file of the logs or samples table."""

    file: str
    rows: int
    sha256: str


class InputEntry(TypedDict):
    """An ingested input file: path relative to its root, sha256, size in bytes, folder memberships."""

    path: str
    sha256: str
    bytes: int
    memberships: list[str]


class QuarantineEntry(TypedDict):
    """An input refused with ``--on-error skip``: what ``InputEntry`` has plus the error (file, line, field,
    reason)."""

    path: str
    sha256: str
    bytes: int
    error: dict[str, object]


class Totals(TypedDict):
    logs: int
    rows: int
    samples: int
    inputs: int
    quarantined: int


class DatasetManifest(TypedDict):
    """``manifest.json`` of a dataset (``logpipe.storage.artifact`` adds ``artifact``, ``owns`` and ``checksum``)."""

    logpipe_version: str
    schemas: dict[str, str]
    format: str
    protocol: dict[str, Any]
    input_roots: list[str]
    inputs: list[InputEntry]
    quarantined: list[QuarantineEntry]
    shards: list[ShardEntry]
    tables: dict[str, TableEntry]
    totals: Totals
    generation: int
    files: dict[str, FileEntry]


@dataclass
class NewShard:
    """What one batch of inputs adds: its shard (None when no input had rows), logs and samples rows, the
    inputs it took and refused, and the entries of the files it wrote into the staging folder."""

    shard: ShardEntry | None
    logs: pa.Table
    samples: pa.Table
    inputs: list[InputEntry]
    quarantined: list[QuarantineEntry]
    files: dict[str, FileEntry]


class DatasetWriter(FolderWriter):
    """Writes a dataset folder. Use as a context manager: entering locks the folder and cleans what no commit
    names; ``manifest`` is the committed state (None for a new folder).

    Attributes:
        root: the dataset folder.
    """

    ownership = DATASET_OWNED
    kind = DATASET_ARTIFACT
    legacy_keys = DATASET_LEGACY_KEYS

    @property
    def manifest(self) -> DatasetManifest | None:
        return cast(DatasetManifest | None, self._writer.manifest)

    def staging(self) -> Path:
        """A staging folder for workers' shards and MCAPs (removed by the next writer if never committed)."""
        return self._writer.staging()

    def start(self, fmt: str, protocol: SampleProtocol) -> DatasetManifest:
        """The manifest new shards extend: the committed one, or an empty one for a new folder.

        Raises:
            DatasetError: the folder holds a dataset of another format, protocol or schema versions.
        """
        committed = self.manifest
        if committed is None:
            return DatasetManifest(
                logpipe_version=__version__, schemas={name: schema_version(name) for name in SCHEMAS}, format=fmt,
                protocol=protocol.to_dict(), input_roots=[], inputs=[], quarantined=[], shards=[], tables={},
                totals=Totals(logs=0, rows=0, samples=0, inputs=0, quarantined=0), generation=0, files={})
        if "format" not in committed or "protocol" not in committed:
            raise DatasetError(f"{self.root}: holds a manifest.json that is not a logpipe dataset's")
        manifest = cast(DatasetManifest, {**committed, "files": dict(committed.get("files", {}))})
        problems = []
        if manifest["format"] != fmt:
            problems.append(f"format {manifest['format']!r} (now {fmt!r})")
        if manifest["protocol"] != protocol.to_dict():
            problems.append(f"protocol {manifest['protocol']} (now {protocol.to_dict()})")
        versions = {name: schema_version(name) for name in SCHEMAS}
        if manifest["schemas"] != versions:
            problems.append(f"schema versions {manifest['schemas']} (now {versions})")
        if problems:
            raise DatasetError(f"{self.root}: existing dataset was written with " + "; ".join(problems)
                               + ". Ingest into a new folder (or `logpipe index` to change the protocol).")
        return manifest

    def commit_shards(self, manifest: DatasetManifest, batches: Sequence[NewShard], staging: Path) -> None:
        """Move the batches' shards and MCAPs from ``staging`` into place, write the new generation's logs and
        samples tables, and swap the manifest.

        Raises:
            DatasetError: a log id of the batches is already in the dataset (or twice among them).
        """
        out = self.root
        tables = manifest["tables"]
        # As values: the committed file may be of an older writer (strings), the batches' dictionaries differ.
        old_logs = [read_table(out / tables["logs"]["file"])] if "logs" in tables else []
        new_logs = [b.logs for b in batches if b.logs.num_rows]
        all_logs = pa.concat_tables([decode_dictionaries(t) for t in old_logs + new_logs]) if old_logs or new_logs \
            else value_schema(arrow_schema("logs")).empty_table()
        _refuse_log_id_clash(all_logs)
        files = dict(manifest["files"])
        for batch in batches:
            if batch.shard is not None:
                if "/" in batch.shard["file"]:
                    real_folder(out, batch.shard["file"].rpartition("/")[0])
                crash_point(f"move {batch.shard['file']}")
                (staging / batch.shard["file"]).replace(out / batch.shard["file"])
                manifest["shards"].append(batch.shard)
            files.update(batch.files)
        for per_log in (MCAP_DIR, MAPS_DIR):
            if (staging / per_log).is_dir():
                real_folder(out, per_log)  # never moved through a link to outside the dataset
                for folder in sorted((staging / per_log).iterdir()):  # one rename per shard, not per log
                    crash_point(f"move {per_log}/{folder.name}")
                    folder.replace(out / per_log / folder.name)
        old_samples = [read_table(out / tables["samples"]["file"])] if "samples" in tables else []
        all_samples = pa.concat_tables([decode_dictionaries(t) for t in old_samples + [b.samples for b in batches]])
        generation = int(manifest.get("generation", 0)) + 1
        new_tables: dict[str, TableEntry] = {}
        for name, table in (("logs", all_logs), ("samples", all_samples)):
            if name in tables:
                files.pop(tables[name]["file"], None)
            new_tables[name] = self._write_table(name, table, generation, files)
        for batch in batches:
            manifest["inputs"].extend(batch.inputs)
            manifest["quarantined"].extend(batch.quarantined)
        manifest["tables"] = new_tables
        manifest["generation"] = generation
        manifest["files"] = files
        manifest["totals"] = Totals(
            logs=all_logs.num_rows, rows=sum(s["rows"] for s in manifest["shards"]), samples=all_samples.num_rows,
            inputs=len(manifest["inputs"]), quarantined=len(manifest["quarantined"]))
        self._writer.commit(dict(manifest))

    def commit_index(self, samples: pa.Table, protocol: SampleProtocol) -> None:
        """Make ``samples`` (built with ``protocol`` from this dataset's shards) the sample index."""
        committed = self.manifest
        if committed is None:
            raise DatasetError(f"{self.root}: not a logpipe dataset (no manifest.json); run `logpipe ingest` first")
        manifest = cast(DatasetManifest, dict(committed))
        files = dict(manifest.get("files", {}))
        tables = manifest["tables"]
        files.pop(tables["samples"]["file"], None)
        if tables["logs"]["file"] not in files:
            # A dataset of the previous layout: name its files so the commit keeps them.
            for rel in [tables["logs"]["file"], *(s["file"] for s in manifest["shards"])]:
                files[rel] = file_entry(self.root / rel)
        generation = int(manifest.get("generation", 0)) + 1
        manifest["tables"] = {**tables, "samples": self._write_table("samples", samples, generation, files)}
        manifest["protocol"] = protocol.to_dict()
        manifest["totals"] = Totals(**{**manifest["totals"], "samples": samples.num_rows})
        manifest["generation"] = generation
        manifest["files"] = files
        self._writer.commit(dict(manifest))

    def _write_table(self, name: str, table: pa.Table, generation: int, files: dict[str, FileEntry]) -> TableEntry:
        """Write ``table`` as the generation's file of table ``name`` (``logs`` or ``samples``, also its folder)
        and add it to ``files``."""
        rel = table_file(name if name != "samples" else SAMPLES_DIR, generation)
        write_parquet(encode_dictionaries(table, arrow_schema(name)), self.root / rel)
        files[rel] = file_entry(self.root / rel, rows=table.num_rows)
        return TableEntry(file=rel, rows=table.num_rows, sha256=files[rel]["sha256"])


def write_track_shard(tracks: pa.Table, path: Path) -> FileEntry:
    """Write one ingest batch's track rows (canonical order, ``logpipe.dataset.log_table``) as the shard ``path``
    (in ingest's staging folder); returns its file entry (sha256, rows)."""
    # Statistics on log_id (readers filter shards by log) but not on the other strings, and LZ4: the
    # shard is written once per input and read by every later stage; LZ4 costs ~20% less to write than
    # zstd-1 here and decodes faster, for ~4% more bytes (Argoverse shards).
    options = parquet_options(tracks.schema, string_statistics=["log_id"]) | {"compression": "lz4"}
    options.pop("compression_level", None)
    write_parquet(tracks, path, options, dictionaries_as_values=True)
    return file_entry(path, rows=tracks.num_rows)


def known_input_sizes(manifest: DatasetManifest) -> set[int] | None:
    """Sizes (bytes) of every input the dataset already holds or quarantined; None when a quarantine entry
    predates recording sizes (then every new input is hashed before the skip check)."""
    entries = [*manifest["inputs"], *manifest["quarantined"]]
    if any("bytes" not in e for e in entries):
        return None
    return {int(e["bytes"]) for e in entries}


def known_input_digests(manifest: DatasetManifest) -> set[str]:
    """sha256 of every input the dataset already holds or quarantined (a rerun skips those)."""
    return {i["sha256"] for i in manifest["inputs"]} | {q["sha256"] for q in manifest["quarantined"]}


def release_quarantined(manifest: DatasetManifest, sources: Sequence[SourceFile]) -> int:
    """Drop from ``manifest`` the quarantine entries of ``sources`` so this run reads them again (``ingest
    --retry-quarantined``, after fixing an input or its mapping); returns how many. Still bad, they are
    quarantined again; nothing changes on disk before the run commits."""
    again = {s.sha256 for s in sources}
    kept = [q for q in manifest["quarantined"] if q["sha256"] not in again]
    released = len(manifest["quarantined"]) - len(kept)
    manifest["quarantined"] = kept
    return released


def add_input_roots(manifest: DatasetManifest, roots: Sequence[Path]) -> None:
    """Record in ``manifest`` the (resolved) folders and files the inputs were found under, once each, so later
    stages (predict copies bag channels through) can find the originals."""
    known_roots = manifest.setdefault("input_roots", [])
    for root in roots:
        if str(root.resolve()) not in known_roots:
            known_roots.append(str(root.resolve()))


def _refuse_log_id_clash(logs: pa.Table) -> None:
    # Arrow kernels on Arrow values only: a first conversion from numpy or Python (a numpy view, a Python 1
    # in a comparison) would make pyarrow import pandas, ~1 s of CPU, where no work is left to overlap it.
    counts = pc.value_counts(logs.column("log_id"))
    if logs.num_rows and pc.max(counts.field("counts")).as_py() > 1:
        clash = next(v["values"] for v in counts.to_pylist() if v["counts"] > 1)
        sources = logs.filter(pc.equal(logs.column("log_id"), clash)).column("source_file").to_pylist()
        raise DatasetError(f"log id {clash!r} comes from different inputs {sources}: ingest them into separate "
                           "datasets (log ids are file stems)")
