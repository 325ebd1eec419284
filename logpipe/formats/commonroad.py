"""CommonRoad scenario XML → tracks: one log per scenario, one track per dynamic obstacle, and the scenario's map.

A file (format 2018b: ``<obstacle>`` with ``<role>dynamic</role>``; 2020a and later of the same schema:
``<dynamicObstacle>``) holds one scenario in its own local metric frame. Field mapping (docs/formats.md):

* log: ``log_id`` = the ``benchmarkID`` attribute (``USA_US101-9_1_T-1``); ``map_id`` = the same (each scenario
  carries its own lanelet map in its own frame, written into the dataset by ingest, see
  ``logpipe.maps.commonroad``); attributes ``location`` (the benchmark id's ``<country>_<scene>`` part,
  ``USA_US101``), ``synthetic`` (a generated scenario: ``source`` starts with ``SYNTHETIC``, membership
  ``synthetic``), ``commonroad_version``, ``time_step_s``, ``source``, ``tags``, ``static_obstacles``,
  ``resampled_from_hz``; membership ``location/<location>`` so a split can hold a location out
  (``--filter split=location/USA_US101``, ``--train-split all-location/USA_US101``).
* track per dynamic obstacle: ``track_id`` = obstacle id, ``object_type`` from ``<type>`` (``OBJECT_TYPES``;
  the raw type is ``source_type``), role ``other`` (the planning problem's vehicle is not a recorded agent, so a
  CommonRoad log has no ego), ``length``/``width`` from a ``rectangle`` shape (a ``circle``: its diameter both ways).
* row per state (``initialState`` + ``trajectory/state``): ``timestamp_ns`` = ``<time><exact>`` step x
  ``timeStepSize`` (exact, in ns), ``x``/``y`` = ``<position><point>``, ``heading`` = ``<orientation>``,
  ``vx``/``vy`` = ``<velocity>`` along the orientation (or, with ``<velocityY>``, the point-mass model's
  world-frame components).

A scenario recorded at another step than the protocol's (drone datasets: 0.04 s, 0.2 s) is resampled to ``hz`` as
bags are (``logpipe.dataset.resample``: linear, no extrapolation, no bridging of gaps). A state with a gap in its
time steps, time going backwards, a missing or non-finite field, an interval where an exact value belongs, or an
unknown obstacle type is refused with one error naming the file, line, obstacle and field.
"""

from __future__ import annotations

import hashlib
import math
import re
from collections.abc import Sequence
from dataclasses import dataclass
from decimal import Decimal, InvalidOperation
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
import pyarrow as pa
from lxml import etree

from logpipe.dataset.resample import ResampleSpec, resample_track
from logpipe.errors import SourceError
from logpipe.formats.base import (
    TIME_LIMIT_NS,
    ParsedLogs,
    as_source_error,
    check_log_id,
    check_tracks,
    conform_tracks,
    empty_tracks,
    files_with_suffix,
    require_regular,
)
from logpipe.maps import commonroad as crmap
from logpipe.maps.store import MapStore
from logpipe.types import PROTOCOLS, LogMeta, NDArrayFloat, ObjectType, Role, SampleProtocol, SourceFile

OBSTACLE_TYPES: dict[str, ObjectType] = {
    "car": ObjectType.VEHICLE, "taxi": ObjectType.VEHICLE, "priorityVehicle": ObjectType.VEHICLE,
    "parkedVehicle": ObjectType.VEHICLE, "truck": ObjectType.BUS_TRUCK, "bus": ObjectType.BUS_TRUCK,
    "motorcycle": ObjectType.MOTORCYCLIST, "bicycle": ObjectType.CYCLIST, "pedestrian": ObjectType.PEDESTRIAN,
    "train": ObjectType.UNKNOWN, "unknown": ObjectType.UNKNOWN, "constructionZone": ObjectType.UNKNOWN,
    "roadBoundary": ObjectType.UNKNOWN, "building": ObjectType.UNKNOWN, "pillar": ObjectType.UNKNOWN,
    "median_strip": ObjectType.UNKNOWN,
}
"""CommonRoad's obstacle types (its ``ObstacleType`` vocabulary, 2018b-2020a) → ours; any other word is refused."""
MAX_TIME_STEP_S = 10.0
STATE_LIMIT = 1e5
"""Largest |value| of an obstacle state (position in m, velocity in m/s, ...): a CommonRoad scenario is a local
frame a few km across (the real ones here stay within 210 m of the origin), so 100 km is damage; velocities are
bounded tighter by ``logpipe.formats.motion_checks``."""
"""Largest ``timeStepSize`` accepted, seconds (recordings use 0.04-0.2 s)."""
_LOCATION = re.compile(r"^([A-Z]{2,3}_[A-Za-z0-9]+)-")
SYNTHETIC_SOURCE = "SYNTHETIC"
"""How a generated scenario's ``source`` attribute starts: its log is marked ``synthetic`` (attribute and
membership), so simulated traffic is never taken for a recording."""
SYNTHETIC_PREFIX = "synthetic_"
"""How a generated scenario's benchmark id starts; the location is read from the rest (``synthetic_USA_US101-...``
is at ``USA_US101``, so holding a location out holds out its simulated traffic too)."""


