"""Raster runs on disk: where ``logpipe rasterise`` puts them and how training and prediction read them.

A run lives in ``DATASET/rasters/<run_id>/`` (see ``logpipe.stages.rasterise`` for the layout); ``run_id``
hashes every setting that changes pixels, so a reader asks for the settings it wants and never gets a
raster made with others.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path, PurePath
from typing import Any, Self, TypedDict

import numpy as np
import pyarrow as pa

from logpipe.errors import DatasetError
from logpipe.raster.rasteriser import RasterSpec
from logpipe.storage.artifact import EVERYTHING, FileEntry, FolderWriter, check_files, read_manifest
from logpipe.storage.io import read_table, sha256_file
from logpipe.storage.safe_paths import real_folder
from logpipe.types import NDArrayByte, NDArrayFloat

RASTER_DIR = "rasters"
RASTER_ARTIFACT = "raster_run"
"""``manifest.json`` ``artifact`` value of a raster run folder."""
RUN_MANIFEST = "manifest.json"
CENTRES = ("ego", "focal")
CENTRE_FALLBACK = "central_target"
"""What ``centre="ego"`` uses in a log with neither ego nor focal track (``logpipe.raster.centre``); part of the run
settings since it changes those logs' pixels (runs made before it drew them empty, under other run ids)."""
MIN_HEADING_DISP_M = 0.5
"""Motion heading: look back to the latest observed position at least this far away (metres)."""
LANE_HEADING_MAX_DIST_M = 3.0
"""Stationary agents take the direction of a centerline at most this far away (metres)."""


class RasterRunIdentity(TypedDict):
    """A run's inputs (manifest ``identity``): the sample index's sha256, every map file the run resolves to
    (sha256 by path) and the shard size (it decides which sample lands in which file)."""

    samples_sha256: str
    maps: dict[str, str]
    shard_size: int


class RasterRunSettings(TypedDict):
    """Everything that determines a run's pixels (manifest ``settings``, hashed into ``run_id``); ``spec`` is
    ``RasterSpec.to_dict()`` (open JSON: its keys follow the spec's version). Distances in metres."""

    spec: dict[str, Any]
    centre: str
    centre_fallback: str
    min_heading_disp_m: float
    lane_heading_max_dist_m: float


class RasterShardEntry(TypedDict):
    """One rendered shard in the manifest's ``shards``: its ``.npy`` and index file names (in the run folder), its
    rows (samples) and the ``.npy``'s sha256."""

    file: str
    index: str
    rows: int
    sha256: str


class RasterRunCounts(TypedDict, total=False):
    """Manifest ``counts`` over the whole run's index: empty rasters, samples with no centre, samples by heading
    rule and by centre role (only the values that occur). Empty (``{}``) until the run is complete."""

    empty: int
    no_centre: int
    heading_source: dict[str, int]
    centre_role: dict[str, int]


class RasterRunManifest(TypedDict):
    """What ``RasterRunWriter`` commits as ``manifest.json`` (the storage layer adds ``artifact``, ``owns`` and
    ``checksum``); ``complete`` stays false until the last shard is committed."""

    logpipe_version: str
    run_id: str
    settings: RasterRunSettings
    fingerprint: str
    identity: RasterRunIdentity
    samples: int
    shard_size: int
    shards: list[RasterShardEntry]
    complete: bool
    counts: RasterRunCounts
    files: dict[str, FileEntry]


class CommittedShard(TypedDict):
    """A shard a previous invocation committed (``RasterRunWriter.committed_shards``): its manifest entry, its
    files' entries (with every committed preview) and whether previews were written."""

    entry: RasterShardEntry
    files: dict[str, FileEntry]
    previews: bool


def shard_file(i: int, tag: str) -> str:
    """``shard-TAG-NNNNN.npy``; ``tag`` names the run's inputs (``inputs_tag``), so files made from other
    samples, maps or shard size never take the name of a committed one."""
    return f"shard-{tag}-{i:05d}.npy"


def index_file(i: int, tag: str) -> str:
    """``index-TAG-NNNNN.parquet``."""
    return f"index-{tag}-{i:05d}.parquet"


def _comparable(identity: dict[str, Any]) -> dict[str, Any]:
    """``identity`` with its maps keyed by file name, not path: the same map files reached by another path
    (``../data`` against ``/work/data``, a moved folder) are the same inputs, while two files that swapped their
    contents are not."""
    maps = identity.get("maps") or {}
    return {**identity, "maps": sorted((PurePath(path).name, digest) for path, digest in maps.items())}


