"""The predictions table: its schema, its metadata and how it is read back (``logpipe.prediction.table``
builds it from forecasts).

Every producer (``logpipe predict``, the reproduction scripts, tests) and every reader (``logpipe score``, the
scripts) goes through this module, so the table's layout and its metadata keys are decided here only.

Layout (``schemas/predictions.json``, version 2): one row per (sample, target track, mode), ordered sample by
sample, target by target (``target_mask`` order), mode 0..K-1; the horizon is fixed-size lists of T values
(``x``, ``y`` in metres, ``timestamp_ns``), as Argoverse 2's submission format keeps ``predicted_trajectory_x/y``.
Ids and the object type are plain strings (earlier files: dictionaries, read alike).
What is constant over a table (predictor,
checkpoint, protocol, K, T, seed, ...) is only its metadata: ``PredictionMeta`` as JSON under the Parquet key
``logpipe.predictions``. Version 1 tables (one row per future step, ``step`` column, constant ``predictor`` and
``checkpoint_id`` columns; run manifests of ``format_version`` 1) are still read: ``PredictionRun.table`` turns
them into this layout.

A prediction run folder (``logpipe predict --out``) is a committed artifact (``logpipe.storage.artifact``)::

    manifest.json                   "artifact": "prediction_run", settings, metadata, finished shards, files
    predictions/part-NNNNN.parquet  this table, one file per dataset shard
    mcap/part-NNNNN/<log_id>.mcap   per-log MCAPs with prediction channels

``PredictionRun.open`` reads such a folder (only the files its manifest names) or a single table file.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, fields, replace
from pathlib import Path
from typing import Any, NotRequired, TypedDict

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
import pyarrow.parquet as pq

from logpipe import __version__
from logpipe.contracts import arrow_schema, decode_dictionaries, field_names, optional_fields
from logpipe.errors import DatasetError, LogpipeError
from logpipe.storage.artifact import MANIFEST, FileEntry, FolderWriter, Ownership, check_files, read_manifest
from logpipe.storage.io import as_numpy
from logpipe.types import NDArrayFloat

RUN_ARTIFACT = "prediction_run"
"""``manifest.json`` ``artifact`` value of a prediction run folder."""
RUN_FORMAT_VERSION = 2
"""2: tables of schemas/predictions.json version 2 (a row per mode); 1: a row per future step (read only)."""
PREDICTIONS_DIR = "predictions"
META_KEY = "logpipe.predictions"
"""Parquet schema-metadata key holding ``PredictionMeta`` as JSON."""
LEGACY_RUN_FILE = "predict.json"
"""Run state of prediction folders written before they were committed artifacts."""
LONG_COLUMNS = ("log_id", "sample_id", "track_id", "object_type", "mode", "step", "timestamp_ns", "x", "y", "score",
                "predictor", "checkpoint_id")
"""Columns of version 1 tables: one row per (sample, track, mode, step), constants as columns."""


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
        out_of_distribution: what flagged targets got (``warn``, ``fallback``), when the predictor scores each
            target against its training data: the table then has the ``optional_fields`` of
            schemas/predictions.json (``ood_score``, ``ood_flag``, ``fallback``). None: it has not.
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
    out_of_distribution: str | None = None

    def to_dict(self) -> dict[str, Any]:
        """The JSON form (manifest ``metadata``, Parquet ``logpipe.predictions``); ``out_of_distribution`` only when
        set, so the metadata of runs without it is as before."""
        data = asdict(self)
        if data["out_of_distribution"] is None:
            del data["out_of_distribution"]
        return data

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
        """The contract schema (lists of ``pred_len`` values; with the out-of-distribution columns when the run
        has them) with this metadata attached."""
        schema = arrow_schema("predictions", pred_len=self.pred_len)
        if self.out_of_distribution is not None:
            schema = pa.schema([*schema, *optional_fields("predictions")], metadata=schema.metadata)
        extra = {META_KEY.encode(): json.dumps(self.to_dict(), sort_keys=True).encode()}
        return schema.with_metadata({**(schema.metadata or {}), **extra})


# ---- reading -------------------------------------------------------------------------------------------


def read_table_file(path: Path, expect_rows: int | None = None) -> pa.Table:
    """One predictions file of either layout, checked against its contract (a damaged file is a one-line error).

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
    wanted = LONG_COLUMNS if "step" in table.column_names else field_names("predictions")
    missing = [c for c in wanted if c not in table.column_names]
    if missing:
        raise PredictionsError(f"{path}: not a predictions table (schemas/predictions.json), missing columns "
                               f"{missing}")
    if expect_rows is not None and table.num_rows != expect_rows:
        raise PredictionsError(f"{path}: {table.num_rows} rows, the manifest says {expect_rows}")
    return table