@dataclass
class _Track:
    """One dynamic obstacle's states, before they become rows (metres, rad, m/s; ``steps`` in time steps)."""

    track_id: str
    source_type: str
    object_type: str
    length: float | None
    width: float | None
    steps: np.ndarray
    values: dict[str, NDArrayFloat]


class CommonRoadAdapter:
    """CommonRoad scenario files → tracks and per-log lanelet maps (see the module docstring).

    Args:
        hz: rate of the output rows; scenarios recorded at another step are resampled to it.
    """

    name: ClassVar[str] = "commonroad"
    default_protocol: ClassVar[SampleProtocol] = PROTOCOLS["commonroad"]
    batch_files: ClassVar[int] = 8
    hashes_while_reading: ClassVar[bool] = True  # read() hashes the bytes it parses

    def __init__(self, hz: float = 10.0) -> None:
        if not (math.isfinite(hz) and 0 < hz <= 1000):
            raise ValueError(f"hz must be in (0, 1000], got {hz}")
        self.spec = ResampleSpec(hz=hz)

    def sniff(self, path: Path) -> bool:
        """An ``.xml`` file opening a ``<commonRoad>`` element."""
        return crmap.sniff(path)

    def discover(self, root: Path) -> list[Path]:
        """CommonRoad files (``.xml``, ``.xml.gz``) under ``root`` (or ``root`` itself), in path order."""
        return [p for p in files_with_suffix(root, (".xml", ".xml.gz")) if self.sniff(p)]

    def read(self, sources: Sequence[SourceFile], *, keep_going: bool) -> ParsedLogs:
        """Parse ``sources`` (see ``FormatAdapter.read``); each log's lanelet map is in ``ParsedLogs.maps``."""
        tables: list[pa.Table] = []
        logs: list[LogMeta] = []
        maps: dict[str, MapStore] = {}
        failures: list[SourceError] = []
        for src in sources:
            try:
                require_regular(src.path, src.relpath)
                table, meta, store = self.read_scenario(src)
                check_tracks(table, src.relpath)
            except Exception as exc:  # whatever a damaged file makes the parser raise is this input's failure
                err = as_source_error(exc, src.relpath)
                if not keep_going:
                    raise err from None
                failures.append(err)
                continue
            tables.append(table)
            logs.append(meta)
            maps[meta.log_id] = store
        tracks = pa.concat_tables(tables) if tables else empty_tracks()
        return ParsedLogs(tracks=tracks, logs=logs, failures=failures, maps=maps)

    def read_scenario(self, src: SourceFile) -> tuple[pa.Table, LogMeta, MapStore]:
        """One file's rows, log metadata and map."""
        name = src.relpath
        raw = Path(src.path).read_bytes()
        data = crmap.read_scenario_bytes(Path(src.path), name) if name.endswith(".gz") else raw
        root = crmap.parse_scenario(data, name)
        log_id = check_log_id(root.get("benchmarkID") or "", name, "benchmarkID")
        step_ns = _time_step_ns(root, name)
        obstacles = _dynamic_obstacles(root)
        tracks = [_track(el, name) for el in obstacles]
        _refuse_repeated_ids(tracks, obstacles, name)
        period = self.spec.period_ns
        resample = step_ns != period
        table = _rows(log_id, tracks, step_ns, self.spec if resample else None, name)
        location = _location(log_id)
        synthetic = (root.get("source") or "").startswith(SYNTHETIC_SOURCE)
        attributes: dict[str, Any] = {
            "location": location, "synthetic": synthetic, "commonroad_version": root.get("commonRoadVersion"),
            "time_step_s": float(Decimal(step_ns) / Decimal(10**9)), "source": root.get("source"),
            "tags": _tags(root), "static_obstacles": len(_static_obstacles(root)),
            "resampled_from_hz": round(1e9 / step_ns, 6) if resample else None,
        }
        meta = LogMeta(log_id=log_id, source_format=self.name, source_file=name,
                       source_sha256=hashlib.sha256(raw).hexdigest(), map_id=log_id,
                       frame_rate_hz=1e9 / (period if resample else step_ns),
                       memberships=(*src.memberships, *([f"location/{location}"] if location else []),
                                    *(["synthetic"] if synthetic else [])),
                       attributes=attributes)
        return conform_tracks(table), meta, crmap.lanelet_map(root, log_id, name)


