"""The straightforward reference rasteriser the fast ``logpipe.raster.rasteriser.Rasteriser`` is held to: same geometry,
transform and drawing primitives, no index and no batching (tests compare pixels, the benchmark speeds)."""

from __future__ import annotations

import math

import cv2
import numpy as np

from logpipe.maps import FeatureKind, MapStore
from logpipe.raster.rasteriser import (
    CHANNEL_KIND,
    QUADRANT_CHANNELS,
    RasterSpec,
    direction_values,
    effective_heading,
    query_box,
    to_fixed_point,
    world_to_pixel,
)
from logpipe.types import NDArrayByte


def render_baseline(
    store: MapStore | None, spec: RasterSpec, cx: float, cy: float, heading: float | None
) -> NDArrayByte:
    """Straightforward reference rasteriser: a linear scan of every chunk of the map and one OpenCV call
    per chunk. Same geometry, transform and drawing primitives as ``Rasteriser.render``, no index and no
    batching; used by the tests and the benchmark as ground truth and as the speed baseline.
    """
    img = np.zeros(spec.shape, dtype=np.uint8)
    if store is None:
        return img
    affine = world_to_pixel(spec, cx, cy, heading)
    t = effective_heading(spec, heading)
    xmin, ymin, xmax, ymax = query_box(spec, cx, cy, heading)
    k = spec.direction_bins
    values = direction_values(k)
    for ci, name in enumerate(spec.channels):
        layer = store.render_layer(CHANNEL_KIND[name])
        for i in range(len(layer)):
            lo, hi = layer.lo[i], layer.hi[i]
            if hi[0] < xmin or lo[0] > xmax or hi[1] < ymin or lo[1] > ymax:
                continue
            pts = layer.points[layer.offsets[i] : layer.offsets[i + 1]]
            pix = to_fixed_point(pts, affine, spec.shift)
            phi = float(layer.chord_angle[i]) - t + math.pi / 2.0
            if name == "lane_direction":
                sector = math.floor(phi * k / (2.0 * math.pi) + 0.5) % k
                cv2.polylines(img[ci], [pix], False, int(values[sector]), 1, cv2.LINE_8, spec.shift)
            elif name in QUADRANT_CHANNELS:
                if math.floor(phi * 4 / (2.0 * math.pi) + 0.5) % 4 == QUADRANT_CHANNELS.index(name):
                    cv2.polylines(img[ci], [pix], False, 255, 1, cv2.LINE_AA, spec.shift)
            elif layer.kind in (FeatureKind.DRIVABLE_AREA, FeatureKind.CROSSING):
                cv2.fillPoly(img[ci], [pix], 255, cv2.LINE_AA, spec.shift)
            else:
                cv2.polylines(img[ci], [pix], False, 255, 1, cv2.LINE_AA, spec.shift)
    return img
