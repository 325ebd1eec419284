"""The on-disk dataset written by ``logpipe ingest``: its layout, its writer's ownership rule and its reader.

Layout::

    DATASET/
      manifest.json                    the commit point (``logpipe.storage.artifact``): versions, inputs (sha256),
                                       quarantined inputs, shards, tables, protocol, and every file's
                                       bytes / sha256 / rows
      tracks/part-00000.parquet        track-table shards, whole logs each, sorted by log, time, track
      logs/logs-NNNNN.parquet          one row per log (schemas/logs.json); NNNNN = the commit's generation
      samples/samples-NNNNN.parquet    the prediction-sample index (schemas/samples.json)
      mcap/part-NNNNN/<log_id>.mcap    each log for a viewer, grouped like the shards
      maps/part-NNNNN/<log_id>.parquet the log's own map store (schemas/map.json), for formats whose inputs carry
                                       their map (CommonRoad); ``rasterise`` uses it without ``--maps``
      rasters/<run>/                   raster runs: artifacts of their own (``logpipe rasterise``)

Only what the manifest names is read, so files of an interrupted run are never seen; every commit writes
its tables under a new generation's name, so a reader holding the previous manifest reads a consistent state.
Datasets written before this layout (``part-*.parquet``, ``logs.parquet`` at the top) are read the same way:
the manifest names their files.

Each table folder holds that table only, so engines read one table with one glob
(``read_parquet('DATASET/samples/*.parquet')`` in DuckDB, ``pl.scan_parquet``, ``pyarrow.dataset.dataset``).
Ids and labels are plain strings in every table (tracks, logs, samples, and a prediction run's predictions), so
the natural joins work in DuckDB, Polars and pandas without a cast. Tables written by earlier versions stored the
logs' and samples' ids as dictionaries (``dictionary<int32,string>``, Polars: Categorical); ``Dataset`` hands every
table to logpipe's stages as plain strings either way (``decode_dictionaries``).
"""

from __future__ import annotations

import hashlib
import re
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path
from typing import Any

import pyarrow as pa

from logpipe.contracts import decode_dictionaries
from logpipe.dataset.locations import track_sharing_groups
from logpipe.dataset.shards import log_slices
from logpipe.dataset.windows import LogWindows
from logpipe.errors import DatasetError
from logpipe.storage.artifact import MANIFEST, Ownership, check_files, read_manifest
from logpipe.storage.io import read_table
from logpipe.types import SampleProtocol, SceneSample

TRACKS_DIR = "tracks"
LOGS_DIR = "logs"
SAMPLES_DIR = "samples"
MCAP_DIR = "mcap"
MAPS_DIR = "maps"
DATASET_ARTIFACT = "dataset"
"""``manifest.json`` ``artifact`` value of a dataset folder."""
DATASET_OWNED = Ownership([f"{TRACKS_DIR}/", f"{LOGS_DIR}/", f"{SAMPLES_DIR}/", f"{MCAP_DIR}/", f"{MAPS_DIR}/",
                           "part-?????.parquet", "logs.parquet", "samples.parquet"])
"""A dataset's own files: the table and MCAP folders, and the top-level files of the previous layout; never
``rasters/`` (raster runs are artifacts of their own)."""
DATASET_LEGACY_KEYS = ("format", "shards", "tables")
"""Keys of a dataset manifest written before manifests named their kind (``artifact``)."""


def table_file(table: str, generation: int) -> str:
    """``logs/logs-NNNNN.parquet`` / ``samples/samples-NNNNN.parquet`` of a commit generation (``table`` is
    also the folder name: ``LOGS_DIR``, ``SAMPLES_DIR``)."""
    return f"{table}/{table}-{generation:05d}.parquet"


HASH_SPLITS = {"train": (0.0, 0.7), "val": (0.7, 0.85), "test": (0.85, 1.0)}
"""``hash/<split>``: a fixed split by log for datasets whose folders carry none (share of logs per split)."""


def hash_fraction(log_id: str) -> float:
    """Position of a log in [0, 1) from the sha256 of its id: stable across runs, machines and datasets."""
    return int(hashlib.sha256(log_id.encode()).hexdigest()[:12], 16) / float(1 << 48)


def shard_name(index: int) -> str:
    """``tracks/part-NNNNN.parquet``."""
    return f"{TRACKS_DIR}/part-{index:05d}.parquet"


def shard_number(shard: str) -> int:
    """NNNNN of ``[tracks/]part-NNNNN.parquet``."""
    return int(Path(shard).name[5:10])


def mcap_folder(shard: str) -> str:
    """``mcap/part-NNNNN``: the MCAP files of one shard's logs (moved into place as one folder)."""
    return f"{MCAP_DIR}/{Path(shard).name.removesuffix('.parquet')}"


