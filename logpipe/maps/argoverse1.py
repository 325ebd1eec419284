"""Argoverse 1 maps: the pickle-free lane-centerline ``.npz`` and the official vector-map XML.

Both are in the AV1 city frame of their city (MIA or PIT), metres, the same frame as the forecasting CSVs.

* ``{CITY}_lane_centerlines.npz``: arrays ``lane_ids`` (L,) int64, ``offsets`` (L+1,) int64 and
  ``points`` (N, 2) float64; lane ``i`` is ``points[offsets[i]:offsets[i+1]]``. Centerlines only. Loaded
  with ``allow_pickle=False``: the original ``*_array`` pickles are never opened.
* ``pruned_argoverse_{CITY}_{ID}_vector_map.xml``: an OSM-like document whose ``<node id x y [height]>``
  elements are centerline vertices and whose ``<way lane_id=...>`` elements are lane segments, with
  ``<nd ref>`` children in travel order and ``<tag k v>`` children ``has_traffic_control``,
  ``turn_direction`` (NONE/LEFT/RIGHT), ``is_intersection``, ``l_neighbor_id``, ``r_neighbor_id`` (an id
  or ``None``) and repeated ``predecessor`` / ``successor``.
"""

from __future__ import annotations

import re
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pyarrow as pa

from logpipe.errors import SourceError
from logpipe.maps.feature_kinds import FeatureKind
from logpipe.maps.store import MAP_COORD_LIMIT_M, MapBuilder, MapStore, map_schema

NPZ_SOURCE = "argoverse1_npz"
XML_SOURCE = "argoverse1_xml"
_CITY_RE = re.compile(r"(?:^|[^A-Za-z])(MIA|PIT)(?:[^A-Za-z]|$)")
_XML_RE = re.compile(r"pruned_argoverse_([A-Za-z]+)_\d+_vector_map")


def city_from_name(path: Path) -> str | None:
    """City from an AV1 map file name: ``pruned_argoverse_<CITY>_<id>_vector_map.xml`` or a name that
    contains ``MIA`` / ``PIT`` as a word (``MIA_lane_centerlines.npz``)."""
    m = _XML_RE.search(path.name)
    if m:
        return m.group(1)
    m = _CITY_RE.search(path.name)
    return m.group(1) if m else None


def sniff_npz(path: Path) -> bool:
    """A zip (``.npz``) that holds the three lane-centerline arrays."""
    if path.suffix != ".npz":
        return False
    try:
        with np.load(path, allow_pickle=False) as z:
            return {"lane_ids", "offsets", "points"} <= set(z.files)
    except (OSError, ValueError):
        return False


def load_npz(path: Path, map_id: str | None = None) -> MapStore:
    """Lane centerlines from a derived AV1 ``.npz``.

    Args:
        path: the ``.npz``.
        map_id: city name; defaults to the one in the file name.

    Raises:
        SourceError: missing arrays, inconsistent offsets or non-finite points.
    """
    name = str(path)
    try:
        with np.load(path, allow_pickle=False) as z:
            lane_ids = np.asarray(z["lane_ids"], dtype=np.int64)
            offsets = np.asarray(z["offsets"], dtype=np.int64)
            points = np.asarray(z["points"], dtype=np.float64)
    except KeyError as exc:
        raise SourceError(name, f"missing array {exc}") from exc
    except (OSError, ValueError) as exc:
        raise SourceError(name, f"not a pickle-free lane-centerline npz: {exc}") from exc
    if points.ndim != 2 or points.shape[1] != 2:
        raise SourceError(name, f"points has shape {points.shape}, expected (N, 2)", field="points")
    if len(offsets) != len(lane_ids) + 1 or offsets[0] != 0 or offsets[-1] != len(points):
        raise SourceError(name, "offsets do not cover points with one entry per lane + 1", field="offsets")
    if np.any(np.diff(offsets) < 2):
        raise SourceError(name, "a lane has fewer than 2 points", field="offsets")
    if not (np.abs(points) < MAP_COORD_LIMIT_M).all():  # NaN, inf and 1e300 alike (the store's one rule)
        raise SourceError(name, f"coordinates not finite or beyond {MAP_COORD_LIMIT_M:.0e} m", field="points")
    city = map_id or city_from_name(path) or path.stem
    # Build the Arrow table straight from the flat arrays: 12k lanes, no per-lane Python objects.
    n = len(lane_ids)
    order = np.argsort(lane_ids, kind="stable")
    if not np.array_equal(order, np.arange(n)):
        counts = np.diff(offsets)[order]
        points = np.concatenate([points[offsets[i] : offsets[i + 1]] for i in order.tolist()])
        lane_ids = lane_ids[order]
        offsets = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
    ids = pa.array([str(i) for i in lane_ids.tolist()], type=pa.string())
    off32 = pa.array(offsets.astype(np.int32))
    schema = map_schema()
    cols: dict[str, pa.Array] = {
        "map_id": pa.array([city] * n, type=pa.string()),
        "feature_id": ids,
        "kind": pa.array([str(FeatureKind.LANE_CENTERLINE)] * n, type=pa.string()),
        "xs": pa.ListArray.from_arrays(off32, pa.array(points[:, 0])),
        "ys": pa.ListArray.from_arrays(off32, pa.array(points[:, 1])),
        "lane_id": ids,
        "direction": pa.array(["forward"] * n, type=pa.string()),
        "derived": pa.array([False] * n, type=pa.bool_()),
        "source": pa.array([NPZ_SOURCE] * n, type=pa.string()),
    }
    arrays = [cols[f.name] if f.name in cols else pa.nulls(n, f.type) for f in schema]
    return MapStore(pa.Table.from_arrays(arrays, schema=schema))


