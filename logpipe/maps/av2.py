"""Argoverse 2 map JSON (``log_map_archive_*.json``): lane segments, drivable areas, pedestrian crossings.

Coordinates are the AV2 city frame in metres (the same frame as the scenario parquet and, for PIT/MIA,
the AV1 city frames). Top-level keys ``lane_segments``, ``drivable_areas``, ``pedestrian_crossings``, each
a dict keyed by id:

* lane segment: ``left_lane_boundary`` / ``right_lane_boundary`` lists of ``{x, y, z}`` in travel order,
  ``centerline`` (newer files only), ``is_intersection``, ``lane_type``, ``*_lane_mark_type``,
  ``left_neighbor_id``, ``right_neighbor_id``, ``predecessors``, ``successors``;
* drivable area: ``area_boundary`` (a ring);
* pedestrian crossing: ``edge1`` and ``edge2``, two parallel 2-point edges pointing the same way.

Where a lane has no centerline it is computed (``derived=True``) by resampling both boundaries to the
same number of points by arc length and averaging them.
"""

from __future__ import annotations

import json
import re
from pathlib import Path
from typing import Any

import numpy as np

from logpipe.errors import SourceError
from logpipe.maps.feature_kinds import FeatureKind
from logpipe.maps.store import MapBuilder, MapStore
from logpipe.types import NDArrayFloat

SOURCE = "av2_json"
_NAME_RE = re.compile(r"log_map_archive_(?P<log>[0-9a-f-]+)(?:_+(?P<city>[A-Za-z]+_city_\d+))?\.json$")
CENTERLINE_SPACING_M = 2.0
"""Target vertex spacing of derived centerlines, metres (fine enough for 0.45 m/px rasters on curves)."""


def sniff(path: Path) -> bool:
    """A ``.json`` that starts like an AV2 map archive."""
    if path.suffix != ".json":
        return False
    with path.open("rb") as fh:
        head = fh.read(4096)
    return any(k in head for k in (b'"lane_segments"', b'"drivable_areas"', b'"pedestrian_crossings"'))


def names_from_path(path: Path) -> tuple[str | None, str | None]:
    """(log id, city map name such as ``PIT_city_57819``) from an AV2 map file name, when present."""
    m = _NAME_RE.search(path.name)
    if not m:
        return None, None
    return m.group("log"), m.group("city")


def _xy(points: Any, name: str, where: str) -> NDArrayFloat:
    try:
        return np.array([[float(p["x"]), float(p["y"])] for p in points], dtype=np.float64).reshape(-1, 2)
    except (KeyError, TypeError, ValueError) as exc:
        raise SourceError(name, f"expected a list of {{x, y, z}} points: {exc}", field=where) from exc


