"""How far AV2 rasters drawn from the lanelet conversion (what SYNTHETIC AV2-map scenes carry) are from rasters drawn
from the real AV2 map JSON (what real AV2 logs are rasterised with): per channel, pixel IoU (value > 127) and mean
absolute difference over windows centred on lane centerline points, heading along the lane (the ``--rotate`` view).

``python -m scripts.synthetic_av2_rasters --shared ../shared/data [--every 40] [--out FILE.json]``.
"""

from __future__ import annotations

import argparse
import json
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from logpipe.maps import load_map
from logpipe.raster.rasteriser import Rasteriser, RasterSpec
from logpipe.synthetic import scenes
from logpipe.synthetic.roads import LaneExtras, build_roads


def compare(json_path: Path, every: int) -> dict[str, object]:
    """Per-channel IoU and mean |difference| (0-255) of the two renderings of one AV2 map."""
    real = load_map(json_path)
    converted = scenes.av2_source(json_path).store
    spec = RasterSpec(rotate=True)
    a, b = Rasteriser(real, spec), Rasteriser(converted, spec)
    roads = build_roads(converted, LaneExtras(), scenes.CITY_LIMIT, np.random.default_rng(0))
    rows = np.arange(0, len(roads.pts), every)
    inter = np.zeros(len(spec.channels))
    union = np.zeros(len(spec.channels))
    diff = np.zeros(len(spec.channels))
    for r in rows.tolist():
        x, y = roads.pts[r]
        ra = a.render(float(x), float(y), float(roads.heading[r]), warn=False).image
        rb = b.render(float(x), float(y), float(roads.heading[r]), warn=False).image
        on_a, on_b = ra > 127, rb > 127
        inter += (on_a & on_b).sum(axis=(1, 2))
        union += (on_a | on_b).sum(axis=(1, 2))
        diff += np.abs(ra.astype(np.int16) - rb.astype(np.int16)).mean(axis=(1, 2))
    return {
        "map": json_path.name, "windows": len(rows),
        "iou": {c: round(float(i / u), 3) if u else None for c, i, u in zip(spec.channels, inter, union, strict=True)},
        "mean_abs_diff": {c: round(float(d / len(rows)), 2) for c, d in zip(spec.channels, diff, strict=True)},
    }


def main(argv: Sequence[str] | None = None) -> int:
    """Compare every AV2 map under ``--shared``; print and write the JSON."""
    ap = argparse.ArgumentParser(prog="python -m scripts.synthetic_av2_rasters", description=__doc__.split("\n\n")[0])
    ap.add_argument("--shared", type=Path, default=Path("../shared/data"))
    ap.add_argument("--every", type=int, default=40, help="a window at every N-th resampled centerline point")
    ap.add_argument("--out", type=Path, default=Path("out/synthetic_av2_rasters.json"))
    args = ap.parse_args(argv)
    result = [compare(p, args.every) for p in sorted(args.shared.glob("av2/**/log_map_archive_*.json"))]
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=1) + "\n")
    print(json.dumps(result, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
