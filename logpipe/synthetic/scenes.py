"""Map sources and writers of the pre-training traffic: where a scene's lanes come from and how it is written so
that ``logpipe ingest`` reads it and ``logpipe rasterise`` draws it with that source's own map.

* NGSIM CommonRoad scenarios (``USA_US101``, ``USA_Lanker``, ``USA_Peach``): the file's lanelet network (with its
  traffic signs, lights and intersections) is copied verbatim into a CommonRoad 2020a ``.xml.gz`` holding the
  simulated cars as ``dynamicObstacle`` s; speed limits from its ``R2-1``/``274`` signs, light cycles from its
  ``trafficLight`` s, stop lines from ``stopLine`` s without a light, widths from the lanelet bounds.
* AV2 log maps (location ``USA_AV2``): each lane segment becomes a lanelet (bounds, links, same-direction
  neighbours, ``lineMarking`` from the AV2 paint, BIKE/BUS lanes as ``bicycleLane``/``busLane``), each pedestrian
  crossing a ``crosswalk`` lanelet; written like the NGSIM ones. AV2 drivable-area polygons have no lanelet
  counterpart and are not carried (docs/synthetic.md measures what that changes in the rasters).
* AV1 city centerlines (MIA, PIT): scenes on 250 m boxes of the city graph, cut into AV1 forecasting CSVs (one
  window of 50 steps per file: an AV, an AGENT, OTHERS), rasterised with the city npz.

Every output is labelled: file names and log ids start with ``synthetic_``; CommonRoad roots carry
``source="SYNTHETIC traffic (logpipe.synthetic)"`` and ``benchmarkID="synthetic_<real id>_<n>"`` (the adapter marks
the log ``synthetic`` and reads its real location from the id).
"""

from __future__ import annotations

import gzip
import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from lxml import etree

from logpipe.maps import MapStore, load_map
from logpipe.maps import commonroad as crmap
from logpipe.maps.av2 import resample
from logpipe.synthetic.flow import DT_S, Tracks
from logpipe.synthetic.roads import LaneExtras, Roads, Signal
from logpipe.synthetic.traffic import AV_TRACK_ID, CSV_HEADER
from logpipe.types import NDArrayBool, NDArrayFloat, NDArrayInt

SYNTHETIC_SOURCE = "SYNTHETIC traffic (logpipe.synthetic)"
SPEED_SIGNS = ("R2-1", "274")
"""CommonRoad traffic sign ids whose ``additionalValue`` is a speed limit in m/s (US, Germany)."""
URBAN_LIMIT = 15.6
"""Default limit of urban lanes without a sign, m/s (35 mph, the NGSIM arterials' posted limit)."""
HIGHWAY_LIMIT = 29.0
"""Default limit on scenarios tagged ``highway`` (65 mph, US-101's posted limit), m/s."""
CITY_LIMIT = 13.4
"""Default limit on AV1/AV2 city lanes (30 mph), m/s; curves slow cars further."""
_AV2_PAINT = {"SOLID": "solid", "DASHED": "dashed", "DOUBLE_SOLID": "broad_solid", "DOUBLE_DASH": "broad_dashed",
              "NONE": "no_marking"}
_AV2_TYPES = {"VEHICLE": "urban", "BIKE": "bicycleLane", "BUS": "busLane"}


@dataclass
class LaneletSource:
    """A lanelet network to simulate on and copy: its store, extras, the XML of its map elements, the real
    benchmark id the output names, the location, and the highest id used (obstacle ids go above it)."""

    store: MapStore
    extras: LaneExtras
    map_xml: list[bytes]
    real_id: str
    location: str
    max_id: int
    default_limit: float


def ngsim_source(path: Path) -> LaneletSource:
    """A real NGSIM CommonRoad file as a source (module docstring)."""
    root = crmap.parse_scenario(crmap.read_scenario_bytes(path, str(path)), str(path))
    real_id = root.get("benchmarkID") or path.stem
    store = crmap.lanelet_map(root, real_id, str(path))
    tags = (root.get("tags") or "") + " ".join(t.tag for t in root.iterfind("scenarioTags/*"))
    limit = HIGHWAY_LIMIT if "highway" in tags else URBAN_LIMIT
    keep = ("lanelet", "trafficSign", "trafficLight", "intersection")
    elements = [el for el in root if el.tag in keep]
    ids = [int(el.get("id")) for el in root.iter() if (el.get("id") or "").lstrip("-").isdigit()]
    return LaneletSource(store, lanelet_extras(root, rng_offset=0.0), [etree.tostring(el) for el in elements],
                         real_id, real_id.split("-")[0], max(ids, default=0), limit)


