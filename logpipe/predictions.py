"""The predictions table: its schema, its metadata, how it is built from forecasts and how it is read back.

Every producer (``logpipe predict``, the reproduction scripts, tests) and every reader (``logpipe score``, the
scripts) goes through this module, so the table's layout and its metadata keys are decided here only.

Layout (``schemas/predictions.json``): one row per (sample, target track, mode, future step), ordered sample
by sample, target by target (``target_mask`` order), mode 0..K-1, step 1..T. The table's Parquet metadata
holds ``PredictionMeta`` as JSON under ``logpipe.predictions``.

A prediction run folder (``logpipe predict --out``) is a committed artifact (``logpipe.artifact``)::

    manifest.json                   "artifact": "prediction_run", settings, metadata, finished shards, files
    predictions/part-NNNNN.parquet  this table, one file per dataset shard
    mcap/part-NNNNN/<log_id>.mcap   per-log MCAPs with prediction channels

``PredictionRun.open`` reads such a folder (only the files its manifest names) or a single table file.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from dataclasses import asdict, dataclass, fields
from pathlib import Path
from typing import Any, TypedDict

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
import pyarrow.parquet as pq

from logpipe import __version__
from logpipe.artifact import MANIFEST, FileEntry, FolderWriter, Ownership, check_files, read_manifest
from logpipe.contracts import arrow_schema
from logpipe.errors import DatasetError, LogpipeError
from logpipe.io import as_numpy
from logpipe.types import OBJECT_TYPES, NDArrayFloat, NDArrayInt, SceneSample

RUN_ARTIFACT = "prediction_run"
"""``manifest.json`` ``artifact`` value of a prediction run folder."""
RUN_FORMAT_VERSION = 1
PREDICTIONS_DIR = "predictions"
META_KEY = "logpipe.predictions"
"""Parquet schema-metadata key holding ``PredictionMeta`` as JSON."""
LEGACY_RUN_FILE = "predict.json"
"""Run state of prediction folders written before they were committed artifacts."""


class PredictionsError(LogpipeError):
    """A predictions table or run folder is missing, damaged or inconsistent with its metadata."""


@dataclass(frozen=True)
class PredictionMeta:
    """What a predictions table was made with: enough to score it without guessing.

    Attributes:
        predictor: method name (``zhu2020``, ``cv``, ...), also the ``predictor`` column.
        checkpoint_id: weights sha256 plus non-default inference settings, or the baseline with its parameters;
            also the ``checkpoint_id`` column.
        protocol: the sample protocol's name (``ethucy``, ``argoverse1``, ...), None when unknown.
        obs_len: observed steps of each window (0 when unknown: tables of older writers).
        pred_len: T, predicted steps (the horizon).
        num_modes: K, futures per target.
        checkpoint_sha256: the weights' sha256 alone (None for baselines).
        seed: the seed of every random draw (None when not recorded).
        dataset_manifest_sha256: sha256 of the dataset's ``manifest.json`` the forecasts were made on.
        noise_scale: std of the network's noise z (1 = as trained).
        constant_velocity_modes: modes held to constant velocity (None = the checkpoint's own).
        context_max_neighbours: neighbour cap of the context (None = all).
        logpipe_version: the writer's version.
    """

    predictor: str
    checkpoint_id: str
    protocol: str | None
    obs_len: int
    pred_len: int
    num_modes: int
    checkpoint_sha256: str | None = None
    seed: int | None = None
    dataset_manifest_sha256: str | None = None
    noise_scale: float = 1.0
    constant_velocity_modes: int | None = None
    context_max_neighbours: int | None = None
    logpipe_version: str = __version__

    def to_dict(self) -> dict[str, Any]:
        """The JSON form (manifest ``metadata``, Parquet ``logpipe.predictions``)."""
        return asdict(self)

    @classmethod
    def from_dict(cls, data: Any, where: str) -> PredictionMeta:
        """Parse the JSON form; unknown keys are ignored (a newer writer may add some).

        Raises:
            PredictionsError: not an object, or a required key is missing or of the wrong type.
        """
        if not isinstance(data, dict):
            raise PredictionsError(f"{where}: predictions metadata is not a JSON object")
        known = {f.name for f in fields(cls)}
        values = {k: v for k, v in data.items() if k in known}
        try:
            meta = cls(**values)
        except TypeError as exc:
            raise PredictionsError(f"{where}: predictions metadata incomplete ({exc})") from None
        ints = (meta.pred_len, meta.num_modes)
        if not all(isinstance(v, int) and v >= 1 for v in ints) or not isinstance(meta.obs_len, int) \
                or not isinstance(meta.predictor, str):
            raise PredictionsError(f"{where}: predictions metadata has bad lengths or names: {values}")
        return meta

    def schema(self) -> pa.Schema:
        """The contract schema with this metadata attached."""
        schema = arrow_schema("predictions")
        extra = {META_KEY.encode(): json.dumps(self.to_dict(), sort_keys=True).encode()}
        return schema.with_metadata({**(schema.metadata or {}), **extra})


# ---- building ------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class SampleForecast:
    """One sample's forecasts, the unit tables are built from.

    Attributes:
        log_id: the sample's log.
        sample_id: the sample-index id.
        track_ids: (N,) predicted targets.
        object_types: (N,) their normalised classes.
        futures: (N, K, T, 2) metres, world frame.
        scores: (N, K) mode scores, or None for uniform ones (predictors without scores).
        step_ns: (T,) times of the future steps.
    """

    log_id: str
    sample_id: str
    track_ids: Sequence[str]
    object_types: Sequence[str]
    futures: NDArrayFloat
    scores: NDArrayFloat | None
    step_ns: NDArrayInt


def build_table(meta: PredictionMeta, forecasts: Sequence[SampleForecast]) -> pa.Table:
    """The predictions rows of ``forecasts`` in the table's order, built column-wise (no per-row Python).

    Raises:
        PredictionsError: a forecast whose shape is not (N, K, T, 2) with the metadata's K and T.
    """
    schema = meta.schema()
    k, t = meta.num_modes, meta.pred_len
    done = [f for f in forecasts if len(f.track_ids)]
    for f in done:
        if f.futures.shape != (len(f.track_ids), k, t, 2):
            raise PredictionsError(f"{f.sample_id}: forecasts of shape {f.futures.shape}, expected "
                                   f"({len(f.track_ids)}, {k}, {t}, 2) (targets, K, T, xy)")
    if not done:
        return schema.empty_table()
    per_target = k * t
    n_targets = np.array([len(f.track_ids) for f in done])
    total = int(n_targets.sum()) * per_target
    track_names = [str(n) for f in done for n in f.track_ids]
    type_names = [str(n) for f in done for n in f.object_types]
    futures = np.concatenate([np.asarray(f.futures, np.float64) for f in done]).reshape(-1, 2)
    step_ns = np.concatenate([np.tile(np.asarray(f.step_ns, np.int64), len(f.track_ids) * k) for f in done])
    uniform = np.full(k, 1.0 / k)
    scores = np.concatenate([np.repeat((np.broadcast_to(uniform, (len(f.track_ids), k)) if f.scores is None
                                        else np.asarray(f.scores)).reshape(-1), t) for f in done])
    per_sample = n_targets * per_target
    target_index = pa.array(np.repeat(np.arange(len(track_names)), per_target))
    sample_index = pa.array(np.repeat(np.arange(len(done)), per_sample))
    columns = {
        "log_id": pa.array([f.log_id for f in done], pa.string()).take(sample_index),
        "sample_id": pa.array([f.sample_id for f in done], pa.string()).take(sample_index),
        "track_id": pa.array(track_names, pa.string()).take(target_index),
        "object_type": pa.array(type_names, pa.string()).take(target_index),
        "mode": pa.array(np.tile(np.repeat(np.arange(k, dtype=np.int16), t), len(track_names))),
        "step": pa.array(np.tile(np.arange(1, t + 1, dtype=np.int16), len(track_names) * k)),
        "timestamp_ns": pa.array(step_ns.astype(np.int64)),
        "x": pa.array(futures[:, 0]),
        "y": pa.array(futures[:, 1]),
        "score": pa.array(scores.astype(np.float32)),
        "predictor": pa.repeat(pa.scalar(meta.predictor, pa.string()), total),
        "checkpoint_id": pa.repeat(pa.scalar(meta.checkpoint_id, pa.string()), total),
    }
    return pa.Table.from_arrays([columns[f.name] for f in schema], schema=schema)


def samples_table(meta: PredictionMeta, samples: Sequence[SceneSample], forecasts: Sequence[NDArrayFloat], *,
                  sample_log: dict[str, str] | None = None) -> pa.Table:
    """The predictions table for ``Predictor.predict`` outputs on ``samples`` (uniform scores).

    ``logpipe predict`` is the normal producer; this serves tests and the reproduction scripts. Step times are
    the window's own; ``sample_log`` maps sample id to log id (default: the id before its last ``:``).

    Raises:
        PredictionsError: a forecast array that does not match its sample's targets, K or T.
    """
    out = []
    for s, f in zip(samples, forecasts, strict=True):
        idx = np.flatnonzero(s.target_mask)
        futures = np.asarray(f, np.float64)
        if futures.shape[0] != len(idx):
            raise PredictionsError(f"{s.sample_id}: {futures.shape[0]} forecasts for {len(idx)} targets")
        log = sample_log[s.sample_id] if sample_log else s.sample_id.rsplit(":", 1)[0]
        out.append(SampleForecast(
            log_id=log, sample_id=s.sample_id, track_ids=[s.track_ids[a] for a in idx],
            object_types=[OBJECT_TYPES[int(s.object_types[a])] for a in idx], futures=futures, scores=None,
            step_ns=np.asarray(s.timestamps_ns[s.obs_len : s.obs_len + meta.pred_len], np.int64)))
    return build_table(meta, out)


# ---- reading -------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class DenseForecasts:
    """A predictions table as arrays, one row per predicted agent (sorted by sample, then track).

    Attributes:
        sample_ids: (N,) sample of each agent row.
        track_ids: (N,) track of each agent row.
        object_types: (N,) normalised class of each agent row.
        pred: (N, K, T, 2) metres, world frame; mode 0 the most likely.
        checkpoint_ids: distinct ``checkpoint_id`` values.
    """

    sample_ids: Any
    track_ids: Any
    object_types: Any
    pred: NDArrayFloat
    checkpoint_ids: list[str]


def meta_from_table(schema: pa.Schema, table: pa.Table | None, where: str) -> PredictionMeta:
    """The metadata of a table file: ``logpipe.predictions``, else the keys of older writers (with the
    predictor and checkpoint from the columns and K/T from the rows when no key gives them).

    Raises:
        PredictionsError: no metadata and no rows to infer it from, or several predictors in one table.
    """
    raw = {k.decode(): v.decode() for k, v in (schema.metadata or {}).items()}
    if META_KEY in raw:
        try:
            return PredictionMeta.from_dict(json.loads(raw[META_KEY]), where)
        except ValueError:
            raise PredictionsError(f"{where}: damaged {META_KEY} metadata (not JSON)") from None
    if table is None:
        raise PredictionsError(f"{where}: no {META_KEY} metadata")
    protocol: dict[str, Any] = {}
    if "logpipe.protocol" in raw:  # logpipe predict before this module
        protocol = json.loads(raw["logpipe.protocol"])
    if table.num_rows == 0:
        raise PredictionsError(f"{where}: the predictions table is empty")
    names = sorted(set(table.column("predictor").to_pylist()))
    ids = sorted(set(table.column("checkpoint_id").to_pylist()))
    if len(names) != 1 or len(ids) != 1:
        raise PredictionsError(f"{where}: holds several predictors or checkpoints ({names}, {len(ids)} ids); "
                               "score one table per method")

    def number(key: str, fallback: int) -> int:
        value = protocol.get(key, raw.get(key))
        return int(value) if value is not None else fallback

    seed = raw.get("logpipe.seed")
    return PredictionMeta(
        predictor=names[0], checkpoint_id=ids[0], protocol=protocol.get("name"),
        obs_len=number("obs_len", 0),
        pred_len=number("pred_len", int(pc.max(table.column("step")).as_py())),
        num_modes=number("num_modes", int(pc.max(table.column("mode")).as_py()) + 1),
        seed=int(seed) if seed is not None else None,
        dataset_manifest_sha256=raw.get("logpipe.dataset_manifest_sha256"),
        logpipe_version=raw.get("logpipe.version", "unknown"),
    )


def read_table_file(path: Path, expect_rows: int | None = None) -> pa.Table:
    """One predictions file, checked against the contract (a damaged file is a one-line error).

    Raises:
        PredictionsError: unreadable, truncated, columns missing, or another row count than ``expect_rows``.
    """
    try:
        table = pq.read_table(path, page_checksum_verification=True)
    except FileNotFoundError:
        raise PredictionsError(f"{path}: predictions file not found") from None
    except (OSError, pa.ArrowException) as exc:
        first = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise PredictionsError(f"{path}: unreadable predictions file ({first}); truncated or damaged? "
                               "`logpipe verify` checks a run folder") from None
    missing = [c for c in arrow_schema("predictions").names if c not in table.column_names]
    if missing:
        raise PredictionsError(f"{path}: not a predictions table (schemas/predictions.json), missing columns "
                               f"{missing}")
    if expect_rows is not None and table.num_rows != expect_rows:
        raise PredictionsError(f"{path}: {table.num_rows} rows, the manifest says {expect_rows}")
    return table


@dataclass(frozen=True)
class PredictionRun:
    """A prediction run folder (or a single predictions file) opened for reading.

    Attributes:
        source: the folder or file.
        name: the folder's name or the file's stem (labels methods whose predictor names collide).
        meta: what the forecasts were made with.
        files: the predictions files (those the committed manifest names, in shard order).
        rows: rows of each file as the manifest records them (None for a single file).
    """

    source: Path
    name: str
    meta: PredictionMeta
    files: tuple[Path, ...]
    rows: tuple[int, ...] | None

    @classmethod
    def open(cls, path: Path) -> PredictionRun:
        """Open a run folder by its committed manifest, or a single predictions ``.parquet`` file.

        Raises:
            PredictionsError: not found, not a prediction run, damaged manifest or metadata, files missing or
                of another size than committed.
        """
        path = Path(path)
        if path.is_dir():
            return cls._open_folder(path)
        if not path.is_file():
            raise PredictionsError(f"{path}: predictions not found (give a `logpipe predict` output folder or a "
                                   "predictions .parquet file)")
        try:
            schema = pq.read_schema(path)
        except (OSError, pa.ArrowException) as exc:
            raise PredictionsError(f"{path}: not a readable Parquet file ({str(exc).splitlines()[0]})") from None
        table = None if META_KEY.encode() in (schema.metadata or {}) else read_table_file(path)
        return cls(path, path.stem, meta_from_table(schema, table, str(path)), (path,), None)

    @classmethod
    def _open_folder(cls, root: Path) -> PredictionRun:
        if not (root / MANIFEST).is_file() and (root / LEGACY_RUN_FILE).is_file():
            raise PredictionsError(f"{root}: a prediction run of an older logpipe ({LEGACY_RUN_FILE}, no "
                                   f"{MANIFEST}); re-run `logpipe predict` into a new folder (or score its "
                                   "predictions/*.parquet files one at a time)")
        try:
            manifest = read_manifest(root)
        except DatasetError as exc:
            raise PredictionsError(str(exc)) from None
        assert manifest is not None
        if manifest.get("artifact") != RUN_ARTIFACT:
            raise PredictionsError(f"{root}: not a prediction run folder (its {MANIFEST} is a "
                                   f"{manifest.get('artifact') or 'dataset or other artifact'}'s)")
        meta = PredictionMeta.from_dict(manifest.get("metadata"), str(root / MANIFEST))
        files = manifest.get("files")
        if not isinstance(files, dict):
            raise PredictionsError(f"{root / MANIFEST}: lists no files")
        try:
            check_files(root, files)
        except DatasetError as exc:
            raise PredictionsError(str(exc)) from None
        # part-NNNNN names sort in shard order
        tables = [rel for rel in sorted(files) if rel.startswith(PREDICTIONS_DIR + "/") and rel.endswith(".parquet")]
        return cls(root, root.name, meta, tuple(root / rel for rel in tables),
                   tuple(int(files[rel].get("rows", -1)) for rel in tables))

    def table(self) -> pa.Table:
        """Every row, checked: contract columns, committed row counts, one predictor and checkpoint as the
        metadata says."""
        parts = [read_table_file(p, None if self.rows is None else self.rows[i]) for i, p in enumerate(self.files)]
        schema = self.meta.schema()
        table = pa.concat_tables([t.select(schema.names).cast(schema) for t in parts]) if parts \
            else schema.empty_table()
        for column, want in (("predictor", self.meta.predictor), ("checkpoint_id", self.meta.checkpoint_id)):
            seen = set(pc.unique(table.column(column)).to_pylist())
            if seen - {want}:
                raise PredictionsError(f"{self.source}: {column} values {sorted(seen)[:3]} differ from the metadata's "
                                       f"{want!r}")
        return table

    def dense(self) -> DenseForecasts:
        """The rows as (agents, K, T, 2), K and T from the metadata.

        Raises:
            PredictionsError: empty, or not one row per (sample, track, mode 0..K-1, step 1..T).
        """
        table = self.table()
        if table.num_rows == 0:
            raise PredictionsError(f"{self.source}: the predictions table is empty")
        return dense_forecasts(table, self.meta.num_modes, self.meta.pred_len, str(self.source))


def dense_forecasts(table: pa.Table, k: int, t: int, where: str) -> DenseForecasts:
    """Rows of one method → arrays (see ``DenseForecasts``); the rows must form a full grid."""
    order = pc.sort_indices(table, sort_keys=[(c, "ascending") for c in ("sample_id", "track_id", "mode", "step")])
    table = table.take(order)
    steps = as_numpy(table.column("step")).astype(np.int64)
    modes = as_numpy(table.column("mode")).astype(np.int64)
    n_rows = table.num_rows
    if n_rows % (k * t):
        raise PredictionsError(f"{where}: {n_rows} rows is not agents x {k} modes x {t} steps")
    n = n_rows // (k * t)
    grid_ok = np.array_equal(steps.reshape(n, k, t), np.broadcast_to(np.arange(1, t + 1), (n, k, t))) and \
        np.array_equal(modes.reshape(n, k, t), np.broadcast_to(np.arange(k)[:, None], (n, k, t)))
    sid = pc.dictionary_encode(table.column("sample_id")).combine_chunks()
    tid = pc.dictionary_encode(table.column("track_id")).combine_chunks()
    key = sid.indices.to_numpy().astype(np.int64) * (len(tid.dictionary) + 1) + tid.indices.to_numpy()
    key = key.reshape(n, k * t)
    if not grid_ok or not np.all(key == key[:, :1]):
        raise PredictionsError(f"{where}: rows are not one per (sample, track, mode 0..{k - 1}, step 1..{t}); "
                               "duplicated or missing rows")
    first = np.arange(n) * k * t
    xy = np.stack([as_numpy(table.column("x")), as_numpy(table.column("y"))], axis=-1).astype(np.float64)
    return DenseForecasts(
        sample_ids=as_numpy(table.column("sample_id"))[first].astype(str),
        track_ids=as_numpy(table.column("track_id"))[first].astype(str),
        object_types=as_numpy(table.column("object_type"))[first].astype(str),
        pred=xy.reshape(n, k, t, 2),
        checkpoint_ids=sorted(set(table.column("checkpoint_id").to_pylist())),
    )


# ---- the write side of a prediction run folder ---------------------------------------------------------

MCAP_DIR = "mcap"
RUN_OWNED = Ownership([f"{PREDICTIONS_DIR}/", f"{MCAP_DIR}/"])
"""A prediction run's own paths (its writer removes those its manifest does not name)."""


class RunSettings(TypedDict):
    """What a run was made with; a rerun resumes only with equal settings."""

    dataset_manifest_sha256: str
    predictor: str
    checkpoint_id: str
    num_modes: int
    seed: int
    batch_size: int
    filter: dict[str, Any]
    protocol: dict[str, Any]
    write_mcap: bool
    raster_run: str | None


class RunShardEntry(TypedDict):
    """A finished dataset shard in the run manifest (``file`` None when none of its logs was selected)."""

    shard: str
    logs: int
    samples: int
    rows: int
    file: str | None


class PredictionRunWriter(FolderWriter):
    """Writes a prediction run folder (``PredictionRun`` reads it): locked, one commit per finished dataset
    shard, so an interrupted run resumes from its committed shards (``logpipe.artifact``)."""

    ownership = RUN_OWNED
    kind = RUN_ARTIFACT

    @property
    def manifest(self) -> dict[str, Any] | None:
        return self._writer.manifest

    @staticmethod
    def refuse_other_folders(out_dir: Path) -> None:
        """Never adopt a folder that holds another artifact (a dataset: its ``mcap/`` would look like ours) or a
        run of an older logpipe: entering the writer would remove their files."""
        if not out_dir.is_dir():
            return
        existing = read_manifest(out_dir, required=False)
        if existing is not None and existing.get("artifact") != RUN_ARTIFACT:
            raise DatasetError(f"{out_dir}: holds another logpipe artifact ({MANIFEST} of a "
                               f"{existing.get('artifact') or 'dataset'}), not a prediction run; choose another --out")
        if existing is None and (out_dir / LEGACY_RUN_FILE).is_file():
            raise DatasetError(f"{out_dir}: holds a prediction run of an older logpipe ({LEGACY_RUN_FILE}); "
                               "choose another --out or delete it")

    def committed(self, settings: RunSettings) -> tuple[list[RunShardEntry], dict[str, FileEntry]]:
        """The committed shards and files (none for a new folder), refused when made with other settings."""
        committed = self.manifest
        if committed is None:
            return [], {}
        self.refuse_other_folders(self.root)
        wanted = json.loads(json.dumps(settings))
        if committed.get("settings") != wanted:
            old = committed.get("settings") or {}
            diff = sorted(k for k in wanted if old.get(k) != wanted[k])
            raise DatasetError(f"{self.root}: holds predictions made with other settings ({', '.join(diff)}); "
                               "use another --out or delete it")
        return list(committed.get("shards", [])), dict(committed.get("files", {}))

    def commit(self, settings: RunSettings, meta: PredictionMeta, shards: list[RunShardEntry],
               files: dict[str, FileEntry]) -> None:
        """Commit the run's state. Nothing in the manifest depends on time, pid or machine, so a resumed run
        equals a whole one."""
        self._writer.commit({"format_version": RUN_FORMAT_VERSION, "logpipe_version": __version__,
                             "settings": settings, "metadata": meta.to_dict(), "shards": shards, "files": files})
