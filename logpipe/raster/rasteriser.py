"""The map rasteriser: a window of a ``MapStore`` around a centre → a uint8 (C, H, W) image + its affine.

Pure computation, no dataset IO. Frames and conventions:

* **world frame**: the map's metric frame (metres), the same as the tracks' ``x``/``y``.
* **pixel frame**: OpenCV's, ``u`` = column, ``v`` = row, pixel centres at integer coordinates. The
  centre ``(cx, cy)`` maps to ``((W-1)/2, (H-1)/2)``, the exact middle of the image.
* **orientation**: without rotation the image is "north up": world +x points right, world +y points up
  (towards row 0). With ``rotate=True`` the centre's heading points up and its left is image left, i.e.
  the raster is the agent's own frame. ``world_to_pixel`` returns the (2, 3) affine ``A`` with
  ``[u, v] = A @ [x, y, 1]``; the rasteriser and every consumer (ROI pooling, previews) use the same one.

Channels (``RasterSpec.channels`` picks and orders them):

* ``drivable_area``: filled polygons, anti-aliased (255 inside).
* ``lane_centerline``: anti-aliased 1-px polylines (255 on the line).
* ``lane_direction``: the direction of travel of the centerline in the *image* frame, quantised to
  ``direction_bins`` sectors: value ``(b + 1) * 255 // K`` for sector ``b = round(phi / (2 pi / K)) mod
  K`` where ``phi`` is measured counter-clockwise from image right (image up = pi/2); 0 means no lane.
  ``phi`` is per chunk (first-to-last vertex; chunks turn by at most 30 degrees, see ``maps.store``), so
  a segment is within about one sector of its value. Drawn with 8-connected, non-anti-aliased lines so a
  value always decodes to a sector; where lanes of different directions overlap the higher value wins.
* ``lane_up`` / ``lane_left`` / ``lane_down`` / ``lane_right`` (the default direction encoding):
  anti-aliased centerlines split by travel direction in the image frame, each chunk into the channel of
  the quadrant (within 45 degrees) its direction points to; with rotation ``lane_up`` holds the lanes
  going the agent's way and ``lane_down`` the oncoming ones. Their maximum is ``lane_centerline``.
* ``lane_boundary``: anti-aliased 1-px polylines.
* ``crossing``: filled polygons, anti-aliased.

Default channels: ``DEFAULT_CHANNELS`` (drivable area, the four direction quadrants, boundaries,
crossings): one anti-aliased pass over the lanes encodes both where they are and where they go, which is
about twice as fast as ``lane_centerline`` + ``lane_direction``.

Speed: each layer's vertices are prepared once per rasteriser (``logpipe.raster.layers``); a window is then
~2 contiguous slices transformed in place, one product culls the chunks that miss the image, and the survivors
are drawn in layer order with one ``cv2.polylines`` call per channel (per direction sector for
``lane_direction``). Polygons are filled one call each because ``fillPoly`` with several contours fills by the
even-odd rule, which would punch holes where areas overlap. ``logpipe.raster.reference`` is the straightforward
renderer the tests and the benchmark hold this one to.
"""

from __future__ import annotations

import hashlib
import json
import math
import sys
import warnings
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from logpipe.maps import FeatureKind, MapStore
from logpipe.raster.layers import BAND_ROWS, PreparedLayer
from logpipe.types import NDArrayByte, NDArrayFloat, NDArrayInt, NDArrayInt32