def lanelet_extras(root: etree._Element, rng_offset: float) -> LaneExtras:
    """Widths, sign speed limits, light cycles and stop lines of a CommonRoad lanelet network."""
    step = float(root.get("timeStepSize") or DT_S)
    signs: dict[str, float] = {}
    for sign in root.iter("trafficSign"):
        for el in sign.iter("trafficSignElement"):
            value = el.findtext("additionalValue")
            if el.findtext("trafficSignID") in SPEED_SIGNS and value:
                signs[str(sign.get("id"))] = float(value)
    lights: dict[str, Signal] = {}
    for light in root.iter("trafficLight"):
        durations = {c.findtext("color"): float(c.findtext("duration") or 0) * step for c in light.iter("cycleElement")}
        offset = float(light.findtext("cycle/timeOffset") or 0) * step
        if durations.get("green"):
            lights[str(light.get("id"))] = Signal(durations.get("green", 0.0), durations.get("yellow", 0.0),
                                                  durations.get("red", 0.0) + durations.get("redYellow", 0.0),
                                                  offset + rng_offset)
    extras = LaneExtras()
    for el in root.iterchildren("lanelet"):
        lid = str(el.get("id"))
        left = crmap.polyline(el.find("leftBound"), "", lid)
        right = crmap.polyline(el.find("rightBound"), "", lid)
        extras.widths[lid] = float(np.hypot(*(resample(left, 20) - resample(right, 20)).T).mean())
        for ref in el.iterfind("trafficSignRef"):
            if ref.get("ref") in signs:
                extras.limits[lid] = signs[str(ref.get("ref"))]
        light_refs = [r.get("ref") for r in el.iterfind("trafficLightRef")]
        light_refs += [r.get("ref") for r in el.iterfind("stopLine/trafficLightRef")]
        hit = next((lights[str(r)] for r in light_refs if str(r) in lights), None)
        if hit is not None:
            extras.signals[lid] = hit
        elif el.find("stopLine") is not None:
            extras.stop_lines.add(lid)
    return extras


def av2_source(path: Path) -> LaneletSource:
    """An AV2 log map JSON as lanelets (module docstring); location ``USA_AV2``."""
    doc = json.loads(path.read_text(encoding="utf-8"))
    log = path.stem.removeprefix("log_map_archive_").split("_")[0]
    real_id = f"USA_AV2-{log[:8]}"
    parts: list[bytes] = []
    lanes = doc.get("lane_segments", {})
    lane_ids = {int(k) for k in lanes}
    for key, lane in sorted(lanes.items(), key=lambda kv: int(kv[0])):
        parts.append(_av2_lanelet(int(key), lane, lane_ids))
    next_id = max(lane_ids, default=0) + 1
    for _, cross in sorted(doc.get("pedestrian_crossings", {}).items()):
        e1, e2 = (np.array([[p["x"], p["y"]] for p in cross[k]]) for k in ("edge1", "edge2"))
        parts.append(_lanelet_xml(next_id, e1, e2, [], [], None, None, ("unknown", "unknown"), ["crosswalk"]))
        next_id += 1
    root = etree.fromstring(b"<commonRoad>" + b"".join(parts) + b"</commonRoad>")
    store = crmap.lanelet_map(root, real_id, str(path))
    return LaneletSource(store, lanelet_extras(root, 0.0), parts, real_id, "USA_AV2", next_id, CITY_LIMIT)


