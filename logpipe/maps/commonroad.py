"""CommonRoad scenario XML: the secure parse every CommonRoad reader shares, and a scenario's lanelet network as a map.

A CommonRoad file (``<commonRoad>``, format versions 2018b and 2020a; later versions with the same elements read
the same) holds one scenario: ``<lanelet>`` elements with a ``leftBound`` and a ``rightBound`` (``<point><x><y>``
polylines in the scenario's own local metric frame, both ordered in the driving direction, with an optional
``<lineMarking>``), ``predecessor`` / ``successor`` / ``adjacentLeft`` / ``adjacentRight`` references, optional
``laneletType`` (2020a), ``stopLine``, ``trafficSignRef`` / ``trafficLightRef``; 2020a adds ``<intersection>``
elements naming the lanelets a turn takes. The obstacles of the same file are read by ``logpipe.formats.commonroad``.

Mapping to the store (``schemas/map.json``):

* each drivable lanelet: its outline (left bound + right bound reversed) as a ``drivable_area`` polygon, the mean of
  its two bounds as a ``lane_centerline`` (``derived``, direction ``forward``: CommonRoad lanelets are one-way), and
  each bound once as a ``lane_boundary`` (``<lanelet>:left`` / ``<lanelet>:right``; a bound two lanelets share is
  stored once) with its ``lineMarking`` as ``mark_type``; a ``stopLine`` is a ``lane_boundary`` ``<lanelet>:stop``
  with ``mark_type`` ``stop_line``;
* ``crosswalk`` lanelets: ``crossing`` polygons; ``sidewalk`` lanelets are not road and are left out;
* lane attributes: ``lane_type`` (the ``laneletType`` values joined by ``/``, null in 2018b), neighbours (adjacent
  lanelets driven the same way), predecessors, successors, ``has_traffic_control`` (a traffic light or stop line),
  and from 2020a intersections ``is_intersection`` and ``turn_direction`` (``LEFT`` | ``RIGHT`` | ``NONE``).

Files may be gzip-compressed (``.xml.gz``: synthetic scenarios are written so). Parsing is defused: no DTD is
accepted (a CommonRoad file never has one), entities are never expanded, nothing is
fetched from a network, and text nodes are bounded (lxml without ``huge_tree``).
"""

from __future__ import annotations

import math
import zlib
from pathlib import Path
from typing import Any

import numpy as np
from lxml import etree

from logpipe.errors import SourceError
from logpipe.maps.av2 import centerline_from_boundaries
from logpipe.maps.feature_kinds import FeatureKind
from logpipe.maps.store import MapBuilder, MapStore
from logpipe.types import NDArrayFloat

SOURCE = "commonroad_xml"
MAX_FILE_BYTES = 16 << 20
"""Largest CommonRoad file read (16 MiB, after any gzip): the real ones are 0.1-4 MB. The XML is parsed whole
(lxml, ~22x the file in memory): a 16.7 MB file of 30,000 obstacles took 7.0 s and 372 MB to ingest here, a
250 MB one 103 s and 4.4 GB; larger files are refused before parsing, with this limit in the error."""
COORDINATE_LIMIT_M = 1e7
"""Largest |x| or |y| accepted, metres: CommonRoad frames are local, so anything beyond 10,000 km is damage."""
_NOT_ROAD = frozenset({"sidewalk"})
_CROSSING = frozenset({"crosswalk"})
_TURNS = {"Right": "RIGHT", "Left": "LEFT", "Straight": "NONE"}


def _parser() -> etree.XMLParser:
    # No entity expansion, no DTD loading, no network, bounded text nodes: the "defused" reading of untrusted XML.
    return etree.XMLParser(resolve_entities=False, no_network=True, load_dtd=False, dtd_validation=False,
                           huge_tree=False, remove_comments=True, remove_pis=True)