def _location(benchmark_id: str) -> str | None:
    found = _LOCATION.match(benchmark_id.removeprefix(SYNTHETIC_PREFIX))
    return found.group(1) if found else None


def _tags(root: etree._Element) -> list[str]:
    """The scenario's tags: 2018b's ``tags`` attribute, 2020a's ``<scenarioTags>`` children."""
    words = (root.get("tags") or "").split()
    holder = root.find("scenarioTags")
    if holder is not None:
        words += [str(child.tag) for child in holder if isinstance(child.tag, str)]
    return words


def _time_step_ns(root: etree._Element, name: str) -> int:
    text = root.get("timeStepSize")
    try:
        step = Decimal(text) if text is not None else None
    except InvalidOperation:
        step = None
    if step is None or not step.is_finite() or not 0 < step <= MAX_TIME_STEP_S:
        raise SourceError(name, f"timeStepSize {text!r} is not a step in (0, {MAX_TIME_STEP_S:g}] s",
                          line=root.sourceline, field="timeStepSize")
    return int((step * 10**9).to_integral_value())


def _dynamic_obstacles(root: etree._Element) -> list[etree._Element]:
    """2020a ``<dynamicObstacle>`` elements and 2018b ``<obstacle>`` elements whose role is dynamic."""
    found = list(root.iterchildren("dynamicObstacle"))
    found += [el for el in root.iterchildren("obstacle") if (el.findtext("role") or "").strip() == "dynamic"]
    return found


def _static_obstacles(root: etree._Element) -> list[etree._Element]:
    return [*root.iterchildren("staticObstacle"),
            *(el for el in root.iterchildren("obstacle") if (el.findtext("role") or "").strip() != "dynamic")]


def _track(el: etree._Element, name: str) -> _Track:
    """One dynamic obstacle (errors name the file, line, obstacle id and field)."""
    obstacle_id = (el.get("id") or "").strip()
    if not obstacle_id or not obstacle_id.isprintable():
        raise SourceError(name, f"an obstacle has no usable id ({obstacle_id[:40]!r})", line=el.sourceline,
                          field="id")
    where = f"obstacle {obstacle_id}"
    raw_type = (el.findtext("type") or "").strip()
    if raw_type not in OBSTACLE_TYPES:
        known = ", ".join(sorted(OBSTACLE_TYPES))
        raise SourceError(name, f"{where}: unknown obstacle type {raw_type[:40]!r} (CommonRoad types: {known})",
                          line=el.sourceline, field="type")
    length, width = _size(el.find("shape"), name, where)
    initial = el.find("initialState")
    if initial is None:
        raise SourceError(name, f"{where}: <initialState> is missing", line=el.sourceline, field="initialState")
    states = [initial, *el.iterfind("trajectory/state")]
    steps, values = _states(el, states, name, where)
    return _Track(obstacle_id, raw_type, OBSTACLE_TYPES[raw_type].value, length, width, steps, values)


def _size(shape: etree._Element | None, name: str, where: str) -> tuple[float | None, float | None]:
    """(length, width) in metres from a rectangle (a circle: its diameter); (None, None) for other shapes."""
    if shape is None:
        raise SourceError(name, f"{where}: <shape> is missing", field="shape")
    rectangle, circle = shape.find("rectangle"), shape.find("circle")
    if rectangle is not None:
        return (_positive(rectangle, "length", name, where), _positive(rectangle, "width", name, where))
    if circle is not None:
        diameter = 2.0 * _positive(circle, "radius", name, where)
        return diameter, diameter
    return None, None


