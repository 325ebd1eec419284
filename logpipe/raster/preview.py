"""PNG previews of rasters (``logpipe rasterise --preview N``): the raster's channels as a colour composite, 3x
enlarged, with every track of the sample's window drawn over it: observed steps solid, future steps dotted.

Colours (BGR): centre track / ego cyan, focal / targets red, other agents white; lanes coloured by direction.
Pixel positions come from the raster's own affine (world metres → pixels), so tracks sit where the raster put them.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import cv2
import numpy as np

from logpipe.errors import DatasetError
from logpipe.raster.centre import Centre, LogView
from logpipe.raster.rasteriser import RasterSpec, direction_values
from logpipe.storage.io import atomic_path
from logpipe.types import NDArrayByte, NDArrayFloat

_PREVIEW_SCALE = 3  # 224 px -> 672 px so tracks stay readable
_SUBPIXEL = 16  # OpenCV draws at 1/16 px (shift=4), so anti-aliased tracks are not snapped to whole pixels

_QUADRANT_COLOURS = {
    # Direction quadrants (BGR): up = green, down = blue, left = orange, right = magenta.
    "lane_up": (80, 200, 80),
    "lane_down": (220, 120, 40),
    "lane_left": (40, 160, 255),
    "lane_right": (255, 80, 220),
}


def write_preview(
    png: Path,
    image: NDArrayByte,
    affine: NDArrayFloat,
    spec: RasterSpec,
    view: LogView,
    sample: dict[str, Any],
    centre: Centre,
) -> None:
    """Write ``png``: the colour composite of ``image`` (C, H, W) with the sample's tracks drawn over it.

    ``affine`` is the raster's world (metres) → pixel transform; ``view`` holds the log's tracks.
    """
    big = _composite(image, spec)
    _draw_tracks(big, affine, view, sample, centre)
    orient = f"heading={centre.heading_source}" if spec.rotate else "north up"
    label = f"{sample['sample_id']}  centre={centre.role}  {orient}"
    cv2.putText(big, label, (6, 18), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (255, 255, 255), 1, cv2.LINE_AA)
    png.parent.mkdir(parents=True, exist_ok=True)
    ok, buf = cv2.imencode(".png", big)
    if not ok:
        raise DatasetError(f"could not encode preview {png}")
    with atomic_path(png) as tmp:
        tmp.write_bytes(buf.tobytes())


def _composite(image: NDArrayByte, spec: RasterSpec) -> NDArrayByte:
    """The raster's channels blended into one BGR uint8 image, ``_PREVIEW_SCALE`` times the raster's size."""
    ch = {name: image[i] for i, name in enumerate(spec.channels)}
    size = spec.size_px
    bgr = np.zeros((size, size, 3), np.float32)
    if "drivable_area" in ch:
        bgr += ch["drivable_area"][..., None].astype(np.float32) / 255.0 * np.array([60, 60, 60], np.float32)
    if "crossing" in ch:
        bgr += ch["crossing"][..., None].astype(np.float32) / 255.0 * np.array([120, 60, 0], np.float32)
    if "lane_boundary" in ch:
        bgr += ch["lane_boundary"][..., None].astype(np.float32) / 255.0 * np.array([0, 140, 170], np.float32)
    for name, rgb in _QUADRANT_COLOURS.items():
        if name in ch:
            a = ch[name].astype(np.float32)[..., None] / 255.0
            bgr = bgr * (1 - a) + np.array(rgb, np.float32) * a
    if "lane_centerline" in ch:
        line = ch["lane_centerline"].astype(np.float32) / 255.0
        colour = np.full((size, size, 3), 200.0, np.float32)
        if "lane_direction" in ch:
            # Hue from the direction sector, so opposite lanes read as different colours.
            k = spec.direction_bins
            vals = direction_values(k)
            d = ch["lane_direction"]
            sector = np.argmin(np.abs(d[..., None].astype(np.int64) - vals[None, None, :]), axis=2)
            hsv = np.stack([(sector * 180 // k).astype(np.uint8), np.full_like(d, 200), np.full_like(d, 255)], axis=2)
            hue = cv2.cvtColor(hsv, cv2.COLOR_HSV2BGR).astype(np.float32)
            colour = np.where((d > 0)[..., None], hue, colour)
        bgr = bgr * (1 - line[..., None]) + colour * line[..., None]
    big = cv2.resize(
        np.clip(bgr, 0, 255).astype(np.uint8),
        None,
        fx=_PREVIEW_SCALE,
        fy=_PREVIEW_SCALE,
        interpolation=cv2.INTER_NEAREST,
    )
    return np.asarray(big, dtype=np.uint8)  # already uint8: no copy, only the type for mypy


def _draw_tracks(big: NDArrayByte, affine: NDArrayFloat, view: LogView, sample: dict[str, Any],
                 centre: Centre) -> None:
    """Draw every track of the sample's window into ``big`` (in place): observed steps as a line ending in a
    ring at the current position, future steps as dots (every second one)."""
    start, cur, end = int(sample["start_step"]), int(sample["current_step"]), int(sample["end_step"])
    targets = {str(t) for t in sample.get("target_track_ids") or []}
    for track_id in view.windows.track_ids():
        rows = view.rows(track_id, start, end)
        if not len(rows):
            continue
        xy = np.stack([view.x[rows], view.y[rows]], axis=1)
        uv = (xy @ affine[:, :2].T + affine[:, 2] + 0.5) * _PREVIEW_SCALE
        obs = view.step[rows] <= cur
        pen = _pen(track_id, str(view.role[rows[0]]), centre, targets)
        pts = np.round(uv * _SUBPIXEL).astype(np.int32)
        if obs.sum() >= 2:
            cv2.polylines(big, [pts[obs]], False, pen, 2, cv2.LINE_AA, 4)
        for p in pts[~obs][::2]:
            cv2.circle(big, (int(p[0]), int(p[1])), 2 * _SUBPIXEL, pen, -1, cv2.LINE_AA, 4)
        if obs.any():
            q = pts[obs][-1]
            cv2.circle(big, (int(q[0]), int(q[1])), 4 * _SUBPIXEL, pen, 1, cv2.LINE_AA, 4)


def _pen(track_id: str, role: str, centre: Centre, targets: set[str]) -> tuple[int, int, int]:
    """BGR colour of a track: centre/ego cyan, focal/targets red, everyone else white."""
    if track_id == centre.track_id or role == "ego":
        return (255, 255, 0)
    if track_id in targets or role == "focal":
        return (0, 0, 255)
    return (235, 235, 235)
