"""The PNG plots of a score report: ``horizon.png`` (error against horizon per method) and ``scenes_<method>.png``
(a grid of samples: history, truth and the K forecasts, over the map raster when the dataset has one).

Positions are metres in the world frame; over a raster they are drawn in its pixel frame (``u`` right, ``v``
down) through the raster's world→pixel affine. Files are returned as bytes: ``logpipe.scoring.reports`` commits them.
"""

from __future__ import annotations

import io
import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc

from logpipe.dataset.reader import Dataset
from logpipe.errors import DatasetError
from logpipe.raster.runs import RasterShards, find_raster_run
from logpipe.types import NDArrayFloat, SceneSample


class Forecasts(Protocol):
    """What the plots read of one method's forecasts (``logpipe.scoring.method_forecasts.MethodForecasts``)."""

    sample_ids: Any  # (N,) sample of each agent row
    track_ids: Any  # (N,) track of each agent row
    pred: NDArrayFloat  # (N, K, T, 2) metres, world frame

    @property
    def num_modes(self) -> int: ...


@dataclass(frozen=True)
class ScoredMethod:
    """One method as scored: its forecasts, and the true futures (M, T, 2) metres and samples (M,) of the
    agents that counted."""

    forecasts: Forecasts
    truth: NDArrayFloat
    sample_ids: Any


def _png(fig: Any, dpi: int) -> bytes:
    """The figure as PNG bytes (the report folder commits files it has whole, see ``write_report_folder``)."""
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", dpi=dpi)
    return buffer.getvalue()


def render_plots(report: dict[str, Any], scored: Mapping[str, ScoredMethod], ds: Dataset,
                 plot_samples: int) -> dict[str, bytes]:
    """``horizon.png`` (error vs horizon per method) and ``scenes_<method>.png`` (a grid of samples: history,
    truth and the K forecasts, over the map raster when the dataset has a raster run): file name -> PNG bytes."""
    import matplotlib

    matplotlib.use("Agg")  # files only, no display
    import matplotlib.pyplot as plt

    files: dict[str, bytes] = {}
    horizon = report["protocol"]["horizon_s"]
    fig, ax = plt.subplots(figsize=(7, 4.5))
    colours = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    for i, (name, e) in enumerate(report["methods"].items()):
        for k, style in zip(sorted({e["ks"][0], e["ks"][-1]}), ("-", "--"), strict=False):
            b = e["overall"].get(f"k{k}")
            if b:
                ax.plot(horizon, b["error_by_step"], style, marker=".", color=colours[i % len(colours)],
                        label=f"{name} K={k}")
    ax.set_xlabel("horizon (s)")
    ax.set_ylabel("mean L2 error (m)")
    ax.set_title("Error by horizon (mode with the lowest ADE of the first K)")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7, ncol=2)
    fig.tight_layout()
    files["horizon.png"] = _png(fig, 110)
    plt.close(fig)
    if plot_samples <= 0 or not scored:
        return files
    # The same samples for every method: evenly spread over the sample ids all methods scored.
    common = sorted(set.intersection(*(set(v.sample_ids.tolist()) for v in scored.values())))
    if not common:
        return files
    # Prefer samples where someone moves (standing pedestrians make empty-looking panels): the half with the
    # longest true displacement, then evenly spread in id order.
    first = next(iter(scored.values()))
    sids = first.sample_ids
    travel = np.linalg.norm(first.truth[:, -1] - first.truth[:, 0], axis=-1)
    best: dict[str, float] = {}
    for sid, d in zip(sids.tolist(), travel.tolist(), strict=True):
        best[sid] = max(best.get(sid, 0.0), d)
    moving = [s for s in common if best.get(s, 0.0) >= float(np.median([best.get(c, 0.0) for c in common]))]
    pool = moving or common
    pick = sorted({pool[int(i)] for i in np.linspace(0, len(pool) - 1, min(plot_samples, len(pool)))})
    scenes = _scene_samples(ds, pick)
    try:
        rasters = find_raster_run(ds.root, None, None)
    except DatasetError:  # several raster runs: the map under the plots is decoration, so draw tracks only
        rasters = None
    for name, method in scored.items():
        fname, data = _scene_grid(plt, name, method.forecasts, pick, scenes, rasters)
        files[fname] = data
    return files


def _scene_samples(ds: Dataset, ids: list[str]) -> dict[str, SceneSample]:
    keep = pc.is_in(pc.field("sample_id"), value_set=pa.array(ids, pa.string()))
    return {s.sample_id: s for s in ds.iter_scene_samples(keep)}


def _scene_grid(plt: Any, name: str, m: Forecasts, pick: list[str], scenes: dict[str, SceneSample],
                rasters: RasterShards | None) -> tuple[str, bytes]:
    cols = min(3, len(pick))
    rows = math.ceil(len(pick) / cols)
    fig, axes = plt.subplots(rows, cols, figsize=(4.2 * cols, 4.2 * rows), squeeze=False)
    row_of = {(s, t): i for i, (s, t) in enumerate(zip(m.sample_ids.tolist(), m.track_ids.tolist(), strict=True))}
    for ax, sid in zip(axes.ravel(), pick, strict=False):
        s = scenes.get(sid)
        if s is None:
            ax.set_visible(False)
            continue
        affine = None
        if rasters is not None:
            try:
                img, affine = rasters.get(sid)
                ax.imshow(np.asarray(img).max(axis=0), cmap="Greys", vmin=0, vmax=400, origin="upper")
            except KeyError:
                affine = None

        def to_px(xy: NDArrayFloat, a: Any = affine) -> NDArrayFloat:
            if a is None:
                return xy
            out: NDArrayFloat = xy @ a[:, :2].T + a[:, 2]
            return out

        for a in np.flatnonzero(s.target_mask):
            hist = to_px(s.positions[a, : s.obs_len])
            fut = to_px(s.positions[a, s.obs_len - 1 :])
            ax.plot(hist[:, 0], hist[:, 1], "-", color="tab:blue", lw=1.5)
            ax.plot(fut[:, 0], fut[:, 1], "-", color="tab:green", lw=1.5)
            r = row_of.get((sid, s.track_ids[a]))
            if r is not None:
                cur = s.positions[a, s.obs_len - 1]
                for k in range(m.num_modes):
                    path = to_px(np.vstack([cur, m.pred[r, k]]))
                    ax.plot(path[:, 0], path[:, 1], "--", color="tab:red", lw=0.8, alpha=0.6)
        ax.set_title(sid, fontsize=8)
        ax.set_aspect("equal", adjustable="datalim")
        if affine is None:
            ax.grid(alpha=0.3)
        ax.tick_params(labelsize=6)
    for ax in axes.ravel()[len(pick):]:
        ax.set_visible(False)
    fig.suptitle(f"{name} (K={m.num_modes}): history blue, truth green, forecasts red dashed", fontsize=9)
    fig.tight_layout()
    safe = "".join(c if c.isalnum() or c in "-_" else "_" for c in name)
    fname = f"scenes_{safe}.png"
    data = _png(fig, 75)
    plt.close(fig)
    return fname, data
