"""What the full Argoverse sets would cost: every stage timed on a replica of ~2,000 AV1 sequences, projected.

The replica is the 69 real AV1 sequences copied to ``--sequences`` files that differ in the AV's track id (so
content hashing keeps them apart; the benchmark's corpus). Timed here, each in this process, on this machine:
``ingest`` (Parquet, every fully observed vehicle but the AV a target, as the driving model trains) and
``rasterise`` (ego-centred, turned to the ego's heading, AV1 city lane centerlines) with 1 and 2 workers; ``train``
(the full model of ``configs/argoverse_logs.toml``, batch 8, one torch thread) per 1,000 steps; ``predict`` (the
shipped driving model, K = 6, Parquet only; and constant velocity) per 1,000 samples with 1 and 2 threads. FLOPs per
sample (``torch.utils.flop_counter``) give the GPU column: no GPU here, so that column is a projection from an
assumed sustained rate, stated beside it.

    python -m scripts.replica_cost [--sequences 2000] [--work out/replica_cost] [--results docs/results]
"""

from __future__ import annotations

import argparse
import json
import math
import os
import shutil
import sys
import time
from collections.abc import Callable
from functools import partial
from pathlib import Path
from typing import Any

import torch

from logpipe.api import ingest, predict, rasterise, train

from .locations import CHECKPOINTS, REPO

AV_ID = b"00000000-0000-0000-0000-000000000000"
# The full sets (sequences). AV1: Chang et al., CVPR 2019 (train / val / test). AV2 motion forecasting: Wilson et
# al., NeurIPS 2021 Datasets; its scenarios are 11 s, cut here into one 2 s + 3 s window each like AV1's.
FULL_SETS = {"Argoverse 1 (train + val + test)": 205_942 + 39_472 + 78_143,
             "Argoverse 2 motion forecasting (train + val + test; at AV1 rates)": 199_908 + 24_988 + 24_984}
TRAIN_SETS = {"Argoverse 1 train": 205_942, "Argoverse 2 train": 199_908}
CLUSTER_CORES = 16 * 32  # the CPU-cluster column: 16 nodes of 32 cores (an assumption, stated in the table)
GPU_SUSTAINED_TFLOPS = 20.0  # the GPU column: sustained fp16/bf16 rate assumed for a mid-range training GPU


def make_replica(source: Path, folder: Path, count: int) -> int:
    """``count`` AV1 CSVs copied from ``source`` with distinct AV track ids; returns the number written."""
    originals = [(p.stem, p.read_bytes()) for p in sorted(source.glob("*.csv"))]
    folder.mkdir(parents=True, exist_ok=True)
    for i in range(count):
        stem, blob = originals[i % len(originals)]
        (folder / f"{i:06d}_{stem}.csv").write_bytes(blob.replace(AV_ID, f"{i:08d}".encode() + AV_ID[8:]))
    return count


def timed(action: Callable[[], Any]) -> tuple[float, Any]:
    """Seconds of wall time of ``action()`` and its result."""
    start = time.perf_counter()
    result = action()
    return time.perf_counter() - start, result


def flops_per_sample(checkpoint: Path, dataset: Path, count: int = 8) -> dict[str, float]:
    """FLOPs per sample of the network's inference at K = 6 (``predict``) and an estimate of one training step's
    (forward at the training K = 20 times 3: backward costs about twice the forward), counted by torch."""
    from torch.utils.flop_counter import FlopCounterMode

    from logpipe.dataset.reader import Dataset
    from logpipe.model.zhu2020.predictor import NetPredictor
    from logpipe.raster.runs import find_raster_run
    from logpipe.stages.train import scene_samples

    ds = Dataset.open(dataset)
    samples = scene_samples(ds, "hash/train", limit=count, rasters=find_raster_run(ds.root, None, None))
    net = NetPredictor.from_checkpoint(checkpoint, expect_kind=ds.kind)
    out: dict[str, float] = {}
    for name, modes, factor in (("predict", 6, 1), ("train", 20, 3)):
        counter = FlopCounterMode(display=False)
        with counter, torch.no_grad():
            net.predict(samples, modes, seed=0)
        out[name] = factor * counter.get_total_flops() / len(samples)
    return out


