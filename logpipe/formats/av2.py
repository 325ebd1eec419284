"""Argoverse 2: motion-forecasting scenarios and sensor-dataset logs.

* Scenario: ``scenario_<id>.parquet`` (one row per track and timestep, city frame, 110 steps at 10 Hz, the
  first 50 observed) beside ``log_map_archive_<id>.json``. The track ``AV`` is the ego, ``object_category``
  3 is the focal track. ``map_id`` = the scenario's city.
* Sensor log: a folder with ``city_SE3_egovehicle.feather`` (ego pose in the city frame, ~170 Hz) and
  ``annotations.feather`` / ``annotations_with_ego.feather`` (3D boxes per 10 Hz lidar sweep, in the ego-vehicle
  frame of that sweep). Boxes are moved to the city frame with the ego pose at the sweep's timestamp; the ego
  itself becomes a track sampled at the sweep timestamps. ``map_id`` = the city code in the map file name.

Timestamps are AV2's own (ns); nothing is resampled: both kinds are already on a common 10 Hz clock.
"""

from __future__ import annotations

import contextlib
import json
import math
import re
from collections.abc import Sequence
from decimal import Decimal
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
import pyarrow.parquet as pq
from pyarrow import feather

from logpipe.errors import SourceError
from logpipe.formats.base import (
    TIME_LIMIT_NS,
    ParsedLogs,
    as_source_error,
    check_log_id,
    check_tracks,
    conform_tracks,
    empty_tracks,
    require_regular,
    require_regular_tree,
)
from logpipe.geometry import quat_mul, quat_rotate, quat_yaw
from logpipe.types import PROTOCOLS, LogMeta, NDArrayFloat, SampleProtocol, SourceFile

# Scenario object_type → ObjectType (AV2 motion-forecasting vocabulary).
SCENARIO_TYPES: dict[str, str] = {
    "vehicle": "vehicle",
    "pedestrian": "pedestrian",
    "motorcyclist": "motorcyclist",
    "cyclist": "cyclist",
    "bus": "bus_truck",
}

# Sensor-dataset annotation categories → ObjectType (riderless bicycles, cones, signs... are "unknown").
SENSOR_TYPES: dict[str, str] = {
    "REGULAR_VEHICLE": "vehicle",
    "LARGE_VEHICLE": "vehicle",
    "RAILED_VEHICLE": "vehicle",
    "BUS": "bus_truck",
    "SCHOOL_BUS": "bus_truck",
    "ARTICULATED_BUS": "bus_truck",
    "BOX_TRUCK": "bus_truck",
    "TRUCK": "bus_truck",
    "TRUCK_CAB": "bus_truck",
    "VEHICULAR_TRAILER": "bus_truck",
    "PEDESTRIAN": "pedestrian",
    "OFFICIAL_SIGNALER": "pedestrian",
    "STROLLER": "pedestrian",
    "WHEELCHAIR": "pedestrian",
    "BICYCLIST": "cyclist",
    "WHEELED_RIDER": "cyclist",
    "MOTORCYCLIST": "motorcyclist",
}

FOCAL_CATEGORY = 3
EGO_TRACK = "AV"
SCENARIO_COLUMNS = (
    "track_id", "object_type", "object_category", "timestep", "position_x", "position_y", "heading",
    "velocity_x", "velocity_y", "scenario_id", "start_timestamp", "end_timestamp", "num_timestamps", "city",
)  # fmt: skip
POSE_COLUMNS = ("timestamp_ns", "qw", "qx", "qy", "qz", "tx_m", "ty_m", "tz_m")
BOX_COLUMNS = ("timestamp_ns", "track_uuid", "category", "length_m", "width_m", *POSE_COLUMNS[1:])
_CITY = re.compile(r"____(?P<city>[A-Z]{3})_city_\d+\.json$")


QUAT_TOLERANCE = 1e-3
"""Largest accepted | |q| - 1 | of a pose or box rotation."""


def _require(table: pa.Table, columns: Sequence[str], rel: str) -> None:
    for c in columns:
        if c not in table.column_names:
            raise SourceError(rel, f"column is missing (has: {', '.join(table.column_names)})", field=c)


def _quat(table: pa.Table) -> NDArrayFloat:
    """(N, 4) quaternions in (x, y, z, w) order from AV2's qw/qx/qy/qz columns."""
    return np.stack([table.column(c).to_numpy().astype(np.float64) for c in ("qx", "qy", "qz", "qw")], axis=1)


