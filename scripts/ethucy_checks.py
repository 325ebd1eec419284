"""The ETH/UCY reproduction's checks beyond its main table: the frame-rate check's resampled validation files, and
the diagnoses nothing is chosen with (standing and moving pedestrians, per-agent paired differences with a block
bootstrap over test windows). Positions in metres, the Social-GAN files' frames at 25 fps."""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from logpipe.dataset.reader import Dataset
from logpipe.dataset.resample import ResampleSpec, resample_track
from logpipe.formats.ethucy import FRAME_PERIOD_NS
from logpipe.model.predictor import Predictor
from logpipe.model.zhu2020.predictor import NetPredictor
from logpipe.scoring import metrics
from logpipe.storage.io import atomic_open
from logpipe.types import NDArrayBool, NDArrayFloat, NDArrayInt, SceneSample
from scripts.locations import ensure_dataset, find_checkpoint
from scripts.validation import K_BEST, best_of_k, truth_of, tuned

STILL_STEP_M = 0.03
"""A pedestrian whose last observed step is shorter than this (metres) counts as standing in the motion breakdown."""

STAY_RADIUS_M = 0.5
"""A standing pedestrian within this distance (metres) of where it stood at the last predicted step stayed."""

FRAME_RATE_SHIFT = 10 / 6
"""Factor of the frame-rate check: ``S/val`` resampled so that one step spans this many of its 0.4 s steps. The
original ETH annotations are 6 video frames (0.4 s) apart and Social-GAN's biwi_eth has 10-frame steps with more
rows (see the data's SOURCE.md and agrimgupta92/sgan#84): if its 10-frame step was made from the 6-frame ones, each
biwi_eth step spans 10/6 x 0.4 s of the recording, a longer time as well as a faster walk."""

MOTION_METHODS = ("cv_sampler", "noise_lstm", "zhu2020")
"""Methods of the motion breakdown: the best-of-20 ones of the main table."""

PAIRED_BASELINES = {"noise_lstm": "Noise-LSTM", "cv_sampler": "CV sampler"}
"""Baselines the paper's method is paired with agent by agent (the best-of-20 rows nearest to it), and their labels."""


def rate_shifted_text(path: Path, factor: float = FRAME_RATE_SHIFT) -> str:
    """A Social-GAN ``frame ped x y`` file resampled (linear interpolation within each track) to one step per
    ``factor`` of its 0.4 s steps, written back with 10-frame steps: each step then spans ``factor`` times the time
    of the recording it did, as in biwi_eth if its steps were relabelled (``FRAME_RATE_SHIFT``)."""
    step_frames = 10  # Social-GAN's annotation step, 0.4 s of the 25 fps video
    rows = np.loadtxt(path, ndmin=2)  # the rewritten file is validated when it is ingested
    spec = ResampleSpec(hz=1e9 / (step_frames * FRAME_PERIOD_NS * factor))
    out: list[tuple[int, float, float, float]] = []
    for ped in np.unique(rows[:, 1]):
        track = rows[rows[:, 1] == ped]
        t_ns = np.rint(track[:, 0] * FRAME_PERIOD_NS).astype(np.int64)
        grid, xy = resample_track(t_ns, {"x": track[:, 2], "y": track[:, 3]}, spec)
        steps = np.rint(grid / spec.period_ns).astype(np.int64)
        out += [(step_frames * int(s), float(ped), float(x), float(y))
                for s, x, y in zip(steps, xy["x"], xy["y"], strict=True)]
    out.sort()
    return "".join(f"{f:.1f}\t{p:.1f}\t{x:.4f}\t{y:.4f}\n" for f, p, x, y in out)


def rate_shifted_dataset(data: Path, work: Path) -> Dataset:
    """The frame-rate check's dataset: every ``<scene>/val`` file of ``data`` through ``rate_shifted_text``,
    ingested like the real ones (so the windows follow the same protocol)."""
    files = work / "files"
    for src in sorted(data.glob("*/val/*.txt")):
        dst = files / src.relative_to(data)
        text = rate_shifted_text(src)
        if not dst.is_file() or dst.read_text() != text:  # unchanged files keep their ingest
            with atomic_open(dst, "w") as fh:
                fh.write(text)
    return ensure_dataset(files, work / "dataset", "ethucy")