QUADRANT_CHANNELS: tuple[str, ...] = ("lane_right", "lane_up", "lane_left", "lane_down")
"""Centerlines split by travel direction in the image frame: quadrant ``q`` holds chunks whose direction
``phi`` (CCW from image right) is within 45 degrees of ``q * 90`` degrees."""
CHANNELS: tuple[str, ...] = (
    "drivable_area",
    "lane_centerline",
    "lane_direction",
    *QUADRANT_CHANNELS,
    "lane_boundary",
    "crossing",
)
"""Every channel the rasteriser can draw."""
DEFAULT_CHANNELS: tuple[str, ...] = (
    "drivable_area",
    "lane_up",
    "lane_left",
    "lane_down",
    "lane_right",
    "lane_boundary",
    "crossing",
)
"""The default set: direction is encoded by which of four anti-aliased lane channels a lane is drawn in
(up = the agent's heading when rotated). ``lane_centerline`` is their maximum; it and the finer
``lane_direction`` sector code can be requested instead."""
CHANNEL_KIND: dict[str, FeatureKind] = {
    "drivable_area": FeatureKind.DRIVABLE_AREA,
    "lane_centerline": FeatureKind.LANE_CENTERLINE,
    "lane_direction": FeatureKind.LANE_CENTERLINE,
    "lane_right": FeatureKind.LANE_CENTERLINE,
    "lane_up": FeatureKind.LANE_CENTERLINE,
    "lane_left": FeatureKind.LANE_CENTERLINE,
    "lane_down": FeatureKind.LANE_CENTERLINE,
    "lane_boundary": FeatureKind.LANE_BOUNDARY,
    "crossing": FeatureKind.CROSSING,
}
RASTER_VERSION = "2"
"""Bumped whenever drawing changes in a way that alters pixels (part of the fingerprint)."""


class OffMapWarning(UserWarning):
    """The raster window holds no map feature (centre off the map, or no map for the log)."""


@dataclass(frozen=True)
class RasterSpec:
    """Everything that determines a raster's pixels (recorded with every raster shard).

    Attributes:
        size_px: image height = width, pixels.
        extent_m: side of the square window, metres (resolution = extent_m / size_px m/px).
        channels: channel names, in order (subset of ``CHANNELS``).
        rotate: rotate so the centre's heading points up; otherwise north up.
        direction_bins: sectors of the ``lane_direction`` channel (K).
        shift: fractional bits of the fixed-point vertex coordinates passed to OpenCV.
    """

    size_px: int = 224
    extent_m: float = 100.0
    channels: tuple[str, ...] = DEFAULT_CHANNELS
    rotate: bool = False
    direction_bins: int = 16
    shift: int = 8

    def __post_init__(self) -> None:
        unknown = [c for c in self.channels if c not in CHANNELS]
        if unknown or not self.channels:
            raise ValueError(f"unknown raster channels {unknown}; choose from {CHANNELS}")
        if self.size_px < 2 or self.extent_m <= 0 or not 1 <= self.direction_bins <= 255:
            raise ValueError(f"bad raster spec {self}")
        if not 0 <= self.shift <= 16:
            raise ValueError("shift must be in 0..16 (OpenCV's limit for sub-pixel drawing)")

    @property
    def resolution_m(self) -> float:
        """Metres per pixel."""
        return self.extent_m / self.size_px

    @property
    def shape(self) -> tuple[int, int, int]:
        """(C, H, W) of one raster."""
        return (len(self.channels), self.size_px, self.size_px)

    def to_dict(self) -> dict[str, Any]:
        """Plain dict for manifests (includes the drawing version)."""
        return {
            "size_px": self.size_px,
            "extent_m": self.extent_m,
            "resolution_m": self.resolution_m,
            "channels": list(self.channels),
            "rotate": self.rotate,
            "direction_bins": self.direction_bins,
            "shift": self.shift,
            "version": RASTER_VERSION,
        }

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> RasterSpec:
        """Inverse of ``to_dict`` (ignores derived keys)."""
        return cls(
            size_px=int(d["size_px"]),
            extent_m=float(d["extent_m"]),
            channels=tuple(d["channels"]),
            rotate=bool(d["rotate"]),
            direction_bins=int(d["direction_bins"]),
            shift=int(d["shift"]),
        )

    def fingerprint(self) -> str:
        """Short hash of ``to_dict()``: rasters made with another fingerprint must not be mixed."""
        blob = json.dumps(self.to_dict(), sort_keys=True).encode()
        return hashlib.sha256(blob).hexdigest()[:16]