def parse_scenario(data: bytes, name: str) -> etree._Element:
    """The ``<commonRoad>`` root element of a file's bytes.

    Raises:
        SourceError: too large, malformed XML (with its line), a DOCTYPE (entity declarations are refused, not
            expanded), or another root element.
    """
    head = data[: max(data.find(b"<commonRoad"), 0) or 1 << 16]
    if b"<!DOCTYPE" in head or b"<!ENTITY" in head:
        raise SourceError(name, "the file declares a DOCTYPE; CommonRoad files never do, and DTDs (entity "
                          "declarations) are refused rather than expanded", line=1, field="DOCTYPE")
    if len(data) > MAX_FILE_BYTES:
        raise SourceError(name, f"{len(data):,} bytes is over the {MAX_FILE_BYTES >> 20} MiB a CommonRoad file may "
                          "have; refused before parsing")
    try:
        root = etree.fromstring(data, _parser())
    except etree.XMLSyntaxError as exc:
        raise SourceError(name, f"malformed XML: {exc.msg}", line=exc.lineno) from None
    info = root.getroottree().docinfo
    if info.doctype or info.internalDTD is not None:
        raise SourceError(name, "the file declares a DOCTYPE; CommonRoad files never do, and DTDs (entity "
                          "declarations) are refused rather than expanded", line=1, field="DOCTYPE")
    if root.tag != "commonRoad":
        raise SourceError(name, f"the root element is <{root.tag}>, not <commonRoad>", line=root.sourceline)
    return root


def sniff(path: Path) -> bool:
    """An ``.xml`` file (or a gzip-compressed ``.xml.gz``) whose first KiB opens a ``<commonRoad`` element."""
    name = path.name.lower()
    if not name.endswith((".xml", ".xml.gz")) or not path.is_file():
        return False
    with path.open("rb") as fh:
        head = fh.read(1024)
        if name.endswith(".gz"):
            fh.seek(0)
            try:
                head = zlib.decompressobj(wbits=31).decompress(fh.read(1 << 16), 1024)
            except zlib.error:
                return False
        return b"<commonRoad" in head


def read_scenario_bytes(path: Path, name: str) -> bytes:
    """A file's XML bytes: as stored, or decompressed from ``.gz`` with at most ``MAX_FILE_BYTES`` out (a
    decompression bomb is refused once it passes that, never held whole).

    Raises:
        SourceError: unreadable, or damaged or oversized gzip data.
    """
    try:
        data = path.read_bytes()
    except OSError as err:
        raise SourceError(name, f"not readable: {err.strerror or err}") from None
    if not path.name.lower().endswith(".gz"):
        return data
    inflate = zlib.decompressobj(wbits=31)
    try:
        out = inflate.decompress(data, MAX_FILE_BYTES + 1)
    except zlib.error as err:
        raise SourceError(name, f"damaged gzip data: {err}") from None
    if len(out) > MAX_FILE_BYTES or inflate.unconsumed_tail:
        raise SourceError(name, f"decompresses to over {MAX_FILE_BYTES >> 20} MiB; refused (a gzip bomb?)")
    if not inflate.eof:
        raise SourceError(name, "damaged gzip data: the stream ends early (cut short?)")
    return out


def load(path: Path, map_id: str | None = None) -> MapStore:
    """The lanelet network of a CommonRoad file as a map store (``map_id`` default: the benchmark id, else the stem).

    Raises:
        SourceError: an unreadable file, or a lanelet with a missing, non-numeric or absurd bound.
    """
    root = parse_scenario(read_scenario_bytes(path, str(path)), str(path))
    return lanelet_map(root, map_id or root.get("benchmarkID") or path.stem, str(path))


def number(el: etree._Element, tag: str, name: str, where: str) -> float:
    """The finite float in ``el``'s child ``tag`` (a ``SourceError`` naming ``where`` and the field otherwise)."""
    text = el.findtext(tag)
    if text is None:
        raise SourceError(name, f"{where}: <{tag}> is missing", line=el.sourceline, field=tag)
    try:
        value = float(text)
    except ValueError:
        raise SourceError(name, f"{where}: <{tag}> is not a number: {text.strip()[:40]!r}", line=el.sourceline,
                          field=tag) from None
    if not math.isfinite(value) or abs(value) > COORDINATE_LIMIT_M:
        raise SourceError(name, f"{where}: <{tag}> is {text.strip()[:40]!r}: not finite or beyond "
                          f"{COORDINATE_LIMIT_M:.0e} m", line=el.sourceline, field=tag)
    return value


def polyline(bound: etree._Element | None, name: str, where: str) -> NDArrayFloat:
    """(n, 2) points of a bound or stop line (``<point><x><y>`` children), metres."""
    if bound is None:
        raise SourceError(name, f"{where} is missing", field=where.rsplit(" ", 1)[-1])
    points = bound.findall("point")
    if len(points) < 2:
        raise SourceError(name, f"{where} has {len(points)} point(s); a bound needs at least 2",
                          line=bound.sourceline, field="point")
    return np.array([(number(p, "x", name, where), number(p, "y", name, where)) for p in points], dtype=np.float64)


def _refs(el: etree._Element, tag: str) -> list[str]:
    return [str(r.get("ref")) for r in el.findall(tag) if r.get("ref")]