def motion_groups(samples: Sequence[SceneSample], pred_len: int, min_agents: int) -> dict[str, NDArrayBool]:
    """Masks over ``truth_of(samples)`` rows of the agents in windows with >= ``min_agents`` targets and a full
    future: ``standing`` (last observed step under ``STILL_STEP_M``) split into ``stays`` (within ``STAY_RADIUS_M``
    of where it stood at the last predicted step) and ``starts``; ``moving``; ``all``."""
    crowded = np.concatenate([np.full(int(s.target_mask.sum()), int(s.target_mask.sum()) >= min_agents)
                              for s in samples])
    track = np.concatenate([s.positions[s.target_mask, s.obs_len - 2 : s.obs_len + pred_len] for s in samples])
    last_step = np.linalg.norm(track[:, 1] - track[:, 0], axis=-1)
    moved = np.linalg.norm(track[:, -1] - track[:, 1], axis=-1)
    ok = crowded & np.all(np.isfinite(track), axis=(1, 2))
    standing = ok & (last_step < STILL_STEP_M)
    return {"standing": standing, "stays": standing & (moved < STAY_RADIUS_M),
            "starts": standing & (moved >= STAY_RADIUS_M), "moving": ok & (last_step >= STILL_STEP_M), "all": ok}


def motion_breakdown(samples: Sequence[SceneSample], forecasts: dict[str, NDArrayFloat], pred_len: int,
                     min_agents: int) -> dict[str, Any]:
    """The agents of ``motion_groups`` (their counts) and each method's per-agent best-of-K ADE/FDE on each group,
    from ``forecasts`` (method -> (N, K, T, 2) in ``truth_of`` order). A diagnosis; nothing is chosen with it."""
    groups = motion_groups(samples, pred_len, min_agents)
    truth = truth_of(samples, pred_len)
    out: dict[str, Any] = {"agents": {g: int(m.sum()) for g, m in groups.items()}, "methods": {}}
    for method, pred in forecasts.items():
        out["methods"][method] = {g: best_of_k(pred[m], truth[m]) for g, m in groups.items() if m.any()}
    return out


def window_blocks(samples: Sequence[SceneSample]) -> NDArrayInt:
    """A cluster label per ``truth_of(samples)`` row: windows of one log whose start steps fall in the same block of
    one window length (obs + pred steps), so windows that share most of their frames resample together."""
    keys = []
    for s in samples:
        log, start = s.sample_id.rsplit(":", 1)
        keys += [f"{log}:{int(start) // len(s.timestamps_ns)}"] * int(s.target_mask.sum())
    return np.unique(np.asarray(keys), return_inverse=True)[1].astype(np.int64)


def paired_differences(samples: Sequence[SceneSample], forecasts: dict[str, NDArrayFloat], pred_len: int,
                       min_agents: int) -> dict[str, Any]:
    """The paper's method minus each of ``PAIRED_BASELINES``, per agent (best-of-K per agent ADE and FDE, on the
    agents of ``motion_groups``' ``all``): mean and 95 % block-bootstrap interval (``window_blocks``)."""
    ok = motion_groups(samples, pred_len, min_agents)["all"]
    truth = truth_of(samples, pred_len)[ok]
    blocks = window_blocks(samples)[ok]
    scores = {m: metrics.best_of_k_per_agent(metrics.displacement_errors(p[ok], truth))
              for m, p in forecasts.items()}
    out: dict[str, Any] = {}
    if "zhu2020" not in scores:
        return out
    for base in (b for b in PAIRED_BASELINES if b in scores):
        out[base] = {key: dataclasses.asdict(metrics.paired_difference_interval(
            getattr(scores["zhu2020"], key) - getattr(scores[base], key), blocks)) for key in ("ade", "fde")}
    return out


def val_forecasts(sampler: Predictor, templates: dict[str, str], noise: dict[str, Any], scene: str, kind: str,
                  val: Sequence[SceneSample], seed: int) -> dict[str, NDArrayFloat]:
    """The ``MOTION_METHODS``' K=20 forecasts of ``val`` at their settings chosen there (``noise``: method -> the
    inference choice), for the motion breakdown; a learned method without a checkpoint is left out."""
    out = {"cv_sampler": np.concatenate(sampler.predict(val, K_BEST, seed))}
    for method in MOTION_METHODS[1:]:
        ckpt = find_checkpoint(templates[method], scene)
        if ckpt is not None and method in noise:
            net = tuned(NetPredictor.from_checkpoint(ckpt, expect_kind=kind), noise[method])
            out[method] = np.concatenate(net.predict(val, K_BEST, seed))
    return out