def effective_heading(spec: RasterSpec, heading: float | None) -> float:
    """The heading (rad, CCW from world +x) the raster is drawn for: north up (pi/2) unless rotating."""
    if spec.rotate and heading is not None and math.isfinite(heading):
        return float(heading)
    return math.pi / 2.0


def _affine_terms(spec: RasterSpec, cx: float, cy: float, heading: float | None) -> tuple[float, ...]:
    """(a, b, tx, c, d, ty, t) with ``u = a x + b y + tx``, ``v = c x + d y + ty``; plain floats (hot path)."""
    t = effective_heading(spec, heading)
    s, c = math.sin(t), math.cos(t)
    inv = 1.0 / spec.resolution_m
    mid = (spec.size_px - 1) / 2.0
    a, b = s * inv, -c * inv
    cc, d = -c * inv, -s * inv
    return (a, b, mid - a * cx - b * cy, cc, d, mid - cc * cx - d * cy, t)


def world_to_pixel(spec: RasterSpec, cx: float, cy: float, heading: float | None = None) -> NDArrayFloat:
    """(2, 3) affine from world metres to pixel (u, v) for a raster centred on (cx, cy).

    With heading ``t`` (rad): forward = (cos t, sin t), left = (-sin t, cos t); image up = forward and
    image left = left, so ``u = c + (dx sin t - dy cos t) / res`` and ``v = c - (dx cos t + dy sin t) / res``.
    """
    a, b, tx, c, d, ty, _ = _affine_terms(spec, cx, cy, heading)
    return np.array([[a, b, tx], [c, d, ty]])


def to_fixed_point(points: NDArrayFloat, affine: NDArrayFloat, shift: int) -> NDArrayInt32:
    """(n, 2) world metres → int32 pixel coordinates x 2**shift (OpenCV sub-pixel input).

    Truncates instead of rounding (one NumPy call less per raster): the error is below 2**-shift px.
    """
    scale = float(1 << shift)
    p = points @ (affine[:, :2].T * scale)
    p += affine[:, 2] * scale
    return p.astype(np.int32)


def query_box(spec: RasterSpec, cx: float, cy: float, heading: float | None) -> tuple[float, float, float, float]:
    """World-frame bounding box (xmin, ymin, xmax, ymax) of the (possibly rotated) window plus one pixel."""
    t = effective_heading(spec, heading) - math.pi / 2.0
    half = spec.extent_m / 2.0 * (abs(math.cos(t)) + abs(math.sin(t))) + spec.resolution_m
    return (cx - half, cy - half, cx + half, cy + half)


def direction_values(k: int) -> NDArrayInt:
    """(K,) the ``lane_direction`` pixel value of each sector."""
    return (np.arange(k, dtype=np.int64) + 1) * 255 // k


def decode_direction(value: int, k: int) -> float | None:
    """Centre angle (rad, CCW from image right) of a ``lane_direction`` pixel value, None for 0."""
    if value == 0:
        return None
    b = int(np.argmin(np.abs(direction_values(k) - value)))
    return b * 2.0 * math.pi / k


@dataclass
class RasterResult:
    """One rendered raster.

    Attributes:
        image: (C, H, W) uint8.
        affine: (2, 3) world metres → pixel (u, v), see ``world_to_pixel``.
        heading: heading the raster was drawn for (rad); pi/2 means north up.
        n_features: map features (or chunks) drawn; 0 means the window was empty.
    """

    image: NDArrayByte
    affine: NDArrayFloat
    heading: float
    n_features: int

    @property
    def empty(self) -> bool:
        """No map feature fell inside the window."""
        return self.n_features == 0


_NO_CHUNKS: NDArrayInt = np.zeros(0, dtype=np.int64)