def is_long(table: pa.Table) -> bool:
    """Whether ``table`` has the version 1 layout (one row per future step)."""
    return "step" in table.column_names


def as_current(table: pa.Table, meta: PredictionMeta, where: str) -> pa.Table:
    """A table of either layout in the current one (``meta.schema()``); a version 1 table is checked to hold one
    predictor and checkpoint, the metadata's, and one row per (sample, track, mode 0..K-1, step 1..T).

    Raises:
        PredictionsError: columns of other types or another horizon than the metadata's, or (version 1) other
            constants or a broken grid.
    """
    schema = meta.schema()
    if is_long(table):
        return _from_long(table, meta, where)
    for name in ("timestamp_ns", "x", "y"):
        kind = table.schema.field(name).type
        if not pa.types.is_fixed_size_list(kind) or kind.list_size != meta.pred_len:
            raise PredictionsError(f"{where}: column {name} is {kind}, expected lists of the metadata's "
                                   f"{meta.pred_len} steps")
    try:
        return table.select(schema.names).cast(schema)
    except (pa.ArrowInvalid, pa.ArrowNotImplementedError, pa.ArrowTypeError) as exc:
        raise PredictionsError(f"{where}: columns not as schemas/predictions.json says ({exc})") from None


def _from_long(table: pa.Table, meta: PredictionMeta, where: str) -> pa.Table:
    """A version 1 table (a row per step) → the current layout, rows sorted by sample, track, mode."""
    k, t = meta.num_modes, meta.pred_len
    for column, want in (("predictor", meta.predictor), ("checkpoint_id", meta.checkpoint_id)):
        seen = set(pc.unique(table.column(column)).to_pylist())
        if seen - {want}:
            raise PredictionsError(f"{where}: {column} values {sorted(seen)[:3]} differ from the metadata's {want!r}")
    n_rows = table.num_rows
    if n_rows % (k * t):
        raise PredictionsError(f"{where}: {n_rows} rows is not agents x {k} modes x {t} steps")
    # Only the sort keys are reordered whole; the wide rows take their ids from each run's first row.
    keys = decode_dictionaries(table.select(["sample_id", "track_id", "mode", "step"]))
    order = pc.sort_indices(keys, sort_keys=[(c, "ascending") for c in keys.column_names])
    keys = keys.take(order)
    n = n_rows // (k * t)
    steps = as_numpy(keys.column("step")).astype(np.int64).reshape(n, k, t)
    modes = as_numpy(keys.column("mode")).astype(np.int64).reshape(n, k, t)
    if not (np.array_equal(steps, np.broadcast_to(np.arange(1, t + 1), (n, k, t)))
            and np.array_equal(modes, np.broadcast_to(np.arange(k)[:, None], (n, k, t)))
            and _one_per_group(keys.select(["sample_id", "track_id", "mode"]), t)):
        raise PredictionsError(f"{where}: rows are not one per (sample, track, mode 0..{k - 1}, step 1..{t}); "
                               "duplicated or missing rows")
    first = order.take(pa.array(np.arange(n * k) * t))
    wide = table.select(["log_id", "sample_id", "track_id", "object_type", "mode", "score"]).take(first)
    columns = {name: wide.column(name) for name in wide.column_names}
    for name in ("timestamp_ns", "x", "y"):
        values = table.column(name).take(order).combine_chunks()
        columns[name] = pa.chunked_array([pa.FixedSizeListArray.from_arrays(values, t)])
    schema = meta.schema()
    return pa.Table.from_arrays([columns[f.name].cast(f.type) for f in schema], schema=schema)