def _av2_lanelet(lid: int, lane: dict[str, object], known: set[int]) -> bytes:
    left = np.array([[p["x"], p["y"]] for p in lane["left_lane_boundary"]])  # type: ignore[attr-defined]
    right = np.array([[p["x"], p["y"]] for p in lane["right_lane_boundary"]])  # type: ignore[attr-defined]
    paint = tuple(_av2_paint(str(lane.get(f"{side}_lane_mark_type"))) for side in ("left", "right"))
    kind = _AV2_TYPES.get(str(lane.get("lane_type")), "unknown")
    nbrs = [int(n) if n is not None and int(n) in known else None  # type: ignore[call-overload]
            for n in (lane.get("left_neighbor_id"), lane.get("right_neighbor_id"))]
    links = [[int(x) for x in lane.get(k) or [] if int(x) in known] for k in ("predecessors", "successors")]  # type: ignore[attr-defined]
    return _lanelet_xml(lid, left, right, links[0], links[1], nbrs[0], nbrs[1], paint, [kind])  # type: ignore[arg-type]


def _av2_paint(mark: str) -> str:
    for word, value in _AV2_PAINT.items():
        if mark.startswith(word) or mark.startswith(f"SOLID_{word}"):
            return value
    return "solid" if "SOLID" in mark else "dashed" if "DASH" in mark else "unknown"


def _lanelet_xml(  # noqa: PLR0913  one lanelet's fields in schema order
    lid: int, left: NDArrayFloat, right: NDArrayFloat, pred: list[int], succ: list[int],
                 left_nb: int | None, right_nb: int | None, paint: tuple[str, str], types: list[str]) -> bytes:
    def bound(tag: str, pts: NDArrayFloat, mark: str) -> str:
        points = "".join(f"<point><x>{x:.4f}</x><y>{y:.4f}</y></point>" for x, y in pts)
        return f"<{tag}>{points}<lineMarking>{mark}</lineMarking></{tag}>"

    body = bound("leftBound", left, paint[0]) + bound("rightBound", right, paint[1])
    body += "".join(f'<predecessor ref="{p}"/>' for p in pred) + "".join(f'<successor ref="{s}"/>' for s in succ)
    if left_nb is not None:
        body += f'<adjacentLeft ref="{left_nb}" drivingDir="same"/>'
    if right_nb is not None:
        body += f'<adjacentRight ref="{right_nb}" drivingDir="same"/>'
    body += "".join(f"<laneletType>{t}</laneletType>" for t in types)
    return f'<lanelet id="{lid}">{body}</lanelet>'.encode()


def write_commonroad(path: Path, src: LaneletSource, n: int, tracks: Tracks, noise_sd: float,
                     rng: np.random.Generator, min_steps: int = 10) -> int:
    """One scene as a gzip CommonRoad 2020a file (benchmark id ``synthetic_<real id>_<n>``); positions get white
    tracking noise of ``noise_sd`` m. Cars seen for fewer than ``min_steps`` steps are left out. Returns the
    number of obstacles written."""
    head = (f'<?xml version="1.0" encoding="utf-8"?>\n<commonRoad commonRoadVersion="2020a" '
            f'benchmarkID="synthetic_{src.real_id}_{n}" date="2026-12-07" author="logpipe.synthetic" '
            f'affiliation="none (simulated)" source="{SYNTHETIC_SOURCE}" timeStepSize="{DT_S}">\n')
    parts = [head.encode(), *src.map_xml]
    written = 0
    order = np.lexsort((tracks.step, tracks.vid))
    vids, starts = np.unique(tracks.vid[order], return_index=True)
    bounds = [*starts.tolist(), len(order)]
    for k, vid in enumerate(vids.tolist()):
        rows = order[bounds[k]:bounds[k + 1]]
        if len(rows) < min_steps:
            continue
        length, width, truck = tracks.sizes[int(vid)]
        xy = tracks.xy[rows] + (rng.normal(0.0, noise_sd, (len(rows), 2)) if noise_sd > 0 else 0.0)
        states = [_state(int(tracks.step[r]), xy[m], float(tracks.heading[r]), float(tracks.speed[r]),
                         float(tracks.accel[r])) for m, r in enumerate(rows)]
        parts.append(
            (f'<dynamicObstacle id="{src.max_id + int(vid)}"><type>{"truck" if truck else "car"}</type><shape>'
             f"<rectangle><length>{length:.3f}</length><width>{width:.3f}</width></rectangle></shape>"
             f"<initialState>{states[0]}</initialState><trajectory>"
             + "".join(f"<state>{s}</state>" for s in states[1:]) + "</trajectory></dynamicObstacle>\n").encode())
        written += 1
    parts.append(b"</commonRoad>\n")
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")  # renamed when whole: a killed run leaves no cut file to ingest
    with tmp.open("wb") as raw, gzip.GzipFile(fileobj=raw, mode="wb", compresslevel=6, mtime=0) as fh:
        fh.write(b"".join(parts))  # mtime 0: the same seed gives the same bytes
    tmp.replace(path)
    return written