class Rasteriser:
    """Draws rasters of one map with one spec; build once per (map, spec), call ``render`` per sample.

    Not thread-safe: renders share per-layer scratch buffers (use one rasteriser per thread).

    Attributes:
        store: the map (None draws empty rasters, e.g. a log without a map).
        spec: raster parameters.
    """

    def __init__(self, store: MapStore | None, spec: RasterSpec) -> None:
        self.store = store
        self.spec = spec
        self._scale = float(1 << spec.shift)
        # Chunks whose pixel box misses [-2, size + 1] px are not drawn (anti-aliasing reaches ~1 px out).
        self._cull_lo = -2.0 * self._scale
        self._cull_hi = (spec.size_px + 1) * self._scale
        self._values = direction_values(spec.direction_bins).tolist()
        self._band_rows = BAND_ROWS
        self._scratch: dict[FeatureKind, PreparedLayer] = {}
        self._plan: list[tuple[int, str, FeatureKind]] = []
        # Chunk direction in sector units, offset by 0.5 (round to nearest) and by a whole number of turns
        # so that adding the heading term stays positive and int truncation equals floor.
        self._chord_units: NDArrayFloat = np.zeros(0)
        self._quad_units: NDArrayFloat = np.zeros(0)
        self._quadrant_plane: list[tuple[int, int]] = []  # (quadrant, channel index)
        if store is not None:
            for ci, name in enumerate(spec.channels):
                layer = store.render_layer(CHANNEL_KIND[name])
                if not len(layer):  # e.g. AV1 maps have no areas or boundaries: skip the empty queries
                    continue
                if layer.kind not in self._scratch:
                    self._scratch[layer.kind] = PreparedLayer(layer, self._band_rows)
                self._plan.append((ci, name, layer.kind))
                if name == "lane_direction":
                    k = spec.direction_bins
                    self._chord_units = layer.chord_angle * (k / (2.0 * math.pi)) + 0.5 + 4.0 * k
                if name in QUADRANT_CHANNELS:
                    self._quadrant_plane.append((QUADRANT_CHANNELS.index(name), ci))
                    self._quad_units = layer.chord_angle * (4.0 / (2.0 * math.pi)) + 0.5 + 16.0

    def memory_bytes(self) -> int:
        """Bytes held for drawing: the layers' geometry and index plus this rasteriser's scratch (vertex
        buffers and chunk views); proportional to the map's vertices, independent of the raster size."""
        total = 0
        for s in self._scratch.values():
            ly, band = s.band.layer, s.band
            total += sum(x.nbytes for x in (ly.points, ly.offsets, ly.lo, ly.hi, ly.features, ly.chord_angle))
            total += 8 * (len(ly.keys) + len(band.keys) + len(s.offsets))
            total += 8 * sum(len(t) for t in (ly.cell_start, band.start) if t is not None)
            total += band.order.nbytes + band.position.nbytes + s.pix.nbytes + s.homog.nbytes + s.boxes.nbytes
            total += len(s.views) * sys.getsizeof(s.pix[:1])
        return total

    def render(
        self,
        cx: float,
        cy: float,
        heading: float | None = None,
        *,
        warn: bool = True,
        out: NDArrayByte | None = None,
    ) -> RasterResult:
        """Rasterise the window centred on (cx, cy) (metres, world frame).

        Args:
            cx, cy: centre, metres, world frame.
            heading: rad CCW from world +x; used only when ``spec.rotate`` (None → north up).
            warn: emit ``OffMapWarning`` when the window holds no map feature.
            out: a zero-filled (C, H, W) uint8 array to draw into (e.g. a row of a shard allocated with
                ``np.zeros``), returned as the result's image; saves an allocation and a copy per raster.
        """
        spec = self.spec
        if out is None:
            img = np.zeros(spec.shape, dtype=np.uint8)
        elif out.shape != spec.shape or out.dtype != np.uint8:
            raise ValueError(f"out must be uint8 {spec.shape}, got {out.dtype} {out.shape}")
        else:
            img = out
        a, b, tx, c, d, ty, t = _affine_terms(spec, cx, cy, heading)
        sc = self._scale
        fa, fb, fc, fd, ftx, fty = a * sc, b * sc, c * sc, d * sc, tx * sc, ty * sc
        aa, ab, ac, ad = abs(fa), abs(fb), abs(fc), abs(fd)
        lo, hi = self._cull_lo, self._cull_hi
        # Every per-raster matrix from one array (one NumPy call instead of four):
        # * affine (2, 3): world → pixel, returned with the raster;
        # * lin (3, 2): fixed-point transform ``[u, v] = [x, y, 1] @ lin``, the product of ``to_fixed_point``;
        # * cull (4, 4) and thr (4,): chunk bounding box (centre x, centre y, half x, half y) @ cull gives
        #   (-lo_u, -lo_v, hi_u, hi_v) of its pixel box minus the offset; drawn when all four are <= thr
        #   (the box meets the image). Exact for the chunk's box north up, its rotated box otherwise (a
        #   superset: chunks drawn in vain draw nothing).
        # fmt: off
        k = np.array([
            a, b, tx, c, d, ty,
            fa, fc, fb, fd, ftx, fty,
            -fa, -fc, fa, fc, -fb, -fd, fb, fd, -aa, -ac, -aa, -ac, -ab, -ad, -ab, -ad,
            ftx - lo, fty - lo, hi - ftx, hi - fty,
        ])
        # fmt: on
        affine = k[:6].reshape(2, 3)
        drawn = 0
        if self._plan:
            box = query_box(spec, cx, cy, heading)
            drawn = self._draw(img, k[6:12].reshape(3, 2), k[12:28].reshape(4, 4), k[28:], t, box)
        if drawn == 0 and warn:
            warnings.warn(
                OffMapWarning(f"no map feature within {spec.extent_m} m of ({cx:.1f}, {cy:.1f})"), stacklevel=2
            )
        return RasterResult(img, affine, t, drawn)

    def _draw(
        self,
        img: NDArrayByte,
        lin: NDArrayFloat,
        cull: NDArrayFloat,
        thr: NDArrayFloat,
        t: float,
        box: tuple[float, float, float, float],
    ) -> int:
        """Draw every planned channel; returns the number of chunks drawn (over kinds)."""
        shift = self.spec.shift
        selected: dict[FeatureKind, NDArrayInt] = {}
        drawn = 0
        quadrants_done = False
        for ci, name, kind in self._plan:
            scratch = self._scratch[kind]
            sel = selected.get(kind)
            if sel is None:
                sel = selected[kind] = self._select(scratch, box, lin, cull, thr)
                drawn += len(sel)
            if not len(sel):
                continue
            views = scratch.views
            if name in QUADRANT_CHANNELS:
                if not quadrants_done:  # all four in one pass over the chunks
                    self._draw_quadrants(img, views, sel, t)
                    quadrants_done = True
            elif name == "lane_direction":
                self._draw_direction(img[ci], views, sel, t)
            elif kind is FeatureKind.DRIVABLE_AREA or kind is FeatureKind.CROSSING:
                plane = img[ci]
                for i in sel.tolist():  # one call each: fillPoly fills several contours even-odd
                    cv2.fillPoly(plane, [views[i]], 255, cv2.LINE_AA, shift)
            else:
                cv2.polylines(img[ci], [views[i] for i in sel.tolist()], False, 255, 1, cv2.LINE_AA, shift)
        return drawn

    def _select(
        self,
        scratch: PreparedLayer,
        box: tuple[float, float, float, float],
        lin: NDArrayFloat,
        cull: NDArrayFloat,
        thr: NDArrayFloat,
    ) -> NDArrayInt:
        """Layer chunks of the window to draw, ascending (the reference's order), their vertices
        transformed into ``scratch.pix``: each band slice in place, not gathered into a new array."""
        band = scratch.band
        ranges = band.ranges(*box)
        if not ranges:
            return _NO_CHUNKS
        o, homog, pix = scratch.offsets, scratch.homog, scratch.pix
        for lo, hi in ranges:
            # Assigning float to int32 truncates, as ``astype`` in ``to_fixed_point``.
            pix[o[lo] : o[hi]] = homog[o[lo] : o[hi]].dot(lin)
        order, boxes = band.order, scratch.boxes
        if len(ranges) == 1:
            lo, hi = ranges[0]
            ids, g = order[lo:hi], boxes[lo:hi]
        else:
            ids = np.concatenate([order[lo:hi] for lo, hi in ranges])
            g = np.concatenate([boxes[lo:hi] for lo, hi in ranges])
        # (k, 4) booleans viewed as one uint32 per chunk: "all four true" without a slow axis reduction.
        inside = g.dot(cull) <= thr
        sel: NDArrayInt = ids[inside.view(np.uint32).ravel() == 0x01010101]
        sel.sort()  # band order → layer order
        return sel

    def _draw_quadrants(self, img: NDArrayByte, views: list[NDArrayInt32], sel: NDArrayInt, heading: float) -> None:
        """Anti-aliased centerlines, each chunk into the channel of its travel-direction quadrant.

        Chunks keep their layer order within a quadrant, the order the reference draws them in, so the
        pixels are identical to drawing chunk by chunk.
        """
        units = self._quad_units[sel] + (math.pi / 2.0 - heading) * (4.0 / (2.0 * math.pi))
        quad = (units.astype(np.int64) & 3).tolist()
        # A plain loop beats argsort + fancy indexing or one mask per quadrant for the ~50 chunks drawn.
        groups: tuple[list[NDArrayInt32], ...] = ([], [], [], [])
        for i, q in zip(sel.tolist(), quad, strict=False):
            groups[q].append(views[i])
        shift = self.spec.shift
        for q, ci in self._quadrant_plane:
            if groups[q]:
                cv2.polylines(img[ci], groups[q], False, 255, 1, cv2.LINE_AA, shift)

    def _draw_direction(self, plane: NDArrayByte, views: list[NDArrayInt32], sel: NDArrayInt, heading: float) -> None:
        """Draw each centerline chunk with the value of its travel-direction sector in the image frame.

        A chunk's direction is its first-to-last vertex vector; centerline chunks turn by at most
        ``MAX_TURN_DEG`` (see ``Layer``), so each segment is within about one sector of it. Where lanes of
        different directions overlap, the higher sector value wins (sectors are drawn in ascending order).
        """
        k = self.spec.direction_bins
        # Image-frame angle: phi = world angle - heading + pi/2 (north up: heading = pi/2, phi = world).
        units = self._chord_units[sel] + (math.pi / 2.0 - heading) * (k / (2.0 * math.pi))
        sector = (units.astype(np.int64) % k).tolist()
        groups: list[list[NDArrayInt32]] = [[] for _ in range(k)]
        for i, s in zip(sel.tolist(), sector, strict=True):
            groups[s].append(views[i])
        values = self._values
        shift = self.spec.shift
        for s, batch in enumerate(groups):  # ascending sectors: the higher value wins where lanes overlap
            if batch:
                cv2.polylines(plane, batch, False, values[s], 1, cv2.LINE_8, shift)


def heading_from_motion(xy: NDArrayFloat, min_disp_m: float = 0.5) -> float | None:
    """Heading (rad, CCW from world +x) at the last row of ``xy`` (T, 2) from the agent's own motion.

    Uses the vector from the latest earlier position at least ``min_disp_m`` away to the last position, so
    a stopped or jittering agent looks further back instead of returning noise. NaN rows are ignored.
    Returns None when the last position is NaN or the agent never moved that far.
    """
    pts = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    if not len(pts) or not np.isfinite(pts[-1]).all():
        return None
    d = np.hypot(pts[:-1, 0] - pts[-1, 0], pts[:-1, 1] - pts[-1, 1])
    far = np.flatnonzero(np.nan_to_num(d, nan=-1.0) >= min_disp_m)
    if not len(far):
        return None
    v = pts[-1] - pts[far[-1]]
    return float(math.atan2(v[1], v[0]))