def resample(polyline: NDArrayFloat, n: int) -> NDArrayFloat:
    """``n`` points spaced evenly by arc length along ``polyline`` (first and last kept)."""
    seg = np.linalg.norm(np.diff(polyline, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    if s[-1] <= 0:
        return np.repeat(polyline[:1], n, axis=0)
    t = np.linspace(0.0, s[-1], n)
    return np.stack([np.interp(t, s, polyline[:, 0]), np.interp(t, s, polyline[:, 1])], axis=1)


def centerline_from_boundaries(left: NDArrayFloat, right: NDArrayFloat) -> NDArrayFloat:
    """Average of the two boundaries after resampling both to the same number of points."""
    length = max(
        float(np.linalg.norm(np.diff(left, axis=0), axis=1).sum()),
        float(np.linalg.norm(np.diff(right, axis=0), axis=1).sum()),
    )
    n = int(np.clip(max(len(left), len(right), np.ceil(length / CENTERLINE_SPACING_M - 1e-3) + 1), 2, 200))
    return (resample(left, n) + resample(right, n)) / 2.0


def _id_or_none(v: Any) -> str | None:
    return None if v is None else str(v)


def load(path: Path, map_id: str | None = None) -> MapStore:
    """Read an AV2 map archive into a ``MapStore``.

    Args:
        path: the JSON file.
        map_id: map name; defaults to the ``<CITY>_city_<n>`` part of the file name, else the log id.

    Raises:
        SourceError: not JSON, or a feature without the geometry it needs (named by feature id).
    """
    name = str(path)
    try:
        with path.open(encoding="utf-8") as fh:
            doc = json.load(fh)
    except (OSError, json.JSONDecodeError) as exc:
        raise SourceError(name, f"not readable JSON: {exc}") from exc
    if not isinstance(doc, dict) or not ({"lane_segments", "drivable_areas"} & set(doc)):
        raise SourceError(name, "no lane_segments or drivable_areas: not an AV2 map archive")
    log_id, city = names_from_path(path)
    builder = MapBuilder(map_id or city or log_id or path.stem, SOURCE)
    seen_bounds: set[bytes] = set()
    for key, lane in sorted(doc.get("lane_segments", {}).items()):
        lid = str(lane.get("id", key))
        where = f"lane_segments[{lid}]"
        left = _xy(lane.get("left_lane_boundary", []), name, f"{where}.left_lane_boundary")
        right = _xy(lane.get("right_lane_boundary", []), name, f"{where}.right_lane_boundary")
        attrs: dict[str, Any] = {
            "lane_id": lid,
            "is_intersection": lane.get("is_intersection"),
            "lane_type": lane.get("lane_type"),
            "left_neighbor_id": _id_or_none(lane.get("left_neighbor_id")),
            "right_neighbor_id": _id_or_none(lane.get("right_neighbor_id")),
            "predecessors": [str(p) for p in lane.get("predecessors") or []],
            "successors": [str(s) for s in lane.get("successors") or []],
        }
        if lane.get("centerline"):
            centre = _xy(lane["centerline"], name, f"{where}.centerline")
            derived = False
        elif len(left) >= 2 and len(right) >= 2:
            centre = centerline_from_boundaries(left, right)
            derived = True
        else:
            raise SourceError(name, "lane has neither a centerline nor two boundaries", field=where)
        builder.add(FeatureKind.LANE_CENTERLINE, lid, centre, derived=derived, direction="forward", **attrs)
        for side, geom in (("left", left), ("right", right)):
            # Neighbouring lanes share a boundary; keep one copy so it is not drawn twice (AA overdraw).
            k1 = np.round(geom, 2).tobytes()
            k2 = np.round(geom[::-1], 2).tobytes()
            if k1 in seen_bounds or k2 in seen_bounds:
                continue
            seen_bounds.add(k1)
            builder.add(
                FeatureKind.LANE_BOUNDARY,
                f"{lid}:{side}",
                geom,
                lane_id=lid,
                side=side,
                mark_type=lane.get(f"{side}_lane_mark_type"),
            )
    for key, area in sorted(doc.get("drivable_areas", {}).items()):
        aid = str(area.get("id", key))
        ring = _xy(area.get("area_boundary", []), name, f"drivable_areas[{aid}].area_boundary")
        builder.add(FeatureKind.DRIVABLE_AREA, aid, ring)
    for key, cross in sorted(doc.get("pedestrian_crossings", {}).items()):
        cid = str(cross.get("id", key))
        e1 = _xy(cross.get("edge1", []), name, f"pedestrian_crossings[{cid}].edge1")
        e2 = _xy(cross.get("edge2", []), name, f"pedestrian_crossings[{cid}].edge2")
        if len(e1) < 2 or len(e2) < 2:
            raise SourceError(name, "crossing edges need 2 points each", field=f"pedestrian_crossings[{cid}]")
        # Both edges point the same way, so edge1 followed by edge2 reversed walks round the crossing.
        builder.add(FeatureKind.CROSSING, cid, np.vstack([e1, e2[::-1]]))
    return builder.build()