def inputs_tag(identity: RasterRunIdentity) -> str:
    """Short hash of a run's input identity (sample index, map files by content, shard size)."""
    return hashlib.sha256(json.dumps(_comparable(dict(identity)), sort_keys=True).encode()).hexdigest()[:8]


def run_settings(spec: RasterSpec, centre: str) -> RasterRunSettings:
    """Everything that determines the pixels of a run (hashed into ``run_id``)."""
    return {
        "spec": spec.to_dict(),
        "centre": centre,
        "centre_fallback": CENTRE_FALLBACK,
        "min_heading_disp_m": MIN_HEADING_DISP_M,
        "lane_heading_max_dist_m": LANE_HEADING_MAX_DIST_M,
    }


def run_id(spec: RasterSpec, centre: str) -> str:
    """Folder name of a run: short hash of ``run_settings``."""
    blob = json.dumps(run_settings(spec, centre), sort_keys=True).encode()
    return hashlib.sha256(blob).hexdigest()[:16]


class RasterShards:
    """Read side for training: rasters of one finished run, memory-mapped, by sample id.

    ``open`` takes the settings the caller expects and refuses a run made with others, so a raster is
    never used with the wrong size, extent, channels or rotation.

    Attributes:
        run_dir: the run folder.
        spec: the run's raster spec.
        index: the concatenated ``index-*.parquet`` tables (``schemas/raster.json``).
    """

    def __init__(self, run_dir: Path, spec: RasterSpec, index: pa.Table,
                 files: dict[str, FileEntry] | None = None) -> None:
        self.run_dir = run_dir
        self.files = files or {}
        """The manifest's entries: each shard's sha256 is checked when a run first reads it."""
        self.spec = spec
        self.index = index
        ids = index.column("sample_id").to_pylist()
        shards = index.column("shard").to_pylist()
        rows = index.column("row").to_pylist()
        self._where = {s: (sh, r) for s, sh, r in zip(ids, shards, rows, strict=True)}
        self._affine = dict(zip(ids, index.column("affine").to_pylist(), strict=True))
        self._mmaps: dict[str, NDArrayByte] = {}

    @classmethod
    def open(cls, dataset_dir: Path, spec: RasterSpec, centre: str = "ego") -> RasterShards:
        """The finished run for ``spec``/``centre`` in a dataset.

        Raises:
            DatasetError: no finished run with exactly these settings.
        """
        run_dir = Path(dataset_dir) / RASTER_DIR / run_id(spec, centre)
        manifest = read_manifest(run_dir, required=False)
        if manifest is None or not manifest.get("complete", True):
            raise DatasetError(
                f"{dataset_dir}: no finished raster run for {spec.to_dict()} centre={centre}; run `logpipe rasterise`"
            )
        if manifest.get("settings") != json.loads(json.dumps(run_settings(spec, centre))):
            raise DatasetError(f"{run_dir}: raster settings differ from the requested ones")
        check_files(run_dir, manifest.get("files", {}))
        index = pa.concat_tables([read_table(run_dir / s["index"]) for s in manifest["shards"]])
        if index.num_rows != manifest.get("samples", index.num_rows):
            raise DatasetError(f"{run_dir}: index holds {index.num_rows} rasters, the manifest says "
                               f"{manifest['samples']}; `logpipe verify` lists what is wrong")
        return cls(run_dir, spec, index, manifest.get("files", {}))

    def __len__(self) -> int:
        return int(self.index.num_rows)

    def get(self, sample_id: str) -> tuple[NDArrayByte, NDArrayFloat]:
        """(C, H, W) uint8 raster (a read-only memory map view) and its (2, 3) world→pixel affine."""
        shard, row = self._where[sample_id]
        arr = self._mmaps.get(shard)
        if arr is None:
            try:
                # Once per shard and reader: a changed byte would otherwise be a silently other raster.
                expected = self.files.get(shard, {}).get("sha256")
                if expected is not None and sha256_file(self.run_dir / shard) != expected:
                    raise ValueError("sha256 differs from the manifest (content changed)")
                arr = np.load(self.run_dir / shard, mmap_mode="r", allow_pickle=False)
            except (OSError, ValueError) as exc:
                raise DatasetError(f"{self.run_dir / shard}: unreadable raster shard ({exc}); `logpipe verify` "
                                   "lists what is wrong") from None
            self._mmaps[shard] = arr
        return arr[row], np.asarray(self._affine[sample_id], dtype=np.float64).reshape(2, 3)


