"""Lanelet2 maps in their OSM XML encoding.

Layout (Lanelet2 ``io`` format): ``<node id lat lon>`` points, optionally with ``local_x`` / ``local_y``
tags (metric map coordinates, used as-is when every node has them); ``<way>`` line strings with ``type`` /
``subtype`` tags (``line_thin`` + ``solid``, ``curbstone``, ``virtual``, ...); ``<relation>`` primitives:

* ``type=lanelet``: members ``role=left`` and ``role=right`` (ways) give the two bounds, ordered in the
  direction of travel; tags ``subtype`` (``road``, ``highway``, ``crosswalk``, ``walkway``,
  ``bicycle_lane``, ...) and ``one_way`` (``no`` for bidirectional lanelets);
* ``type=multipolygon`` with ``role=outer`` ways: areas, ``subtype`` e.g. ``parking``, ``crosswalk``.

Mapping to the store: road-like lanelets give a centerline (average of the two bounds, ``derived``), the
two bounds as lane boundaries (each way once) and their outline as a drivable-area polygon; crosswalk
lanelets and crosswalk areas give crossings; parking/road areas give drivable areas.

Without ``local_x``/``local_y``, lat/lon are projected onto a local tangent plane (equirectangular on the
WGS84 equatorial radius) about ``origin`` (default: the first node), metres east (x) and north (y). That is
accurate to well under a pixel over a few kilometres; pass the dataset's own origin so tracks and map share
a frame.
"""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np

from logpipe.errors import SourceError
from logpipe.maps.av2 import centerline_from_boundaries
from logpipe.maps.feature_kinds import FeatureKind
from logpipe.maps.store import MapBuilder, MapStore
from logpipe.types import NDArrayFloat

SOURCE = "lanelet2_osm"
EARTH_RADIUS_M = 6378137.0
_DRIVABLE_SUBTYPES = {"road", "highway", "play_street", "emergency_lane", "bus_lane", "bicycle_lane"}
_CROSSING_SUBTYPES = {"crosswalk"}
_AREA_DRIVABLE_SUBTYPES = {"road", "parking", "highway", "drivable"}


def sniff(path: Path) -> bool:
    """An ``.osm``/``.xml`` file with lanelet relations."""
    if path.suffix.lower() not in (".osm", ".xml"):
        return False
    with path.open("rb") as fh:
        head = fh.read(1 << 20)
    return b"<osm" in head and b'"lanelet"' in head


def _project(lat: float, lon: float, origin: tuple[float, float]) -> tuple[float, float]:
    lat0, lon0 = origin
    x = math.radians(lon - lon0) * EARTH_RADIUS_M * math.cos(math.radians(lat0))
    y = math.radians(lat - lat0) * EARTH_RADIUS_M
    return x, y


def _orient_like(bound: NDArrayFloat, reference: NDArrayFloat) -> NDArrayFloat:
    """``bound`` reversed if its start lies nearer ``reference``'s end (bounds drawn against each other)."""
    same = np.linalg.norm(bound[0] - reference[0]) + np.linalg.norm(bound[-1] - reference[-1])
    flipped = np.linalg.norm(bound[-1] - reference[0]) + np.linalg.norm(bound[0] - reference[-1])
    return bound[::-1] if flipped < same else bound


def load(path: Path, map_id: str | None = None, origin: tuple[float, float] | None = None) -> MapStore:
    """Read a Lanelet2 OSM map.

    Args:
        path: the ``.osm`` file.
        map_id: map name (default: file stem).
        origin: (lat, lon) in degrees of the local frame's origin when nodes carry no ``local_x/local_y``.

    Raises:
        SourceError: malformed XML, a lanelet without both bounds, a way naming an unknown node.
    """
    name = str(path)
    try:
        root = ET.parse(path).getroot()
    except ET.ParseError as exc:
        raise SourceError(name, f"malformed XML: {exc}", line=exc.position[0]) from exc
    ways = _read_ways(root, _read_nodes(root, name, origin), name)
    builder = MapBuilder(map_id or path.stem, SOURCE)
    used_bounds: set[str] = set()
    for rel in root.iter("relation"):
        rid = rel.attrib.get("id", "")
        tags = _tags(rel)
        members = [(m.attrib.get("role", ""), m.attrib.get("type", ""), m.attrib.get("ref", "")) for m in rel]
        members = [m for m in members if m[1] == "way"]
        if tags.get("type") == "lanelet":
            _add_lanelet(builder, rid, tags, members, ways, used_bounds, name)
        elif tags.get("type") == "multipolygon":
            _add_area(builder, rid, tags.get("subtype", "road"), members, ways)
    return builder.build()


def _tags(el: ET.Element) -> dict[str, str]:
    """The ``<tag k v>`` children of an OSM element as a dict."""
    return {t.attrib.get("k", ""): t.attrib.get("v", "") for t in el.iter("tag")}