def sniff_xml(path: Path) -> bool:
    """An XML whose ways carry ``lane_id`` attributes (AV1), as opposed to Lanelet2 OSM relations."""
    if path.suffix.lower() != ".xml":
        return False
    with path.open("rb") as fh:
        head = fh.read(1 << 16)
    return b"lane_id=" in head or (b"<way" not in head and b"<node" in head and b"x=" in head)


def _bool(value: str, name: str, where: str) -> bool:
    if value in ("True", "true", "1"):
        return True
    if value in ("False", "false", "0"):
        return False
    raise SourceError(name, f"expected True/False, got {value!r}", line=None, field=where)


def load_xml(path: Path, map_id: str | None = None) -> MapStore:
    """Lane segments from an AV1 vector-map XML.

    Raises:
        SourceError: malformed XML, a way without ``lane_id``, an ``nd`` that names an unknown node, bad
            boolean tags. The error names the lane id as the record.
    """
    name = str(path)
    try:
        root = ET.parse(path).getroot()
    except ET.ParseError as exc:
        raise SourceError(name, f"malformed XML: {exc}", line=exc.position[0]) from exc
    nodes: dict[str, tuple[float, float]] = {}
    for el in root.iter("node"):
        try:
            nodes[el.attrib["id"]] = (float(el.attrib["x"]), float(el.attrib["y"]))
        except (KeyError, ValueError) as exc:
            raise SourceError(name, f"node without numeric id/x/y: {el.attrib}", field="node") from exc
    builder = MapBuilder(map_id or city_from_name(path) or path.stem, XML_SOURCE)
    for k, way in enumerate(root.iter("way")):
        lane = way.attrib.get("lane_id")
        if lane is None:
            raise SourceError(name, f"way #{k} has no lane_id attribute", line=k, field="lane_id")
        tags: dict[str, str] = {}
        preds: list[str] = []
        succs: list[str] = []
        refs: list[str] = []
        for child in way:
            if child.tag == "nd":
                refs.append(child.attrib.get("ref", ""))
            elif child.tag == "tag":
                key, value = child.attrib.get("k", ""), child.attrib.get("v", "")
                if key == "predecessor":
                    preds.append(value)
                elif key == "successor":
                    succs.append(value)
                else:
                    tags[key] = value
        missing = [r for r in refs if r not in nodes]
        if missing:
            raise SourceError(name, f"lane {lane} refers to unknown node(s) {missing[:3]}", field="nd")
        xy = np.array([nodes[r] for r in refs], dtype=np.float64).reshape(-1, 2)
        where = f"lane {lane}"
        lnid = tags.get("l_neighbor_id", "None")
        rnid = tags.get("r_neighbor_id", "None")
        builder.add(
            FeatureKind.LANE_CENTERLINE,
            lane,
            xy,
            lane_id=lane,
            direction="forward",
            is_intersection=_bool(tags.get("is_intersection", "False"), name, f"{where}: is_intersection"),
            has_traffic_control=_bool(tags.get("has_traffic_control", "False"), name, f"{where}: has_traffic_control"),
            turn_direction=tags.get("turn_direction", "NONE"),
            left_neighbor_id=None if lnid == "None" else lnid,
            right_neighbor_id=None if rnid == "None" else rnid,
            predecessors=preds,
            successors=succs,
        )
    return builder.build()