def _turns(root: etree._Element) -> dict[str, str]:
    """Lanelet id → turn direction for the lanelets 2020a intersections lead into (``successorsRight``, ...,
    later versions ``outgoingRight``, ...)."""
    turns: dict[str, str] = {}
    for incoming in root.iter("incoming"):
        for word, turn in _TURNS.items():
            for ref in _refs(incoming, f"successors{word}") + _refs(incoming, f"outgoing{word}"):
                turns.setdefault(ref, turn)
    return turns


def _same_way_neighbour(el: etree._Element, tag: str) -> str | None:
    adjacent = el.find(tag)
    if adjacent is None or adjacent.get("drivingDir", "same") != "same":
        return None
    ref = adjacent.get("ref")
    return str(ref) if ref else None


def _bound_key(points: NDArrayFloat) -> bytes:
    """The same bound whichever way two lanelets store it (opposite lanes share it reversed)."""
    rounded = np.round(points, 3)
    return min(rounded.tobytes(), rounded[::-1].copy().tobytes())


def lanelet_map(root: etree._Element, map_id: str, name: str) -> MapStore:
    """The store of ``root``'s lanelet network (see the module docstring for the mapping).

    Raises:
        SourceError: a lanelet without an id or with a bad bound, naming the lanelet and the field.
    """
    builder = MapBuilder(map_id, SOURCE)
    turns = _turns(root)
    drawn_bounds: set[bytes] = set()
    for el in root.iterchildren("lanelet"):
        lanelet_id = el.get("id")
        if not lanelet_id:
            raise SourceError(name, "a lanelet has no id", line=el.sourceline, field="id")
        where = f"lanelet {lanelet_id}"
        left = polyline(el.find("leftBound"), name, f"{where} leftBound")
        right = polyline(el.find("rightBound"), name, f"{where} rightBound")
        types = [t.text.strip() for t in el.findall("laneletType") if t.text and t.text.strip()]
        outline = np.vstack([left, right[::-1]])
        if _CROSSING & set(types):
            builder.add(FeatureKind.CROSSING, lanelet_id, outline, derived=True, lane_type="/".join(types))
            continue
        if _NOT_ROAD & set(types):
            continue
        _add_lane(builder, el, lanelet_id, left, right, types, turns.get(lanelet_id))
        builder.add(FeatureKind.DRIVABLE_AREA, lanelet_id, outline, derived=True, lane_id=lanelet_id)
        for side, bound_el, points in (("left", el.find("leftBound"), left), ("right", el.find("rightBound"), right)):
            key = _bound_key(points)
            if key in drawn_bounds:
                continue
            drawn_bounds.add(key)
            builder.add(FeatureKind.LANE_BOUNDARY, f"{lanelet_id}:{side}", points, lane_id=lanelet_id, side=side,
                        mark_type=bound_el.findtext("lineMarking") if bound_el is not None else None)
        _add_stop_line(builder, el, lanelet_id, name)
    return builder.build()


def _add_lane(
    builder: MapBuilder, el: etree._Element, lanelet_id: str, left: NDArrayFloat, right: NDArrayFloat,
    types: list[str], turn: str | None,
) -> None:
    """The lanelet's centerline with its lane attributes."""
    centre = (left + right) / 2.0 if len(left) == len(right) else centerline_from_boundaries(left, right)
    controlled = el.find("trafficLightRef") is not None or el.find("stopLine") is not None
    attributes: dict[str, Any] = {
        "lane_id": lanelet_id, "direction": "forward", "lane_type": "/".join(types) or None,
        "left_neighbor_id": _same_way_neighbour(el, "adjacentLeft"),
        "right_neighbor_id": _same_way_neighbour(el, "adjacentRight"),
        "predecessors": _refs(el, "predecessor"), "successors": _refs(el, "successor"),
        "has_traffic_control": controlled,
        "is_intersection": turn is not None, "turn_direction": turn,
    }
    builder.add(FeatureKind.LANE_CENTERLINE, lanelet_id, centre, derived=True, **attributes)


def _add_stop_line(builder: MapBuilder, el: etree._Element, lanelet_id: str, name: str) -> None:
    stop = el.find("stopLine")
    if stop is None or len(stop.findall("point")) < 2:
        return  # a stop line without points lies at the lanelet's end; the bounds already draw that edge
    points = polyline(stop, name, f"lanelet {lanelet_id} stopLine")
    builder.add(FeatureKind.LANE_BOUNDARY, f"{lanelet_id}:stop", points, lane_id=lanelet_id,
                mark_type="stop_line")