def _positive(el: etree._Element, tag: str, name: str, where: str) -> float:
    value = crmap.number(el, tag, name, f"{where} shape")
    if value <= 0:
        raise SourceError(name, f"{where}: shape {tag} {value!r} is not positive", line=el.sourceline, field=tag)
    return value


_STATE_PATHS = {"time": "time/exact", "x": "position/point/x", "y": "position/point/y",
                "orientation": "orientation/exact", "velocity": "velocity/exact", "velocityY": "velocityY/exact"}
"""Where each value of a state is (``<time><exact>`` ...), in the order of ``_state``'s tuple."""
_STATES = "(initialState|trajectory/state)"


def _states(el: etree._Element, states: list[etree._Element], name: str,
            where: str) -> tuple[np.ndarray, dict[str, NDArrayFloat]]:
    """Time steps and values of an obstacle's states (NaN where an optional field is absent)."""
    table = _states_fast(el, len(states))
    if table is None:  # something is off: read state by state, which names the state and field at fault
        table = np.array([_state(state, name, f"{where}, {'initialState' if i == 0 else f'trajectory state {i}'}")
                          for i, state in enumerate(states)], dtype=np.float64).reshape(-1, len(_STATE_PATHS))
    steps = table[:, 0].astype(np.int64)
    jumps = np.diff(steps)
    if (jumps != 1).any():
        i = int(np.flatnonzero(jumps != 1)[0])
        what = ("goes backwards" if jumps[i] < 0 else "repeats") if jumps[i] <= 0 else f"skips {jumps[i] - 1} step(s)"
        raise SourceError(name, f"{where}: time {what}: step {steps[i]} then {steps[i + 1]} (states {i} and "
                          f"{i + 1}); a recorded trajectory has one state per time step",
                          line=states[i + 1].sourceline, field="time")
    heading, speed, vy = table[:, 3], table[:, 4], table[:, 5]
    world_vy = np.isfinite(vy)  # the point-mass model's velocity/velocityY are world-frame components
    values = {"x": table[:, 1], "y": table[:, 2], "heading": heading,
              "vx": np.where(world_vy, speed, speed * np.cos(heading)),
              "vy": np.where(world_vy, vy, speed * np.sin(heading))}
    return steps, values


def _states_fast(el: etree._Element, n: int) -> np.ndarray | None:
    """(n, 6) state values by one XPath query per field (~20x faster than element by element), or None when any
    state lacks a required field, has one twice, holds a non-number or an absurd value: the slow path then says
    which."""
    table = np.full((n, len(_STATE_PATHS)), np.nan)
    given = np.zeros(len(_STATE_PATHS), dtype=bool)
    for column, (field, path) in enumerate(_STATE_PATHS.items()):
        texts = el.xpath(f"{_STATES}/{path}/text()")
        if not texts and field not in ("time", "x", "y"):
            continue  # optional and absent everywhere
        if len(texts) != n or el.xpath(f"count({_STATES}[count({path}) != 1])"):
            return None  # absent in some states, or twice in one: the texts would not line up with the states
        try:
            table[:, column] = np.asarray(texts, dtype=np.int64 if field == "time" else np.float64)
        except ValueError:
            return None
        given[column] = True
    values = table[:, given]
    if not np.isfinite(values).all() or (np.abs(values[:, 1:]) > STATE_LIMIT).any():
        return None
    if (table[:, 0] < 0).any() or (table[:, 0] >= 1 << 40).any():
        return None
    return table


def _state(state: etree._Element, name: str, label: str) -> tuple[float, ...]:
    """(time step, x, y, orientation, velocity, velocityY) of one state; NaN for absent optional fields."""
    time_text = _exact(state, "time", name, label, required=True)
    try:
        step = int(time_text) if time_text is not None else -1
    except ValueError:
        raise SourceError(name, f"{label}: <time> {time_text!r} is not a whole time step", line=state.sourceline,
                          field="time") from None
    if not 0 <= step < 1 << 40:
        raise SourceError(name, f"{label}: <time> {step} is outside 0..2^40 steps", line=state.sourceline,
                          field="time")
    point = state.find("position/point")
    if point is None:
        what = "an area (an uncertain position)" if state.find("position") is not None else "missing"
        raise SourceError(name, f"{label}: <position> is {what}; a recorded state has a <point>",
                          line=state.sourceline, field="position")
    x = crmap.number(point, "x", name, label)
    y = crmap.number(point, "y", name, label)
    optional = [_exact(state, tag, name, label, required=False) for tag in ("orientation", "velocity", "velocityY")]
    return (step, x, y, *(_float(v, state, tag, name, label) for v, tag in
                          zip(optional, ("orientation", "velocity", "velocityY"), strict=True)))