def _state(step: int, xy: NDArrayFloat, heading: float, speed: float, accel: float) -> str:
    return (f"<position><point><x>{xy[0]:.3f}</x><y>{xy[1]:.3f}</y></point></position>"
            f"<orientation><exact>{heading:.4f}</exact></orientation><time><exact>{step}</exact></time>"
            f"<velocity><exact>{speed:.3f}</exact></velocity><acceleration><exact>{accel:.3f}</exact></acceleration>")


def av1_windows(  # noqa: PLR0913  the scene, where and how to write it
    tracks: Tracks, city: str, name: str, out: Path, rng: np.random.Generator, stride: int,
                noise_sd: float, t0_s: float, radius: float = 80.0) -> int:
    """Cut a scene into AV1 forecasting CSVs, one 50-step window every ``stride`` steps: the AV and the AGENT
    are cars seen over the whole window (the AGENT within 40 m of the AV at the current step, a car with a turn,
    lane change or stop in the future when there is one), OTHERS every car within ``radius`` m of the AV at the
    current step. Returns the number of files written (``<name>_<window>.csv``)."""
    steps = 50
    by_vid: dict[int, dict[int, int]] = {}
    for r, (k, v) in enumerate(zip(tracks.step.tolist(), tracks.vid.tolist(), strict=True)):
        by_vid.setdefault(v, {})[k] = r
    eventful: dict[int, list[int]] = {}
    for k, v, kind in tracks.events:
        if kind in ("turn", "lane_change", "forced_lane_change", "junction_stop", "red_light_stop", "stop_and_go"):
            eventful.setdefault(v, []).append(k)
    xy = tracks.xy + (rng.normal(0.0, noise_sd, tracks.xy.shape) if noise_sd > 0 else 0.0)
    written = 0
    for w, k0 in enumerate(range(0, tracks.steps - steps + 1, stride)):
        full = [v for v, rows in by_vid.items() if k0 in rows and k0 + steps - 1 in rows]
        if len(full) < 2:
            continue
        av = full[int(rng.integers(len(full)))]
        now = k0 + 19
        centre = xy[by_vid[av][now]]
        near = [v for v in full if v != av and float(np.hypot(*(xy[by_vid[v][now]] - centre))) < 40.0]
        if not near:
            continue
        busy = [v for v in near if any(now < k < k0 + steps for k in eventful.get(v, ()))]
        pool = busy if busy and rng.random() < 0.7 else near
        agent = pool[int(rng.integers(len(pool)))]
        others = [v for v, rows in by_vid.items() if v not in (av, agent) and now in rows
                  and float(np.hypot(*(xy[rows[now]] - centre))) < radius]
        lines = [CSV_HEADER]
        for k in range(k0, k0 + steps):
            ns = round((t0_s + k * DT_S) * 1e9)
            stamp = f"{ns // 1_000_000_000}.{ns % 1_000_000_000:09d}"
            for v, kind in [(av, "AV"), (agent, "AGENT"), *((o, "OTHERS") for o in others)]:
                row = by_vid[v].get(k)
                if row is not None:
                    tid = AV_TRACK_ID if kind == "AV" else f"00000000-0000-0000-0000-{v:012d}"
                    lines.append(f"{stamp},{tid},{kind},{xy[row, 0]:.4f},{xy[row, 1]:.4f},{city}")
        (out / f"{name}_{w:02d}.csv").write_text("\n".join(lines) + "\n")
        written += 1
    return written