def _read_nodes(root: ET.Element, name: str, origin: tuple[float, float] | None) -> dict[str, tuple[float, float]]:
    """Node id → (x, y) metres in the map frame: ``local_x/local_y`` when every node has them, else lat/lon
    projected about ``origin`` (default: the first node)."""
    raw: dict[str, tuple[float, float, dict[str, str]]] = {}
    for el in root.iter("node"):
        tags = _tags(el)
        try:
            raw[el.attrib["id"]] = (float(el.attrib.get("lat", "nan")), float(el.attrib.get("lon", "nan")), tags)
        except (KeyError, ValueError) as exc:
            raise SourceError(name, f"node without id or numeric lat/lon: {el.attrib}", field="node") from exc
    local = bool(raw) and all("local_x" in t and "local_y" in t for _, _, t in raw.values())
    nodes: dict[str, tuple[float, float]] = {}
    if local:
        for nid, (_, _, tags) in raw.items():
            nodes[nid] = (float(tags["local_x"]), float(tags["local_y"]))
    elif raw:
        first = next(iter(raw.values()))
        org = origin if origin is not None else (first[0], first[1])
        for nid, (lat, lon, _) in raw.items():
            if not (math.isfinite(lat) and math.isfinite(lon)):
                raise SourceError(name, f"node {nid} has neither lat/lon nor local_x/local_y", field="node")
            nodes[nid] = _project(lat, lon, org)
    return nodes


def _read_ways(
    root: ET.Element, nodes: dict[str, tuple[float, float]], name: str
) -> dict[str, tuple[NDArrayFloat, dict[str, str]]]:
    """Way id → ((n, 2) vertices in metres, tags)."""
    ways: dict[str, tuple[NDArrayFloat, dict[str, str]]] = {}
    for el in root.iter("way"):
        wid = el.attrib.get("id", "")
        refs = [nd.attrib.get("ref", "") for nd in el.iter("nd")]
        bad = [r for r in refs if r not in nodes]
        if bad:
            raise SourceError(name, f"way {wid} refers to unknown node(s) {bad[:3]}", field="nd")
        ways[wid] = (np.array([nodes[r] for r in refs], dtype=np.float64).reshape(-1, 2), _tags(el))
    return ways


def _add_lanelet(
    builder: MapBuilder,
    rid: str,
    tags: dict[str, str],
    members: list[tuple[str, str, str]],
    ways: dict[str, tuple[NDArrayFloat, dict[str, str]]],
    used_bounds: set[str],
    name: str,
) -> None:
    """A lanelet relation's features: a crossing, or centerline + drivable outline + its two bounds (each way
    once over the map, tracked in ``used_bounds``)."""
    subtype = tags.get("subtype", "road")
    lefts = [ref for role, _, ref in members if role == "left"]
    rights = [ref for role, _, ref in members if role == "right"]
    if len(lefts) != 1 or len(rights) != 1 or lefts[0] not in ways or rights[0] not in ways:
        raise SourceError(name, f"lanelet {rid} needs exactly one known left and right way", field=rid)
    right, right_tags = ways[rights[0]]
    left, left_tags = ways[lefts[0]]
    left = _orient_like(left, right)
    outline = np.vstack([left, right[::-1]])
    if subtype in _CROSSING_SUBTYPES:
        builder.add(FeatureKind.CROSSING, rid, outline, lane_type=subtype, derived=True)
        return
    if subtype not in _DRIVABLE_SUBTYPES:
        return  # walkways, stairs, ...: not part of the road raster
    bidir = tags.get("one_way", "yes") == "no"
    builder.add(
        FeatureKind.LANE_CENTERLINE,
        rid,
        centerline_from_boundaries(left, right),
        derived=True,
        lane_id=rid,
        lane_type=subtype,
        direction="both" if bidir else "forward",
    )
    builder.add(FeatureKind.DRIVABLE_AREA, rid, outline, derived=True, lane_id=rid)
    for side, wid, geom, wtags in (
        ("left", lefts[0], left, left_tags),
        ("right", rights[0], right, right_tags),
    ):
        if wid in used_bounds:
            continue  # a way shared by two lanelets is one boundary
        used_bounds.add(wid)
        mark = "/".join(v for v in (wtags.get("type"), wtags.get("subtype")) if v) or None
        builder.add(FeatureKind.LANE_BOUNDARY, wid, geom, lane_id=rid, side=side, mark_type=mark)


def _add_area(
    builder: MapBuilder,
    rid: str,
    subtype: str,
    members: list[tuple[str, str, str]],
    ways: dict[str, tuple[NDArrayFloat, dict[str, str]]],
) -> None:
    """A multipolygon relation's outer ring as a crossing or a drivable area (other subtypes are skipped)."""
    outer = [ways[ref][0] for role, _, ref in members if role == "outer" and ref in ways]
    if not outer:
        return
    ring = np.vstack(outer)
    if subtype in _CROSSING_SUBTYPES:
        builder.add(FeatureKind.CROSSING, rid, ring, lane_type=subtype)
    elif subtype in _AREA_DRIVABLE_SUBTYPES:
        builder.add(FeatureKind.DRIVABLE_AREA, rid, ring, lane_type=subtype)
