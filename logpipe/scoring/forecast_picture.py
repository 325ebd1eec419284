"""One forecast drawn over its map raster as a PNG, the picture ``make demo`` names and the README shows: the
raster's lanes (green), drivable area (red) and boundaries (blue) as the viewers colour them, each target's observed
history (grey), its true future (orange) and its K forecasts (blue, more opaque the higher their score), with a
legend. The colours are the viewers' (``logpipe.mcap.forecast_scene``).

``python -m logpipe.scoring.forecast_picture RUN --truth DATASET --out PICTURE.png [--sample ID]``
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from logpipe.dataset.reader import Dataset
from logpipe.errors import DatasetError
from logpipe.mcap.forecast_scene import HISTORY_RGBA, MODE_RGB, TRUTH_RGBA
from logpipe.mcap.raster_image import raster_rgb
from logpipe.prediction.runs import PredictionRun
from logpipe.raster.runs import find_raster_run
from logpipe.storage.io import atomic_path


def _to_pixels(affine: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """World metres (N, 2) → raster pixel (column, row) through the (2, 3) world→pixel affine."""
    out: np.ndarray = xy @ affine[:, :2].T + affine[:, 2]
    return out


def render_forecast_picture(run_dir: Path, dataset_dir: Path, out: Path, sample_id: str | None = None) -> Path:
    """Draw ``sample_id`` (default: the run's first sample that has a raster) of the prediction run ``run_dir``
    over its raster in ``dataset_dir``'s raster run; writes ``out`` (PNG, atomically) and returns it.

    Raises:
        DatasetError: the dataset has no raster run, or the sample has no raster or no forecast.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rasters = find_raster_run(dataset_dir, None, None)
    if rasters is None:
        raise DatasetError(f"{dataset_dir}: no raster run to draw the forecast over; run `logpipe rasterise`")
    table = PredictionRun.open(run_dir).table()
    have = set(rasters.index.column("sample_id").to_pylist())
    ids = [s for s in dict.fromkeys(table.column("sample_id").to_pylist()) if s in have]
    chosen = sample_id or (ids[0] if ids else None)
    if chosen is None or chosen not in ids:
        raise DatasetError(f"{run_dir}: no forecast of {'a rastered sample' if chosen is None else chosen} to draw")
    rows = table.filter(np.asarray(table.column("sample_id").to_pylist()) == chosen).to_pylist()
    raster, affine = rasters.get(chosen)
    ds = Dataset.open(dataset_dir)
    sample = next(s for s in ds.samples().to_pylist() if s["sample_id"] == chosen)
    tracks = ds.log_tracks(str(sample["log_id"])).to_pylist()

    fig, ax = plt.subplots(figsize=(6, 6), dpi=110)
    ax.imshow(raster_rgb(np.asarray(raster), rasters.spec.channels))
    top = max(r["score"] for r in rows) or 1.0
    for target in dict.fromkeys(r["track_id"] for r in rows):
        own = [(t["timestamp_ns"], t["x"], t["y"]) for t in tracks if t["track_id"] == target]
        past = np.array([(x, y) for ts, x, y in own if sample["start_ns"] <= ts <= sample["current_ns"]])
        future = np.array([(x, y) for ts, x, y in own if sample["current_ns"] <= ts <= sample["end_ns"]])
        for line, colour in ((past, HISTORY_RGBA), (future, TRUTH_RGBA)):
            if len(line):
                px = _to_pixels(affine, line)
                ax.plot(px[:, 0], px[:, 1], color=colour[:3], lw=3.0, zorder=2)
        for r in (r for r in rows if r["track_id"] == target):  # forecasts on top, each from the current point
            mode = _to_pixels(affine, np.column_stack([[past[-1][0], *r["x"]], [past[-1][1], *r["y"]]]))
            ax.plot(mode[:, 0], mode[:, 1], color=MODE_RGB, lw=1.2, zorder=3,
                    alpha=0.25 + 0.75 * max(r["score"], 0) / top)
    ax.plot([], [], color=HISTORY_RGBA[:3], lw=2.5, label="history")
    ax.plot([], [], color=TRUTH_RGBA[:3], lw=2.5, label="truth")
    modes = len(rows) // max(1, len({r["track_id"] for r in rows}))
    ax.plot([], [], color=MODE_RGB, lw=1.5, label=f"forecasts (K={modes})")
    ax.plot([], [], color=(0.0, 1.0, 0.0), lw=1.5, label="lanes (raster)")
    ax.legend(loc="lower right", fontsize=8, framealpha=0.85)
    ax.set_title(f"{chosen}: {rows[0]['object_type']} forecast over its map raster", fontsize=9)
    ax.set_xlim(0, raster.shape[2])
    ax.set_ylim(raster.shape[1], 0)
    ax.set_xticks([])
    ax.set_yticks([])
    fig.tight_layout()
    with atomic_path(out) as tmp:
        fig.savefig(tmp, format="png")
    plt.close(fig)
    return out


def main(argv: list[str] | None = None) -> None:
    """``python -m logpipe.scoring.forecast_picture RUN --truth DATASET --out PNG [--sample ID]``."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run", type=Path)
    parser.add_argument("--truth", type=Path, required=True)
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--sample", default=None)
    args = parser.parse_args(argv)
    print(render_forecast_picture(args.run, args.truth, args.out, args.sample))


if __name__ == "__main__":
    main()