def av1_region_of(roads: Roads, rng: np.random.Generator, side: float = 200.0) -> tuple[float, float, float, float]:
    """A ``side`` m box around a random centerline point of an AV1 city's roads."""
    x, y = (float(v) for v in roads.pts[int(rng.integers(len(roads.pts)))])
    return (x - side / 2, y - side / 2, x + side / 2, y + side / 2)


def load_av1(path: Path) -> MapStore:
    """An AV1 city centerline map (``load_map``)."""
    return load_map(path)


def remove_overlaps(tracks: Tracks) -> tuple[Tracks, int]:
    """Drop, whole, the later-born car of every pair whose rectangles overlap at some step (the simulator's rare
    misses at merges and lane changes), so no written scene has two cars in one place. Returns the scene and the
    number of cars dropped."""
    pairs = overlapping_pairs(tracks)
    drop = {int(max(a, b)) for a, b in pairs.tolist()}
    if not drop:
        return tracks, 0
    keep = ~np.isin(tracks.vid, list(drop))
    kept = Tracks(step=tracks.step[keep], vid=tracks.vid[keep], xy=tracks.xy[keep], heading=tracks.heading[keep],
                  speed=tracks.speed[keep], accel=tracks.accel[keep], sizes=tracks.sizes,
                  events=[e for e in tracks.events if e[1] not in drop], steps=tracks.steps)
    return kept, len(drop)


def overlapping_pairs(tracks: Tracks) -> NDArrayInt:
    """(P, 2) vehicle ids of pairs whose rectangles overlap at some step (separating-axis test, vectorised)."""
    corners = rectangles(tracks)
    reach = np.array([tracks.sizes[int(v)][0] for v in tracks.vid]) / 2 + 1.5
    order = np.argsort(tracks.step, kind="stable")
    bounds = np.searchsorted(tracks.step[order], np.arange(tracks.steps + 1))
    cand_a, cand_b = [], []
    for k in range(tracks.steps):
        rows = order[bounds[k]:bounds[k + 1]]
        if len(rows) < 2:
            continue
        p = tracks.xy[rows]
        d = np.hypot(p[:, None, 0] - p[None, :, 0], p[:, None, 1] - p[None, :, 1])
        a, b = np.nonzero(np.triu(d < reach[rows][:, None] + reach[rows][None, :], 1))
        cand_a.append(rows[a])
        cand_b.append(rows[b])
    if not cand_a:
        return np.zeros((0, 2), dtype=np.int64)
    ra, rb = np.concatenate(cand_a), np.concatenate(cand_b)
    hit = _sat(corners[ra], corners[rb])
    out: NDArrayInt = np.unique(np.stack([tracks.vid[ra[hit]], tracks.vid[rb[hit]]], axis=1), axis=0)
    return out


def rectangles(tracks: Tracks) -> NDArrayFloat:
    """(R, 4, 2) corners of every row's car, metres."""
    size = np.array([tracks.sizes[int(v)][:2] for v in tracks.vid]).reshape(-1, 2)
    u = np.stack([np.cos(tracks.heading), np.sin(tracks.heading)], axis=1)
    n = np.stack([-u[:, 1], u[:, 0]], axis=1)
    hl, hw = size[:, :1] / 2, size[:, 1:] / 2
    c = tracks.xy
    out: NDArrayFloat = np.stack([c + u * hl + n * hw, c + u * hl - n * hw, c - u * hl - n * hw, c - u * hl + n * hw],
                                 axis=1)
    return out


def _sat(a: NDArrayFloat, b: NDArrayFloat) -> NDArrayBool:
    """(P,) whether rectangles ``a[p]`` and ``b[p]`` ((P, 4, 2) corners) overlap: no edge normal separates them."""
    overlap = np.ones(len(a), dtype=bool)
    for poly in (a, b):
        for i in range(2):
            edge = poly[:, i + 1] - poly[:, i]
            axis = np.stack([-edge[:, 1], edge[:, 0]], axis=1)
            pa = np.einsum("pkd,pd->pk", a, axis)
            pb = np.einsum("pkd,pd->pk", b, axis)
            overlap &= (pa.max(axis=1) > pb.min(axis=1)) & (pb.max(axis=1) > pa.min(axis=1))
    return overlap