def _xyz(table: pa.Table) -> NDArrayFloat:
    return np.stack([table.column(c).to_numpy().astype(np.float64) for c in ("tx_m", "ty_m", "tz_m")], axis=1)


class Av2Adapter:
    """Argoverse 2 scenarios and sensor logs → tracks (see the module docstring).

    Args:
        allow_empty: an input that yields no rows is returned empty instead of an error.
        include_static: keep sensor-log boxes of static classes (bollards, cones, signs) as ``unknown`` tracks.
    """

    name: ClassVar[str] = "argoverse2"
    default_protocol: ClassVar[SampleProtocol] = PROTOCOLS["argoverse2"]
    batch_files: ClassVar[int] = 64
    hashes_while_reading: ClassVar[bool] = False

    def __init__(self, allow_empty: bool = False, include_static: bool = True) -> None:
        self.allow_empty = allow_empty
        self.include_static = include_static

    def sniff(self, path: Path) -> bool:
        """A ``scenario_*.parquet`` file, a folder holding ``city_SE3_egovehicle.feather``, or that file."""
        if path.is_dir():
            return (path / "city_SE3_egovehicle.feather").exists()
        if path.name == "city_SE3_egovehicle.feather":
            return True
        return path.name.startswith("scenario_") and path.suffix == ".parquet"

    def discover(self, root: Path) -> list[Path]:
        """Scenario parquets and sensor-log folders under ``root``, sorted."""
        if root.name == "city_SE3_egovehicle.feather":
            return [root.parent]  # the pose file stands for its sensor-log folder
        if self.sniff(root):
            return [root]
        if not root.is_dir():
            return []
        found = [p for p in root.rglob("scenario_*.parquet") if not p.is_dir()]  # a FIFO is refused, not skipped
        found += [p.parent for p in root.rglob("city_SE3_egovehicle.feather")]
        return sorted(set(found))

    def read(self, sources: Sequence[SourceFile], *, keep_going: bool) -> ParsedLogs:
        """Parse scenarios / sensor logs into track rows (see ``FormatAdapter.read``)."""
        tables: list[pa.Table] = []
        logs: list[LogMeta] = []
        failures: list[SourceError] = []
        for src in sources:
            try:
                require_regular(src.path, src.relpath, folder_ok=True)
                path = Path(src.path)
                table, meta = self._read_sensor_log(src) if path.is_dir() else self._read_scenario(src)
                if table.num_rows == 0 and not self.allow_empty:
                    raise SourceError(src.relpath, "no track rows")
                check_log_id(meta.log_id, src.relpath, "scenario_id" if not path.is_dir() else "log_id")
                check_tracks(table, src.relpath)
            except Exception as exc:  # whatever a damaged file makes pyarrow or numpy raise is this input's failure
                err = as_source_error(exc, src.relpath)
                if not keep_going:
                    raise err from None
                failures.append(err)
                continue
            tables.append(table)
            logs.append(meta)
        tracks = pa.concat_tables(tables) if tables else empty_tracks()
        return ParsedLogs(tracks=tracks, logs=logs, failures=failures)

    # --- motion-forecasting scenario

    def _read_scenario(self, src: SourceFile) -> tuple[pa.Table, LogMeta]:
        rel = src.relpath
        path = Path(src.path)
        try:
            t = pq.read_table(path)
        except (OSError, pa.ArrowException) as err:
            raise SourceError(rel, f"not a readable parquet file: {err}") from None
        _require(t, SCENARIO_COLUMNS, rel)
        if t.num_rows == 0:
            return empty_tracks(), self._scenario_meta(src, path, t, {})
        scenario_id = check_log_id(str(t.column("scenario_id")[0].as_py()), rel, "scenario_id")
        start = float(t.column("start_timestamp")[0].as_py())
        end = float(t.column("end_timestamp")[0].as_py())
        n_steps = int(t.column("num_timestamps")[0].as_py())
        # Checked before any int64 arithmetic: an absurd start/end would wrap the time grid silently.
        for name, value in (("start_timestamp", start), ("end_timestamp", end)):
            if not (math.isfinite(value) and 0 <= value < TIME_LIMIT_NS):
                raise SourceError(rel, f"{value!r} ns is not a finite time in 0..2^62 ns", line=1, field=name)
        if not 1 <= n_steps <= 1_000_000 or end < start:
            raise SourceError(rel, f"{n_steps} timestamps from {start!r} to {end!r} ns is not a time grid",
                              line=1, field="num_timestamps")
        # start/end are float64 ns (64 ns resolution at this magnitude); the grid is exact in whole periods
        period = round((end - start) / max(n_steps - 1, 1))
        # the shortest decimal that round-trips the float is the integer AV2 wrote (no 64 ns float noise)
        start_ns = int(Decimal(repr(start)))
        step = t.column("timestep").to_numpy().astype(np.int64)
        if (step < 0).any() or (step >= n_steps).any():
            bad = int(np.flatnonzero((step < 0) | (step >= n_steps))[0])
            raise SourceError(rel, f"timestep outside 0..{n_steps - 1}", line=bad + 1, field="timestep")
        track = t.column("track_id").to_pylist()
        _check_steps(track, step, rel)
        category = t.column("object_category").to_numpy()
        raw_type = t.column("object_type").to_pylist()
        role = np.where(category == FOCAL_CATEGORY, "focal", "other").astype(object)
        role[np.asarray(track, dtype=object) == EGO_TRACK] = "ego"
        focal = sorted({track[i] for i in np.flatnonzero(category == FOCAL_CATEGORY)})
        if len(focal) != 1:
            raise SourceError(rel, f"expected one focal track (object_category 3), found {len(focal)}",
                              field="object_category")  # fmt: skip
        table = pa.table(
            {
                "log_id": pa.array([scenario_id] * t.num_rows, pa.string()),
                "timestamp_ns": start_ns + step * period,
                "track_id": track,
                "object_type": [SCENARIO_TYPES.get(x, "unknown") for x in raw_type],
                "role": role.tolist(),
                "x": t.column("position_x"),
                "y": t.column("position_y"),
                "heading": t.column("heading"),
                "vx": t.column("velocity_x"),
                "vy": t.column("velocity_y"),
                "source_type": raw_type,
            }
        )
        observed = (
            int(pc.max(t.filter(t.column("observed")).column("timestep")).as_py()) + 1
            if "observed" in t.column_names
            else None
        )
        extra = {
            "scenario_id": scenario_id,
            "focal_track_id": focal[0],
            "num_timestamps": n_steps,
            "observed_steps": observed,
            "period_ns": period,
        }
        return conform_tracks(table), self._scenario_meta(src, path, t, extra)

    def _scenario_meta(self, src: SourceFile, path: Path, t: pa.Table, extra: dict[str, Any]) -> LogMeta:
        city = str(t.column("city")[0].as_py()) if t.num_rows else None
        scenario_id = extra.get("scenario_id") or path.stem.removeprefix("scenario_")
        map_file = path.with_name(f"log_map_archive_{scenario_id}.json")
        attributes = {"kind": "scenario", **extra, "map_file": map_file.name if map_file.exists() else None}
        if map_file.is_file():  # a regular file only: a FIFO of that name would block the read forever
            # newer map archives may name the city; the scenario's own column is the fallback
            with contextlib.suppress(OSError, ValueError):
                city = str(json.loads(map_file.read_text(encoding="utf-8")).get("city_name", city))
        return LogMeta(
            log_id=str(scenario_id), source_format=self.name, source_file=src.relpath, source_sha256=src.sha256,
            map_id=city, frame_rate_hz=10.0, memberships=src.memberships, attributes=attributes,
        )  # fmt: skip

    # --- sensor log

    def _read_sensor_log(self, src: SourceFile) -> tuple[pa.Table, LogMeta]:
        rel = src.relpath
        folder = Path(src.path)
        ann_files = [
            folder / n for n in ("annotations.feather", "annotations_with_ego.feather") if (folder / n).exists()
        ]
        if not ann_files:
            raise SourceError(rel, "sensor log has no annotations.feather or annotations_with_ego.feather")
        require_regular_tree(folder, rel)  # a FIFO here (annotations, map JSON) would block a read forever
        try:
            ego = feather.read_table(folder / "city_SE3_egovehicle.feather")
            boxes = feather.read_table(ann_files[0])
        except (OSError, pa.ArrowException) as err:
            raise SourceError(rel, f"not a readable feather file: {err}") from None
        _require(ego, POSE_COLUMNS, f"{rel}/city_SE3_egovehicle.feather")
        _require(boxes, BOX_COLUMNS, f"{rel}/{ann_files[0].name}")
        _check_poses(ego, f"{rel}/city_SE3_egovehicle.feather", increasing=True)
        _check_poses(boxes, f"{rel}/{ann_files[0].name}", increasing=False)
        # the _with_ego variant has an identity EGO_VEHICLE box per sweep: only its size is news
        ego_box = boxes.filter(pc.equal(boxes.column("category"), "EGO_VEHICLE"))
        ego_size = (
            (float(ego_box.column("length_m")[0].as_py()), float(ego_box.column("width_m")[0].as_py()))
            if ego_box.num_rows
            else None
        )
        boxes = boxes.filter(pc.not_equal(boxes.column("category"), "EGO_VEHICLE"))
        categories = boxes.column("category").to_pylist()
        if not self.include_static:
            keep = np.array([c in SENSOR_TYPES for c in categories], dtype=bool)
            boxes = boxes.filter(pa.array(keep))
            categories = boxes.column("category").to_pylist()

        ego_t = ego.column("timestamp_ns").to_numpy().astype(np.int64)
        order = np.argsort(ego_t, kind="stable")
        ego_t, ego_p, ego_q = ego_t[order], _xyz(ego)[order], _quat(ego)[order]
        box_t = boxes.column("timestamp_ns").to_numpy().astype(np.int64)
        sweeps = np.unique(box_t)
        # ego pose at each sweep: the pose with the same timestamp, else linear between its neighbours
        p_at, q_at, ok = _pose_at(ego_t, ego_p, ego_q, sweeps)
        if not ok.all():
            bad = int(sweeps[~ok][0])
            raise SourceError(f"{rel}/{ann_files[0].name}", f"no ego pose at or around annotation time {bad}",
                              field="timestamp_ns")  # fmt: skip
        k = np.searchsorted(sweeps, box_t)
        pos = quat_rotate(q_at[k], _xyz(boxes)) + p_at[k]
        heading = quat_yaw(quat_mul(q_at[k], _quat(boxes)))
        log_id = folder.name
        n_box, n_ego = boxes.num_rows, len(sweeps)
        table = pa.table(
            {
                "log_id": pa.array([log_id] * (n_box + n_ego), pa.string()),
                "timestamp_ns": np.concatenate([sweeps, box_t]),
                "track_id": ["ego"] * n_ego + boxes.column("track_uuid").to_pylist(),
                "object_type": ["vehicle"] * n_ego + [SENSOR_TYPES.get(c, "unknown") for c in categories],
                "role": ["ego"] * n_ego + ["other"] * n_box,
                "x": np.concatenate([p_at[:, 0], pos[:, 0]]),
                "y": np.concatenate([p_at[:, 1], pos[:, 1]]),
                "heading": np.concatenate([quat_yaw(q_at), heading]),
                "length": pa.concat_arrays([_ego_column(ego_size, 0, n_ego),
                                            boxes.column("length_m").combine_chunks().cast(pa.float64())]),
                "width": pa.concat_arrays([_ego_column(ego_size, 1, n_ego),
                                           boxes.column("width_m").combine_chunks().cast(pa.float64())]),
                "source_type": ["EGO_VEHICLE"] * n_ego + categories,
            }
        )  # fmt: skip
        map_files = sorted((folder / "map").glob("log_map_archive_*.json")) if (folder / "map").is_dir() else []
        city = next((m["city"] for f in map_files if (m := _CITY.search(f.name))), None)
        meta = LogMeta(
            log_id=log_id, source_format=self.name, source_file=src.relpath, source_sha256=src.sha256,
            map_id=city, frame_rate_hz=10.0, memberships=src.memberships,
            attributes={
                "kind": "sensor_log", "annotations_file": ann_files[0].name, "sweeps": n_ego,
                "tracks": len(set(boxes.column("track_uuid").to_pylist())), "ego_pose_rows": ego.num_rows,
                "map_file": map_files[0].name if map_files else None,
            },
        )  # fmt: skip
        return conform_tracks(table), meta