def _one_per_group(keys: pa.Table, group: int) -> bool:
    """Whether ``keys`` rows (sorted by their columns) come in runs of ``group`` rows with one key each, and no
    two runs share a key (a duplicated agent is refused even when K = 1)."""
    same = True
    differs = np.zeros(keys.num_rows // group - 1, dtype=bool) if keys.num_rows else np.zeros(0, dtype=bool)
    for column in keys.columns:
        codes = as_numpy(pc.dictionary_encode(column).combine_chunks().indices).reshape(-1, group)
        same = same and bool(np.all(codes == codes[:, :1]))
        differs |= codes[1:, 0] != codes[:-1, 0]
    return same and bool(differs.all())


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
    if table is None or not is_long(table):
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
        """Every row in the current layout (``meta.schema()``; version 1 files converted), checked: contract
        columns, committed row counts, the metadata's horizon (and for version 1 files its predictor and
        checkpoint)."""
        parts = [as_current(read_table_file(p, None if self.rows is None else self.rows[i]), self.meta, str(p))
                 for i, p in enumerate(self.files)]
        return pa.concat_tables(parts) if parts else self.meta.schema().empty_table()

    def dense(self) -> DenseForecasts:
        """The rows as (agents, K, T, 2), K and T from the metadata.

        Raises:
            PredictionsError: empty, or not one row per (sample, track, mode 0..K-1).
        """
        table = self.table()
        if table.num_rows == 0:
            raise PredictionsError(f"{self.source}: the predictions table is empty")
        return dense_forecasts(table, self.meta.num_modes, self.meta.pred_len, str(self.source))


def dense_forecasts(table: pa.Table, k: int, t: int, where: str) -> DenseForecasts:
    """Rows of one method (either layout; a version 1 table needs its ``logpipe.predictions`` metadata) →
    arrays (see ``DenseForecasts``); the rows must be one per (sample, track, mode 0..K-1).

    Raises:
        PredictionsError: another horizon than ``t``, or missing or duplicated rows.
    """
    raw = (table.schema.metadata or {}).get(META_KEY.encode())
    meta = PredictionMeta.from_dict(json.loads(raw), where) if raw is not None else None
    if is_long(table):
        if meta is None:
            meta = meta_from_table(table.schema, table, where)
        table = _from_long(table, replace(meta, num_modes=k, pred_len=t), where)
    n_rows = table.num_rows
    if n_rows % k:
        raise PredictionsError(f"{where}: {n_rows} rows is not agents x {k} modes")
    for name in ("x", "y"):
        kind = table.schema.field(name).type
        if not pa.types.is_fixed_size_list(kind) or kind.list_size != t or table.column(name).null_count:
            raise PredictionsError(f"{where}: column {name} is {kind} (nulls: {table.column(name).null_count}), "
                                   f"expected lists of {t} values")
    # Sorted by the values (as strings: ``sort_indices`` refuses dictionaries), as version 1 readers sorted.
    keys = decode_dictionaries(table.select(["sample_id", "track_id", "object_type", "mode"]))
    order = pc.sort_indices(keys, sort_keys=[(c, "ascending") for c in ("sample_id", "track_id", "mode")])
    keys = keys.take(order)
    n = n_rows // k
    modes = as_numpy(keys.column("mode")).astype(np.int64).reshape(n, k)
    if not (np.array_equal(modes, np.broadcast_to(np.arange(k), (n, k)))
            and _one_per_group(keys.select(["sample_id", "track_id"]), k)):
        raise PredictionsError(f"{where}: rows are not one per (sample, track, mode 0..{k - 1}); duplicated or "
                               "missing rows")
    x, y = (as_numpy(table.column(name).take(order).combine_chunks().flatten()) for name in ("x", "y"))
    first = np.arange(n) * k
    return DenseForecasts(
        sample_ids=as_numpy(keys.column("sample_id"))[first].astype(str),
        track_ids=as_numpy(keys.column("track_id"))[first].astype(str),
        object_types=as_numpy(keys.column("object_type"))[first].astype(str),
        pred=np.stack([x, y], axis=-1).astype(np.float64).reshape(n, k, t, 2),
        checkpoint_ids=[meta.checkpoint_id] if meta is not None else [],
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
    out_of_distribution: NotRequired[str]  # a residual checkpoint's --out-of-distribution action


class RunShardEntry(TypedDict):
    """A finished dataset shard in the run manifest (``file`` None when none of its logs was selected)."""

    shard: str
    logs: int
    samples: int
    rows: int
    file: str | None


class PredictionRunWriter(FolderWriter):
    """Writes a prediction run folder (``PredictionRun`` reads it): locked, one commit per finished dataset
    shard, so an interrupted run resumes from its committed shards (``logpipe.storage.artifact``)."""

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
        version = committed.get("format_version", 1)
        if version != RUN_FORMAT_VERSION:
            # Shards of another table layout cannot be resumed into; the folder stays readable by `score`.
            raise DatasetError(f"{self.root}: holds predictions of run format {version} (this logpipe writes "
                               f"{RUN_FORMAT_VERSION}); use another --out or delete it")
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