def find_raster_run(dataset_dir: Path, run: str | None, channels: int | None) -> RasterShards | None:
    """The raster run to read, the one rule every stage follows: ``run`` (a folder name under ``rasters/``) when
    given, else the only finished run; with ``channels``, only runs rendering that many channels count. None when
    no finished run fits (each caller decides whether it needs one). Interrupted runs never count.

    Raises:
        DatasetError: ``run`` is not a finished run, or several runs fit and none was named (the message names
            them).
    """
    root = dataset_dir / RASTER_DIR
    runs = sorted(p.parent for p in root.glob(f"*/{RUN_MANIFEST}")) if root.is_dir() else []
    manifests = {r: read_manifest(r) or {} for r in runs}
    runs = [r for r in runs if manifests[r].get("complete", True)]  # an interrupted run is not finished
    if run is not None:
        runs = [r for r in runs if r.name == run]
        if not runs:
            raise DatasetError(f"{dataset_dir}: no finished raster run {run!r} in {root}")
    fitting = [r for r in runs if channels is None or len(manifests[r]["settings"]["spec"]["channels"]) == channels]
    if not fitting:
        return None
    if len(fitting) > 1:
        # Picking one silently would make the result depend on folder names (hashes of the settings).
        raise DatasetError(f"{dataset_dir}: several raster runs fit ({', '.join(r.name for r in fitting)}); "
                           "name one with --raster-run")
    chosen = manifests[fitting[0]]["settings"]
    return RasterShards.open(dataset_dir, RasterSpec.from_dict(chosen["spec"]), chosen["centre"])


class RasterRunWriter(FolderWriter):
    """Writes a raster run folder (``RasterShards`` reads it): locked; a commit after every rendered shard with
    ``complete`` false until the last, so an interrupted run resumes and readers never take it for finished."""

    ownership = EVERYTHING
    kind = RASTER_ARTIFACT

    def __enter__(self) -> Self:
        if self.root.parent.name == RASTER_DIR:  # a link as the dataset's rasters/ would put the run outside it
            real_folder(self.root.parent.parent, RASTER_DIR)
        return super().__enter__()

    def commit(self, manifest: RasterRunManifest) -> None:
        self._writer.commit(dict(manifest))

    def manifest_of(  # noqa: PLR0913  one parameter per manifest field it assembles
        self, spec: RasterSpec, centre: str, identity: RasterRunIdentity, samples: int, shard_size: int,
        shards: list[RasterShardEntry], files: dict[str, FileEntry], complete: bool, counts: RasterRunCounts,
    ) -> RasterRunManifest:
        """The run manifest: settings (hashed into the folder name), input identity, shards and files."""
        from logpipe import __version__

        return {"logpipe_version": __version__, "run_id": self.root.name, "settings": run_settings(spec, centre),
                "fingerprint": spec.fingerprint(), "identity": identity, "samples": samples,
                "shard_size": shard_size, "shards": shards, "complete": complete, "counts": counts, "files": files}

    def committed_shards(self, identity: RasterRunIdentity, force: bool) -> dict[str, CommittedShard]:
        """Shards a previous run of the same inputs committed (by ``.npy`` name), with their files and whether
        their previews were written; refuses a run of other inputs unless ``force`` (then nothing is reused).

        Raises:
            DatasetError: the folder holds a run of other samples, maps or shard size, and not ``force``.
        """
        manifest, out = self._writer.manifest, self.root
        if manifest is None:
            return {}
        old = _comparable(manifest.get("identity") or {})
        new = _comparable(json.loads(json.dumps(identity)))
        if old != new:
            if force:
                return {}
            changed = sorted(k for k, v in new.items() if old.get(k) != v)
            was = f" (shard size was {old.get('shard_size')})" if "shard_size" in changed else ""
            raise DatasetError(f"{out} holds rasters made with other {', '.join(changed) or 'inputs'}{was}; "
                               "rerun with --force to replace them")
        # Read from disk as committed by ``manifest_of`` (the checksum vouches for it), hence typed as written.
        files: dict[str, FileEntry] = manifest.get("files", {})
        previews = {rel: e for rel, e in files.items() if rel.startswith("previews/")}
        shards: list[RasterShardEntry] = manifest.get("shards", [])
        committed: dict[str, CommittedShard] = {}
        for entry in shards:
            own = {rel: files[rel] for rel in (entry["file"], entry["index"]) if rel in files}
            committed[entry["file"]] = {"entry": entry, "files": {**own, **previews}, "previews": bool(previews)}
        return committed