def _check_steps(track: list[Any], step: np.ndarray[Any, Any], rel: str) -> None:
    """Each track's rows must come with strictly increasing ``timestep`` (AV2 writes them so): a repeat is a
    duplicated row, a step back a damaged file."""
    codes = np.unique(np.asarray(track, dtype=object).astype(str), return_inverse=True)[1].reshape(-1)
    same = codes[1:] == codes[:-1]
    bad = np.flatnonzero(same & (step[1:] <= step[:-1]))
    if len(bad):
        row = int(bad[0]) + 1
        what = "duplicated" if step[row] == step[row - 1] else "goes backwards"
        raise SourceError(rel, f"track {track[row]!r}: timestep {what} ({int(step[row - 1])} then {int(step[row])})",
                          line=row + 1, field="timestep")


def _check_poses(table: pa.Table, rel: str, *, increasing: bool) -> None:
    """Poses usable as transforms: finite, a quaternion of non-zero length, a time in 0..2^62 ns (and, for the
    ego trajectory, strictly increasing). A zero quaternion would turn every box it places into NaN."""
    t = table.column("timestamp_ns").to_numpy(zero_copy_only=False)
    if not np.issubdtype(t.dtype, np.integer):
        raise SourceError(rel, f"timestamps are {t.dtype}, not integer nanoseconds", field="timestamp_ns")
    t = t.astype(np.int64)
    outside = (t < 0) | (t >= TIME_LIMIT_NS)
    if outside.any():
        row = int(np.flatnonzero(outside)[0])
        raise SourceError(rel, f"timestamp {int(t[row])} ns is outside 0..2^62 ns", line=row + 1, field="timestamp_ns")
    if increasing and len(t) > 1 and (np.diff(t) <= 0).any():
        row = int(np.flatnonzero(np.diff(t) <= 0)[0]) + 1
        what = "repeats" if t[row] == t[row - 1] else "goes backwards"
        raise SourceError(rel, f"time {what} ({int(t[row - 1])} then {int(t[row])} ns)", line=row + 1,
                          field="timestamp_ns")
    for name in POSE_COLUMNS[1:]:
        values = table.column(name).to_numpy(zero_copy_only=False).astype(np.float64)
        if not np.isfinite(values).all():
            row = int(np.flatnonzero(~np.isfinite(values))[0])
            raise SourceError(rel, f"not finite: {values[row]!r}", line=row + 1, field=name)
    # AV2 writes unit quaternions (float64): one off by more than the tolerance is damage (scaled by 1e-3, it
    # would turn headings silently), not a rotation to normalise.
    off = np.abs(np.linalg.norm(_quat(table), axis=1) - 1.0) > QUAT_TOLERANCE
    if off.any():
        row = int(np.flatnonzero(off)[0])
        norm = float(np.linalg.norm(_quat(table)[row]))
        raise SourceError(rel, f"{int(off.sum())} rows have a rotation quaternion that is not unit length (first: "
                          f"norm {norm:.6g}, tolerance {QUAT_TOLERANCE})", line=row + 1, field="qw")