def _exact(state: etree._Element, tag: str, name: str, label: str, *, required: bool) -> str | None:
    """The text of ``<tag><exact>``; an interval or a missing required field is an error."""
    el = state.find(tag)
    if el is None:
        if required:
            raise SourceError(name, f"{label}: <{tag}> is missing", line=state.sourceline, field=tag)
        return None
    text = el.findtext("exact")
    if text is None:
        raise SourceError(name, f"{label}: <{tag}> has no <exact> value (an interval is an uncertain state, not a "
                          "recorded one)", line=el.sourceline, field=tag)
    return str(text).strip()


def _float(text: str | None, state: etree._Element, tag: str, name: str, label: str) -> float:
    if text is None:
        return math.nan
    try:
        value = float(text)
    except ValueError:
        value = math.nan
        text = f"{text[:40]!r} (not a number)"
    if not math.isfinite(value) or abs(value) > STATE_LIMIT:
        raise SourceError(name, f"{label}: <{tag}> is {text}: not finite or absurd (|value| over {STATE_LIMIT:.0e})",
                          line=state.sourceline,
                          field=tag)
    return value


def _refuse_repeated_ids(tracks: list[_Track], obstacles: list[etree._Element], name: str) -> None:
    seen: set[str] = set()
    for track, el in zip(tracks, obstacles, strict=True):
        if track.track_id in seen:
            raise SourceError(name, f"obstacle {track.track_id}: the id is used twice", line=el.sourceline,
                              field="id")
        seen.add(track.track_id)


def _rows(log_id: str, tracks: list[_Track], step_ns: int, spec: ResampleSpec | None, name: str) -> pa.Table:
    """The canonical rows of all tracks (resampled to ``spec`` when given; times in ns from time step 0)."""
    last = max((int(t.steps[-1]) for t in tracks), default=0)
    if last * step_ns >= TIME_LIMIT_NS:
        raise SourceError(name, f"time step {last} x {step_ns} ns is beyond 2^62 ns", field="time")
    columns: dict[str, list[Any]] = {k: [] for k in ("timestamp_ns", "track_id", "object_type", "x", "y",
                                                     "heading", "vx", "vy", "length", "width", "source_type")}
    for track in tracks:
        times = track.steps * step_ns
        values = track.values
        if spec is not None:
            times, values = resample_track(times, values, spec)
        n = len(times)
        columns["timestamp_ns"].append(times)
        for key in ("x", "y", "heading", "vx", "vy"):
            columns[key].append(values[key])
        for key, value in (("track_id", track.track_id), ("object_type", track.object_type),
                           ("length", track.length), ("width", track.width), ("source_type", track.source_type)):
            columns[key].append([value] * n)
    if not tracks:
        return empty_tracks()
    flat = {k: np.concatenate(v) if k in ("timestamp_ns", "x", "y", "heading", "vx", "vy")
            else [x for part in v for x in part] for k, v in columns.items()}
    n_rows = len(flat["timestamp_ns"])
    return pa.table({
        "log_id": pa.array([log_id] * n_rows, pa.string()),
        "timestamp_ns": pa.array(flat["timestamp_ns"], pa.int64()),
        "track_id": pa.array(flat["track_id"], pa.string()),
        "object_type": pa.array(flat["object_type"], pa.string()),
        "role": pa.array([Role.OTHER.value] * n_rows, pa.string()),
        # NaN (an optional field the source lacks) becomes null; a mask, since from_pandas would import pandas
        **{k: pa.array(flat[k], pa.float64(), mask=np.isnan(flat[k])) for k in ("x", "y", "heading", "vx", "vy")},
        "length": pa.array(flat["length"], pa.float64()),
        "width": pa.array(flat["width"], pa.float64()),
        "source_type": pa.array(flat["source_type"], pa.string()),
    })