def _hours(seconds: float) -> str:
    """A duration in the unit that reads best."""
    if seconds < 60:
        return f"{seconds:.0f} s"
    return f"{seconds / 3600:,.1f} h" if seconds >= 360 else f"{seconds / 60:,.1f} min"


def render(m: dict[str, Any], seconds: float) -> str:
    """``docs/results/argoverse_cost.md`` from the measurements ``m``."""
    n = m["sequences"]
    per = {  # seconds per 1,000 units, (1 worker/thread, 2 workers/threads)
        "ingest (per 1,000 sequences)": (m["ingest_w1_s"] / n * 1000, m["ingest_w2_s"] / n * 1000),
        "rasterise (per 1,000 samples)": (m["rasterise_w1_s"] / n * 1000, m["rasterise_w2_s"] / n * 1000),
        "predict, full model, K = 6 (per 1,000 samples)": (m["predict_full_t1_s"] / m["predict_samples"] * 1000,
                                                           m["predict_full_t2_s"] / m["predict_samples"] * 1000),
        "predict, constant velocity (per 1,000 samples)": (m["predict_cv_t1_s"] / m["predict_samples"] * 1000,
                                                           m["predict_cv_t2_s"] / m["predict_samples"] * 1000),
    }
    step_s = 8 / m["train_samples_per_s"]
    lines = ["# Argoverse at full scale: measured stage costs and projections", "",
             f"Produced by `python -m scripts.replica_cost` in {seconds / 60:.1f} min: every stage timed on a replica "
             f"of {n:,} AV1 sequences (the 69 real ones copied with distinct AV track ids) on this machine "
             f"({m['cpu_count']} cores; load average {m['load_before'][0]:.1f} before, {m['load_after'][0]:.1f} "
             "after: the machine is shared, so these are upper bounds on a quiet core's cost). One sample per "
             "sequence (the first 2 s + 3 s window), every fully observed vehicle but the AV a target. The "
             "replica repeats 69 places, so rasterise's map queries may hit warmer caches than on the full sets; "
             "ingest and constant velocity at 2 workers pay process start-up, which 2,000 files do not amortise.",
             "",
             "## Measured", "", "| stage | 1 worker / thread | 2 workers / threads | scaling |", "|---|---|---|---|"]
    for name, (one, two) in per.items():
        lines.append(f"| {name} | {one:,.1f} s | {two:,.1f} s | {one / two:.2f}x |")
    lines += [f"| train, full model, batch 8, 1 torch thread (per 1,000 steps) | {step_s * 1000:,.0f} s | — | — |",
              "", f"FLOPs per sample (counted by torch on the shipped model): inference at K = 6 "
              f"{m['flops']['predict'] / 1e9:.2f} GFLOP; a training step's share {m['flops']['train'] / 1e9:.2f} "
              "GFLOP (forward at K = 20, times 3 for the backward).", "",
              "## Projected for the full sets", "",
              "Core-hours use the 1-worker rates (work, not wall time). *This machine*: the 2-worker rates. "
              f"*CPU cluster*: {CLUSTER_CORES} cores (16 nodes x 32, Ray for ingest / rasterise / predict, torchrun "
              "DDP for training) at the 1-worker rate per core, i.e. perfect scaling: a lower bound (and 512 ranks "
              "of batch 8 train with an effective batch of 4,096, a different schedule). *Per GPU*: not measurable "
              f"here (no GPU); FLOPs / {GPU_SUSTAINED_TFLOPS:.0f} TFLOP/s sustained (an assumed rate for a "
              "mid-range GPU under autocast), network stages only: a lower bound, since the model's small "
              "LSTM steps are latency-bound on a GPU and its inputs (windows, rasters) come from CPUs at the "
              "rates above; ingest and rasterise stay on CPUs.", "",
              "| set | stage | core-hours | this machine | CPU cluster | per GPU |", "|---|---|---|---|---|---|"]
    for name, count in FULL_SETS.items():
        for stage, (one, two) in per.items():
            short = stage.split(" (")[0]
            core = one / 1000 * count
            gpu = (f"{_hours(count * m['flops']['predict'] / (GPU_SUSTAINED_TFLOPS * 1e12))}"
                   if "full model" in stage else "—")
            lines.append(f"| {name} | {short} | {core / 3600:,.1f} | {_hours(two / 1000 * count)} | "
                         f"{_hours(core / CLUSTER_CORES)} | {gpu} |")
    for name, count in TRAIN_SETS.items():
        epoch = count / 8 * step_s
        gpu = count * m["flops"]["train"] / (GPU_SUSTAINED_TFLOPS * 1e12)
        lines.append(f"| {name} | train, one epoch ({count / 8:,.0f} steps of 8) | {epoch / 3600:,.1f} | "
                     f"{_hours(epoch / 2)} (2 DDP ranks, not measured) | {_hours(epoch / CLUSTER_CORES)} | "
                     f"{_hours(gpu)} |")
    lines += ["", "The paper's schedule is not stated in steps for Argoverse; multiply the epoch row by the epochs "
              "run. These are projections from the measured rates above, not runs on the full sets.", ""]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    """Build the replica, time every stage, write ``argoverse_cost.{json,md}``; returns the exit code."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    shared = REPO.parent / "shared" / "data" / "argoverse1"
    ap.add_argument("--source", type=Path, default=shared / "data")
    ap.add_argument("--maps", type=Path, default=shared / "maps")
    ap.add_argument("--sequences", type=int, default=2000)
    ap.add_argument("--train-steps", type=int, default=25)
    ap.add_argument("--work", type=Path, default=REPO / "out" / "replica_cost")
    ap.add_argument("--results", type=Path, default=REPO / "docs" / "results")
    ap.add_argument("--from-json", type=Path, help="re-render argoverse_cost.md from a measurements file")
    args = ap.parse_args(argv)
    if args.from_json is not None:
        stored: dict[str, Any] = json.loads(args.from_json.read_text())
        (args.results / "argoverse_cost.md").write_text(render(stored, stored.get("seconds", math.nan)))
        return 0
    started = time.perf_counter()
    shutil.rmtree(args.work, ignore_errors=True)
    csv = args.work / "csv"
    n = make_replica(args.source, csv, args.sequences)
    m: dict[str, Any] = {"sequences": n, "cpu_count": os.cpu_count(), "load_before": os.getloadavg()}
    for workers in (1, 2):
        ds = args.work / f"ds{workers}"
        m[f"ingest_w{workers}_s"], _ = timed(partial(ingest, [csv], out=ds, protocol="argoverse", mcap=False,
                                                     targets="fully_observed_no_ego", workers=workers))
        m[f"rasterise_w{workers}_s"], rs = timed(partial(rasterise, ds, maps=[args.maps], rotate=True,
                                                         workers=workers))
    m["samples"] = int(rs["samples"])
    ckpt = CHECKPOINTS / "argoverse" / "paper"
    for threads in (1, 2):
        m[f"predict_full_t{threads}_s"], ps = timed(partial(predict, ds, out=args.work / f"pred_full{threads}",
                                                            checkpoint=ckpt, mcap=False, threads=threads))
        m[f"predict_cv_t{threads}_s"], _ = timed(partial(predict, ds, out=args.work / f"pred_cv{threads}",
                                                         predictor="cv", mcap=False, threads=threads))
    m["predict_samples"] = int(ps["samples"])
    m["train_s"], ts = timed(partial(train, ds, out=args.work / "train", preset="full", steps=args.train_steps,
                                     config=REPO / "configs" / "argoverse_logs.toml", val_split="none"))
    m["train_samples_per_s"] = ts["train_samples_per_s"]
    m["flops"] = flops_per_sample(ckpt, ds)
    m["load_after"] = os.getloadavg()
    seconds = m["seconds"] = time.perf_counter() - started
    args.results.mkdir(parents=True, exist_ok=True)
    (args.results / "argoverse_cost.json").write_text(json.dumps(m, indent=1, sort_keys=True))
    (args.results / "argoverse_cost.md").write_text(render(m, seconds))
    print(f"wrote {args.results / 'argoverse_cost.md'} in {seconds:.0f} s", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