def maps_folder(shard: str) -> str:
    """``maps/part-NNNNN``: the map stores of one shard's logs that carry their own map."""
    return f"{MAPS_DIR}/{Path(shard).name.removesuffix('.parquet')}"


_SPLIT_OPERATOR = re.compile(r"([+-])")
"""Joins split terms: ``+`` union, ``-`` difference (see ``Dataset.logs_in_split``)."""


def is_split_expression(split: str) -> bool:
    """Whether ``split`` joins several terms with ``+`` or ``-``."""
    return _SPLIT_OPERATOR.search(split) is not None


@dataclass
class Dataset:
    """An ingested dataset folder (read-only view).

    Attributes:
        root: the folder.
        manifest: parsed ``manifest.json``.
    """

    root: Path
    manifest: dict[str, Any]

    @classmethod
    def open(cls, root: Path) -> Dataset:
        """Open ``root`` at its committed state, checking that every file it names is there whole (by size).

        Raises:
            DatasetError: no manifest, a damaged one, or a committed file missing or truncated.
        """
        root = Path(root)
        if not (root / MANIFEST).is_file():
            raise DatasetError(f"{root}: not a logpipe dataset (no {MANIFEST}); run `logpipe ingest` first")
        manifest = read_manifest(root)
        assert manifest is not None
        for key in ("format", "protocol", "shards", "tables"):
            if key not in manifest:
                raise DatasetError(f"{root / MANIFEST}: damaged manifest (no {key!r})")
        # The tables and shards every reader opens; not the one MCAP (or map) per log, which only viewers,
        # predict's copy and rasterise read (stat-ing 50k of them would make every open slow).
        check_files(root, {rel: e for rel, e in manifest.get("files", {}).items()
                           if not rel.startswith((f"{MCAP_DIR}/", f"{MAPS_DIR}/"))})
        return cls(root, manifest)

    def _table_path(self, table: str) -> Path:
        entry = self.manifest["tables"].get(table)
        if entry is None:
            raise DatasetError(f"{self.root / MANIFEST}: names no {table} table")
        return self.root / str(entry["file"])

    def without_inputs(self) -> Dataset:
        """This dataset with its manifest's list of input files left out (most of a large corpus's manifest, ~140
        bytes a log): what workers that only read shards need shipped to them."""
        return Dataset(self.root, {k: v for k, v in self.manifest.items() if k != "inputs"})

    @property
    def protocol(self) -> SampleProtocol:
        """The sample protocol the index was built with."""
        return SampleProtocol(**self.manifest["protocol"])

    @property
    def kind(self) -> str:
        """The input format (``argoverse1``, ``ethucy``, ...): what a checkpoint is matched against."""
        return str(self.manifest["format"])

    @property
    def shard_paths(self) -> list[Path]:
        """Shards listed in the manifest, in order."""
        return [self.root / s["file"] for s in self.manifest["shards"]]

    def logs(self) -> pa.Table:
        """The logs table, ids and labels as strings."""
        return decode_dictionaries(read_table(self._table_path("logs")))

    def logs_in_split(self, split: str) -> list[str]:
        """Log ids of a split, in log-table order.

        A split is a folder membership (``eth/train``, from the ETH/UCY layout), ``hash/train``, ``hash/val``,
        ``hash/test`` (70/15/15 by log, see ``HASH_SPLITS``; logs that share tracks go together, by the hash of
        their group's first log), ``all`` or a log id; or such terms joined by ``+``
        (union) and ``-`` (difference), read left to right. A split that is exactly one log id or membership is
        that term even when it contains a ``-`` (CommonRoad ids do); in a longer expression such ids cannot be
        named. ``eth/train-biwi_hotel_train`` is the ETH fold's
        training logs without the HOTEL recording, so a whole scene can be held out for validation
        (``biwi_hotel_train+biwi_hotel_val``).

        Raises:
            DatasetError: a term names no log, or the split has none.
        """
        logs = self.logs()
        ids = logs.column("log_id").to_pylist()
        memberships = logs.column("memberships").to_pylist()
        groups = track_sharing_groups(ids, logs.column("attributes").to_pylist())
        # A whole log id or membership is one term even with a - in it (CommonRoad ids: USA_Peach-4_8_T-1).
        whole = self._term_logs(split.strip(), ids, memberships, groups)
        parts = [split.strip()] if whole else _SPLIT_OPERATOR.split(split.strip())
        chosen: set[str] = set()
        for i in range(0, len(parts), 2):
            term = parts[i].strip()
            picked = self._term_logs(term, ids, memberships, groups)
            if not picked:
                known = sorted({m for ms in memberships for m in ms})
                raise DatasetError(f"{self.root}: no log in split {term!r}"
                                   + (f" (of {split!r})" if term != split else "") + "; splits here: "
                                   + ", ".join(known + [f"hash/{k}" for k in HASH_SPLITS])
                                   + ", all, a log id, or terms joined by + and -")
            chosen = chosen - picked if i and parts[i - 1] == "-" else chosen | picked
        if not chosen:
            raise DatasetError(f"{self.root}: split {split!r} leaves no log")
        return [i for i in ids if i in chosen]

    @staticmethod
    def _term_logs(term: str, ids: list[str], memberships: list[list[str]], groups: dict[str, str]) -> set[str]:
        """Log ids of one split term (membership, ``hash/...`` by ``groups``, ``all`` or a log id)."""
        if term == "all":
            return set(ids)
        if term.startswith("hash/") and term[5:] in HASH_SPLITS:
            lo, hi = HASH_SPLITS[term[5:]]
            return {i for i in ids if lo <= hash_fraction(groups[i]) < hi}
        return {i for i, m in zip(ids, memberships, strict=True) if term in m or term == i}

    def samples(self) -> pa.Table:
        """The sample index, ids as strings."""
        return decode_dictionaries(read_table(self._table_path("samples")))

    def tracks(self, columns: list[str] | None = None) -> pa.Table:
        """All track rows (fine for ETH/UCY-sized data; stream with ``iter_logs`` for large sets)."""
        tables = [read_table(p, columns=columns) for p in self.shard_paths]
        if not tables:
            raise DatasetError(f"{self.root}: dataset has no shards")
        return pa.concat_tables(tables)

    @cached_property
    def _shard_of_log(self) -> dict[str, str]:
        logs = decode_dictionaries(read_table(self._table_path("logs"), columns=["log_id", "shard"]))
        return dict(zip(logs.column("log_id").to_pylist(), logs.column("shard").to_pylist(), strict=True))

    def own_maps(self) -> dict[str, Path]:
        """The map store of each log whose input carried its map (``maps/part-NNNNN/<log_id>.parquet``), by log id."""
        return {Path(rel).stem: self.root / rel for rel in self.manifest.get("files", {})
                if rel.startswith(f"{MAPS_DIR}/") and rel.endswith(".parquet")}

    def mcap_path(self, log_id: str) -> Path:
        """The MCAP file ingest wrote for ``log_id``."""
        shard = self._shard_of_log.get(log_id)
        if shard is None:
            raise DatasetError(f"{self.root}: no log {log_id!r}")
        return self.root / mcap_folder(shard) / f"{log_id}.mcap"

    def log_tracks(self, log_id: str) -> pa.Table:
        """Rows of one log, sorted by step (reads only its shard's matching row groups)."""
        shard = self._shard_of_log.get(log_id)
        if shard is None:
            raise DatasetError(f"{self.root}: no log {log_id!r}")
        return read_table(self.root / shard, filters=[("log_id", "=", log_id)])

    def iter_logs(
        self, shards: Sequence[Path] | None = None, log_ids: Sequence[str] | None = None
    ) -> Iterator[tuple[str, pa.Table]]:
        """(log_id, rows) for every log (of ``shards`` and among ``log_ids`` when given), one shard in memory
        at a time."""
        filters = [("log_id", "in", list(log_ids))] if log_ids is not None else None
        for path in self.shard_paths if shards is None else shards:
            table = read_table(path, filters=filters)
            if table.num_rows == 0:
                continue
            for log_id, (lo, hi) in log_slices(table).items():
                yield log_id, table.slice(lo, hi - lo)

    def iter_scene_samples(self, sample_filter: pa.compute.Expression | None = None) -> Iterator[SceneSample]:
        """``SceneSample``s for every sample (optionally filtered), grouped by log for one read per log."""
        samples = self.samples()
        if sample_filter is not None:
            samples = samples.filter(sample_filter)
        by_log: dict[str, list[dict[str, Any]]] = {}
        for row in samples.to_pylist():
            by_log.setdefault(row["log_id"], []).append(row)
        for log_id, tracks in self.iter_logs():
            for row in by_log.get(log_id, []):
                yield scene_sample(tracks, row, self.protocol)


def scene_sample(tracks: pa.Table, sample: dict[str, Any], protocol: SampleProtocol) -> SceneSample:
    """Cut one sample's window out of a log's rows: every agent seen in it, NaN where unobserved
    (``logpipe.dataset.windows.LogWindows``).

    Args:
        tracks: the log's rows (sorted by step).
        sample: a row of the sample index.
        protocol: gives ``obs_len``.
    """
    cached = _LAST_LOG[0] if _LAST_LOG else None  # a local reference: another thread may replace the entry
    if cached is None or cached[0] is not tracks:
        # Callers cut a log's samples one after another: convert the log's columns once, not per window.
        cached = (tracks, LogWindows(tracks))
        _LAST_LOG[:] = [cached]
    return cached[1].sample(sample, protocol.obs_len)


_LAST_LOG: list[tuple[pa.Table, LogWindows]] = []
"""The last log ``scene_sample`` cut (its table is held, so its identity cannot pass to another table)."""