def _pose_at(
    t: np.ndarray[Any, Any], p: NDArrayFloat, q: NDArrayFloat, at: np.ndarray[Any, Any]
) -> tuple[NDArrayFloat, NDArrayFloat, np.ndarray[Any, Any]]:
    """Poses at times ``at`` (exact match, else interpolation between neighbours; ``ok`` False outside)."""
    i = np.clip(np.searchsorted(t, at, side="right") - 1, 0, max(len(t) - 2, 0))
    ok = (at >= t[0]) & (at <= t[-1]) if len(t) else np.zeros(len(at), dtype=bool)
    if len(t) < 2:
        exact = t[0] == at if len(t) else ok
        return np.repeat(p[:1], len(at), axis=0), np.repeat(q[:1], len(at), axis=0), exact & ok
    w = np.clip((at - t[i]) / np.maximum(t[i + 1] - t[i], 1), 0.0, 1.0)[:, None]
    q1 = np.where(np.sum(q[i] * q[i + 1], axis=1, keepdims=True) < 0, -q[i + 1], q[i + 1])
    qq = q[i] * (1 - w) + q1 * w
    return p[i] * (1 - w) + p[i + 1] * w, qq / np.linalg.norm(qq, axis=1, keepdims=True), ok


def _ego_column(size: tuple[float, float] | None, i: int, n: int) -> pa.Array:
    """The ego's length (i=0) or width (i=1) repeated ``n`` times, or nulls when unknown."""
    return pa.array([size[i]] * n, pa.float64()) if size else pa.nulls(n, pa.float64())
