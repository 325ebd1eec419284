"""Throughput of ``logpipe predict`` end to end (read shards → model → write Parquet + MCAP), on real data.

Measures, in one run (the machine is shared: compare figures of the same run only):

* **with the environment net** on Argoverse 1 (../shared/data, rasterised with its maps): an untrained
  ``TrajectoryNet`` with every feature on (weights do not change speed), K = 6; against the ResNet18
  stages 1-2 backbone alone on the same rasters (the target: end to end >= 0.6 of it);
* **without the environment net** on ETH/UCY scenes (PF + TF, K = 20), against its matmul floor (every matmul at
  the rate of one large GEMM; the target: >= 0.6 of it), and the constant-velocity baseline (IO-bound: the cost of
  the outputs themselves);
* for both networks, the floor of their recurrences on this machine: torch's own LSTM and GRU cells stepping the
  same rows, nothing else; for the full model also its environment kernels alone (the ROIAlign gathers and the W_v
  projection, replaying the run's own calls), so its floor is every heavy kernel it runs, each at torch's speed;
* for each, the share of the time spent in the model and in output/shard IO (``model_seconds`` /
  ``io_seconds`` of the stage summary; the rest is cutting samples and attaching rasters);
* for the constant-velocity rows, the floor of their output: writing the same Parquet tables (and MCAP records,
  already serialized, the originals' chunks copied as the stage copies them) alone with the stage's libraries and
  settings; for the short split, also the run's fixed cost and, with MCAP, reading the original logs it copies.

Run: ``.venv/bin/python -m benchmarks.bench_predict [--quick] [--mcap-rows]`` (prints JSON; ``--mcap-rows``: the
constant-velocity rows only).
"""

from __future__ import annotations

import contextlib
import json
import os
import statistics
import sys
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, cast
from unittest import mock

import numpy as np

from benchmarks.mcap_floor import PredictionFloor, mcap_records, rewrite_as_stage

REPO = Path(__file__).resolve().parents[1]
SHARED = REPO.parent / "shared" / "data"


def _predict(dataset: Path, out: Path, repeats: int, **kwargs: Any) -> dict[str, Any]:
    """Median over ``repeats`` fresh runs of samples/s and the model / IO shares."""
    from logpipe.stages.predict import predict_dataset

    runs = []
    for i in range(repeats):
        started = time.perf_counter()
        s = predict_dataset(dataset, out / f"run{i}", **kwargs)
        wall = time.perf_counter() - started
        runs.append((s["samples"] / wall, s["model_seconds"] / wall, s["io_seconds"] / wall, s))
    rate, model, io, s = sorted(runs, key=lambda r: r[0])[len(runs) // 2]
    wait = s.get("io_wait_seconds", 0.0) / (s["samples"] / rate)
    # IO runs on a writer thread beside the model: io_share is its busy time (it overlaps the model), and
    # io_blocking_share the time the pipeline waited for it (shard read + waiting for the writer).
    blocking = (s["io_seconds"] - s.get("io_busy_seconds", 0.0)) / (s["samples"] / rate) + wait
    return {"samples": s["samples"], "rows": s["rows"], "samples_per_s": round(rate, 1),
            "model_share": round(model, 3), "io_share": round(io, 3), "io_blocking_share": round(blocking, 3),
            "other_share": round(max(0.0, 1 - model - blocking), 3)}


Counts = list[list[tuple[int, int]]]
"""Per forecast batch, per sample: (agents, decoded agents), as the stage batched them."""


@dataclass
class EnvCalls:
    """The environment net's heavy kernel calls of a predict run: each ROIAlign gather's ``F.embedding_bag``
    arguments (indices, projected maps, weights) and each W_v projection's product shape (rows, C, K*K*d_v)."""

    bags: list[tuple[Any, Any, Any]] = field(default_factory=list)
    products: list[tuple[int, int, int]] = field(default_factory=list)


def _sample_counts(dataset: Path, checkpoint: Path, env_calls: EnvCalls | None = None, **kwargs: Any) -> Counts:
    """The agents and decoded agents of every sample the stage forecasts, batch by batch (one process, so every
    batch is forecast here, where the spy sees it); with ``env_calls``, the same run's environment-net kernel calls
    are recorded into it."""
    from torch.nn import functional as F  # noqa: N812

    from logpipe.model.zhu2020.environment import EnvironmentNet
    from logpipe.prediction import sample_shards
    from logpipe.stages.predict import predict_dataset

    batches: Counts = []
    original = sample_shards.run_batch
    embedding_bag, project = F.embedding_bag, EnvironmentNet.project

    def spy(run: Any, batch: Any, *args: Any) -> None:
        batches.append([(len(s.positions), int(np.isfinite(s.positions[:, s.obs_len - 1]).all(axis=1).sum()))
                        for _, _, s in batch])
        original(run, batch, *args)

    def bag_spy(indices: Any, weight: Any, *args: Any, **kw: Any) -> Any:
        assert env_calls is not None
        env_calls.bags.append((indices, weight, kw.get("per_sample_weights")))
        return embedding_bag(indices, weight, *args, **kw)

    def project_spy(env: Any, fmap: Any) -> Any:
        assert env_calls is not None
        b, c, h, w = fmap.shape
        env_calls.products.append((b * h * w, c, env.embed.weight.numel() // c))
        return project(env, fmap)

    with contextlib.ExitStack() as stack:
        tmp = Path(stack.enter_context(tempfile.TemporaryDirectory()))
        stack.enter_context(mock.patch.object(sample_shards, "run_batch", spy))
        if env_calls is not None:
            stack.enter_context(mock.patch.object(F, "embedding_bag", bag_spy))
            stack.enter_context(mock.patch.object(EnvironmentNet, "project", project_spy))
        predict_dataset(dataset, tmp / "out", checkpoint=checkpoint, write_mcap=False, workers=1, **kwargs)
    return batches


def _median_seconds(action: Callable[[], Any], repeats: int) -> float:
    """Median wall seconds of ``action()`` over ``max(repeats, 3)`` timed calls after one warm-up call."""
    action()
    times = []
    for _ in range(max(repeats, 3)):
        t0 = time.perf_counter()
        action()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def _macs_per_sample(cfg: Any, batches: Counts, modes: int) -> dict[str, float]:
    """Multiply-accumulates per sample of the network's matmuls (encoder + decoder, not the backbone) and the
    environment-lookup gathers, from the samples' real agent counts and the checkpoint's config."""
    f, d, hid, g = cfg.features, cfg.embed_dim, cfg.lstm_dim, cfg.gru_dim
    d_fst = d * (int(f.ego_trajectory) + int(f.uses_gru))
    env = d if f.environment else 0
    gru_in = d * (int(f.position) + int(f.tracking) + int(f.ego_motion))
    gru = (gru_in + g) * 3 * g + g * d if f.uses_gru else 0  # eqs. 6-7 per scene and step
    n = np.array([c[0] for b in batches for c in b], float)
    r = np.array([c[1] for b in batches for c in b], float)
    steps = cfg.pred_len - 1
    enc = n * cfg.obs_len * ((d + env + d_fst + hid) * 4 * hid) + cfg.obs_len * gru
    dec_rows = r * modes * steps
    dec = (dec_rows * ((2 + env + d_fst + hid + 1) * 4 * hid + (hid * d if f.tracking else 0) + hid * 2)
           + modes * steps * gru + r * modes * (hid + cfg.noise_dim) * hid)
    bag = (n * cfg.obs_len + dec_rows) * cfg.roi_pool**2 * cfg.roi_sampling**2 * 4 * d if f.environment else 0 * n
    return {"matmul_macs": float((enc + dec).mean()), "gather_macs": float(np.mean(bag)),
            "lstm_width": float(2 + env + d_fst + hid + 1), "gates": float(4 * hid)}


def _recurrent_cells_rate(cfg: Any, batches: Counts, modes: int, repeats: int) -> float:
    """Samples/s of torch's own recurrent cells alone (``nn.LSTMCell``, ``nn.GRUCell``: on CPU two GEMMs and one
    fused gate kernel a step) stepping exactly the rows that the network's LSTM_E, LSTM_D and AIN GRU step for these
    samples, batch by batch as the stage forecast them, on the threads torch uses.

    Nothing else of the network runs (embeddings, pooling, attention, environment lookups, the output layer, cutting,
    IO), and these cells do no more matmul work than the network's own: no network built on these library kernels can
    forecast faster on this machine. The floor of the recurrences, where the matmul floor assumes every matmul at the
    rate of one large GEMM.
    """
    import torch
    from torch import nn

    from logpipe.model.zhu2020.network import TrajectoryNet

    torch.manual_seed(0)
    net = TrajectoryNet(cfg, load_backbone=False)
    hid, lstm_e, gru = cfg.lstm_dim, net.encoder, net.ain.gru
    # LSTM_D as the inference decoder steps it: eq. 17's W_p folded in, so its input starts with the 2-D displacement
    lstm_d = nn.LSTMCell(net.decoder.input_size - net.disp_embed.out_features + 2, hid)
    # (agents, decoded rows, scenes) per batch; inputs made once, outside the timing
    shapes = [(sum(c[0] for c in b), sum(c[1] for c in b) * modes, len(b)) for b in batches]
    inputs = [(torch.randn(n, lstm_e.input_size), torch.randn(r, lstm_d.input_size),
               torch.randn(s * modes, gru.input_size if gru is not None else 0)) for n, r, s in shapes]

    def step_all() -> None:
        for (n, r, s), (x_e, x_d, x_g) in zip(shapes, inputs, strict=True):
            state_e = (x_e.new_zeros(n, hid), x_e.new_zeros(n, hid))
            state_d = (x_d.new_zeros(r, hid), x_d.new_zeros(r, hid))
            h_g = x_g.new_zeros(s, gru.hidden_size) if gru is not None else None
            for _ in range(cfg.obs_len):
                state_e = lstm_e(x_e, state_e)
                if gru is not None:
                    h_g = gru(x_g[:s], h_g)
            h_g = h_g.repeat_interleave(modes, dim=0) if h_g is not None else None
            for _ in range(cfg.pred_len - 1):
                state_d = lstm_d(x_d, state_d)
                if gru is not None:
                    h_g = gru(x_g, h_g)

    with torch.inference_mode():
        return sum(len(b) for b in batches) / _median_seconds(step_all, repeats)


def _environment_ops_rates(calls: EnvCalls, samples: int, repeats: int) -> dict[str, float]:
    """Samples/s of the environment net's two torch kernels alone, replaying exactly the ``calls`` a predict run of
    ``samples`` made (``_sample_counts``): its ROIAlign gathers (``F.embedding_bag`` with the same indices, weights
    and projected maps) and its W_v projection (one ``(B*h*w, C) x (C, K*K*d_v)`` product per batch, same shapes).
    Nothing else runs: not the index and weight arithmetic around the gathers, nor the map's transpose."""
    import torch
    from torch.nn import functional as F  # noqa: N812

    products = [(torch.randn(rows, c), torch.randn(c, n)) for rows, c, n in calls.products]

    def gathers() -> None:
        for indices, weight, per_sample in calls.bags:
            F.embedding_bag(indices, weight, per_sample_weights=per_sample, mode="sum")

    def projections() -> None:
        for a, b in products:
            torch.mm(a, b)

    with torch.inference_mode():
        return {"gathers": samples / _median_seconds(gathers, repeats),
                "projection": samples / _median_seconds(projections, repeats)}


def _matmul_rate(k: int, n: int, repeats: int) -> float:
    """MAC/s of fp32 matmuls of the decoder's LSTM-step shape (2048-row blocks), on the threads torch uses."""
    import torch

    a, b = torch.randn(2048, k), torch.randn(k, n)
    torch.mm(a, b)
    rates = []
    for _ in range(max(repeats, 3)):
        t0 = time.perf_counter()
        for _ in range(20):
            torch.mm(a, b)
        rates.append(20 * 2048 * k * n / (time.perf_counter() - t0))
    return statistics.median(rates)


def _bound(macs: dict[str, float], repeats: int, backbone: float | None = None) -> dict[str, Any]:
    """Upper bound on samples/s if the network's matmuls ran at the measured fp32 rate with nothing else (no
    elementwise ops, gathers, IO), plus one backbone pass per sample when the environment net is on."""
    rate = _matmul_rate(int(macs["lstm_width"]), int(macs["gates"]), repeats)
    per_sample = macs["matmul_macs"] / rate + (1.0 / backbone if backbone else 0.0)
    return {"matmul_macs_per_sample": round(macs["matmul_macs"] / 1e6, 1), "gather_macs_per_sample":
            round(macs["gather_macs"] / 1e6, 1), "measured_fp32_gmac_per_s": round(rate / 1e9, 1),
            "bound_samples_per_s": round(1.0 / per_sample, 1)}


def _backbone_rate(dataset: Path, spec: Any, repeats: int) -> float:
    """Images/s of the backbone alone (same config, batch 32) on the dataset's rasters."""
    import torch

    from logpipe.model.zhu2020.config import ModelConfig
    from logpipe.model.zhu2020.network import TrajectoryNet
    from logpipe.raster.runs import RasterShards

    shards = RasterShards.open(dataset, spec, "ego")
    ids = shards.index.column("sample_id").to_pylist()
    images = np.stack([shards.get(i)[0] for i in ids]).astype(np.float32) / 255.0
    net = TrajectoryNet(ModelConfig(obs_len=20, pred_len=30, raster_channels=len(spec.channels))).eval()
    assert net.env is not None
    batch = torch.from_numpy(images[:32])
    rates = []
    with torch.inference_mode():
        net.env.feature_map(batch)
        for _ in range(repeats):
            t0 = time.perf_counter()
            for lo in range(0, len(images), 32):
                net.env.feature_map(torch.from_numpy(images[lo : lo + 32]))
            rates.append(len(images) / (time.perf_counter() - t0))
    return statistics.median(rates)


def run(quick: bool = False) -> dict[str, Any]:
    """Every figure as a dict (``benchmarks/run.py`` collects it)."""
    import torch

    from logpipe.dataset.sample_filter import parse_filter
    from logpipe.executor import default_workers
    from logpipe.maps import MapSource
    from logpipe.model.zhu2020.checkpoint import save_checkpoint
    from logpipe.model.zhu2020.config import ModelConfig, TrainConfig
    from logpipe.model.zhu2020.meta import read_meta
    from logpipe.model.zhu2020.network import TrajectoryNet
    from logpipe.raster.rasteriser import RasterSpec
    from logpipe.stages.ingest import IngestOptions, ingest
    from logpipe.stages.rasterise import rasterise_dataset

    if not SHARED.is_dir():
        return {"skipped": f"{SHARED} absent"}
    torch.set_num_threads(default_workers())
    repeats = 1 if quick else 3
    result: dict[str, Any] = {"cores": default_workers(), "load_avg_1m": round(os.getloadavg()[0], 2),
                              "repeats": repeats}
    with tempfile.TemporaryDirectory() as tmp_name:
        tmp = Path(tmp_name)
        # --- with the environment net: Argoverse 1, rasters from its maps.
        av1 = tmp / "av1"
        ingest([SHARED / "argoverse1" / "data"], IngestOptions(out=av1))
        spec = RasterSpec(rotate=True)
        rasterise_dataset(av1, MapSource(roots=(SHARED / "argoverse1" / "maps",)), rotate=True, spec=spec)
        cfg = ModelConfig(obs_len=20, pred_len=30, raster_channels=len(spec.channels))
        env_ckpt = save_checkpoint(tmp / "env_ckpt", TrajectoryNet(cfg), TrainConfig(model=cfg),
                                   dataset_kind="argoverse1", manifest_hash="bench", step=0)
        backbone = _backbone_rate(av1, spec, repeats)
        env = _predict(av1, tmp / "env_out", repeats, checkpoint=env_ckpt, batch_size=32)
        env["backbone_alone_samples_per_s"] = round(backbone, 1)
        env["ratio_to_backbone"] = round(env["samples_per_s"] / backbone, 3)
        env_calls = EnvCalls()
        env_batches = _sample_counts(av1, env_ckpt, env_calls, batch_size=32)
        env_cfg = read_meta(env_ckpt).config.model
        env["floor"] = _bound(_macs_per_sample(env_cfg, env_batches, 6), repeats, backbone)
        # The target's own unit: the compute floor (backbone + matmuls at peak, nothing else) over the backbone.
        env["floor_ratio_to_backbone"] = round(env["floor"]["bound_samples_per_s"] / backbone, 3)
        cells = _recurrent_cells_rate(env_cfg, env_batches, 6, repeats)
        env["recurrent_cells_alone_samples_per_s"] = round(cells, 1)
        # The same with the recurrences at the rate torch's own cells reach (backbone + cells, nothing else).
        env["cells_floor_ratio_to_backbone"] = round(1.0 / (1.0 / backbone + 1.0 / cells) / backbone, 3)
        # Add the environment net's own kernels (its gathers and W_v projection, replayed alone): the floor of
        # every heavy kernel this network runs, each at torch's speed, none of the glue between them.
        ops = _environment_ops_rates(env_calls, sum(len(b) for b in env_batches), repeats)
        del env_calls  # the recorded projected maps (~58 MB a batch)
        env["env_gathers_alone_samples_per_s"] = round(ops["gathers"], 1)
        env["env_projection_alone_samples_per_s"] = round(ops["projection"], 1)
        per_sample = 1.0 / backbone + 1.0 / cells + 1.0 / ops["gathers"] + 1.0 / ops["projection"]
        env["kernels_floor_ratio_to_backbone"] = round(1.0 / per_sample / backbone, 3)
        result["env_net_argoverse1"] = env
        result["cv_argoverse1"] = _cv_row(av1, tmp / "cv_av1", repeats)
        # --- without the environment net: ETH/UCY (PF + TF, the paper's setting there), K = 20.
        eth = tmp / "eth"
        ingest([SHARED / "ethucy"], IngestOptions(out=eth))
        plain = ModelConfig().resolved(has_ego=False, has_map=False)
        plain_ckpt = save_checkpoint(tmp / "plain_ckpt", TrajectoryNet(plain), TrainConfig(model=plain),
                                     dataset_kind="ethucy", manifest_hash="bench", step=0)
        split = ["split=eth/test"] if quick else ["split=hotel/test"]
        chosen = parse_filter(split)
        result["no_env_net_ethucy"] = _predict(eth, tmp / "plain_out", repeats, checkpoint=plain_ckpt,
                                               sample_filter=chosen, batch_size=128)
        plain_batches = _sample_counts(eth, plain_ckpt, sample_filter=chosen, batch_size=128)
        no_env = result["no_env_net_ethucy"]
        plain_cfg = read_meta(plain_ckpt).config.model
        no_env["floor"] = _bound(_macs_per_sample(plain_cfg, plain_batches, 20), repeats)
        cells = _recurrent_cells_rate(plain_cfg, plain_batches, 20, repeats)
        no_env["recurrent_cells_alone_samples_per_s"] = round(cells, 1)
        no_env["cells_share_of_matmul_floor"] = round(cells / no_env["floor"]["bound_samples_per_s"], 3)
        result.update(_cv_ethucy_rows(eth, tmp, split, repeats))
    result["targets"] = targets(result)
    return result


def _cv_ethucy_rows(eth: Path, tmp: Path, split: list[str], repeats: int) -> dict[str, dict[str, Any]]:
    """Constant velocity on the ETH/UCY ``split`` and on all of ETH/UCY, with and without MCAP, each beside the
    floor of writing its outputs alone; on the split, also the run's fixed cost."""
    from logpipe.dataset.sample_filter import parse_filter

    chosen = parse_filter(split)
    rows = {"cv_ethucy": _cv_row(eth, tmp / "cv_eth", repeats, sample_filter=chosen),
            "cv_ethucy_no_mcap": _cv_row(eth, tmp / "cv_eth_nomcap", repeats, sample_filter=chosen, write_mcap=False)}
    # The stage's fixed cost on this split: the same run with a filter that selects none of its samples.
    empty = parse_filter([*split, "time=:-1"])
    fixed = _empty_run_seconds(eth, tmp / "cv_eth_empty", repeats, sample_filter=empty)
    rows["cv_ethucy_no_mcap"]["empty_run_seconds"] = fixed
    # A bound for a run of this size: that fixed cost plus writing its outputs alone (the stage's own cost
    # plus the libraries' floor; not a floor of the machine). With MCAP, the write includes the originals'
    # records, and the bound reading them too (the empty run opens no log's MCAP).
    rows["cv_ethucy"]["originals_read_seconds"] = _originals_read_seconds(eth, tmp / "cv_eth" / "run0", repeats)
    for row, floor in ((rows["cv_ethucy_no_mcap"], "parquet_write_alone_samples_per_s"),
                       (rows["cv_ethucy"], "outputs_write_alone_samples_per_s")):
        before = fixed + row.get("originals_read_seconds", 0.0)
        row["fixed_cost_plus_write_samples_per_s"] = round(row["samples"] / (before + row["samples"] / row[floor]), 1)
    # Every ETH/UCY sample (~7,600, ~10 targets each): a throughput the fixed costs of a run do not hide.
    rows["cv_ethucy_all_no_mcap"] = _cv_row(eth, tmp / "cv_eth_all", repeats, write_mcap=False)
    rows["cv_ethucy_all"] = _cv_row(eth, tmp / "cv_eth_all_mcap", repeats)
    return rows


def _cv_row(dataset: Path, out: Path, repeats: int, write_mcap: bool = True, **kwargs: Any) -> dict[str, Any]:
    """Constant velocity's figures (``_predict``) beside the floor of writing its outputs alone: with MCAP,
    ``outputs_write_alone_samples_per_s``; Parquet only, ``parquet_write_alone_samples_per_s``."""
    row = _predict(dataset, out, repeats, predictor="cv", write_mcap=write_mcap, **kwargs)
    floor = _outputs_write_rate(out / "run0", row["samples"], repeats, mcap=write_mcap, dataset=dataset)
    row["outputs_write_alone_samples_per_s" if write_mcap else "parquet_write_alone_samples_per_s"] = floor
    return row


def _empty_run_seconds(dataset: Path, out: Path, repeats: int, **kwargs: Any) -> float:
    """Median seconds of constant velocity to Parquet with ``kwargs`` selecting no sample: the run's fixed cost
    (opening the dataset, reading its tables and the selected logs' tracks, committing the run)."""
    from logpipe.stages.predict import predict_dataset

    times = []
    for i in range(max(repeats, 3)):
        started = time.perf_counter()
        summary = predict_dataset(dataset, out / f"run{i}", predictor="cv", write_mcap=False, **kwargs)
        times.append(time.perf_counter() - started)
        assert summary["samples"] == 0, "the empty run's filter selected samples"
    return round(statistics.median(times), 4)


def _originals_read_seconds(dataset: Path, run: Path, repeats: int) -> float:
    """Median seconds of reading the original MCAPs (the ones ingest wrote) of the logs a predict ``run`` wrote MCAPs
    for as the stage reads them to copy them (``chunk_copy.read_chunked``: records, chunks left compressed, the
    data section's CRC checked): what copying the originals into those MCAPs cannot skip."""
    from logpipe.dataset.reader import Dataset
    from logpipe.mcap.chunk_copy import read_chunked

    ds = Dataset.open(dataset)
    originals = [ds.mcap_path(path.stem) for path in sorted((run / "mcap").rglob("*.mcap"))]

    def read_all() -> None:
        for path in originals:
            read_chunked(path, path.name)

    return round(_median_seconds(read_all, repeats), 4)


def _outputs_write_rate(run: Path, samples: int, repeats: int, mcap: bool = True,
                        dataset: Path | None = None) -> float:
    """Samples/s of writing the run's outputs alone, nothing encoded: its predictions tables (pyarrow, the stage's
    codec) and, with ``mcap``, every log MCAP's records, already serialized, through the writer the stage picks for
    them with its settings (read back from its files): an original of ``dataset`` that the stage copies by chunk
    (every ingest MCAP) is copied by chunk, already read, plus the appended messages (``PredictionFloor``), any other
    MCAP rewritten record by record (``rewrite_as_stage``).
    The floor of a predict path that writes them with these libraries; the forecasting, the message encoding and
    the durability work (fsync, hashes) are not in it."""
    import pyarrow.parquet as pq

    from logpipe.dataset.reader import Dataset
    from logpipe.mcap.merge import NATIVE_COMPRESSION_THREADS

    files = sorted((run / "predictions").glob("*.parquet"))
    tables = [pq.read_table(f) for f in files]
    codec = pq.ParquetFile(files[0]).metadata.row_group(0).column(0).compression.lower()
    logs: list[Any] = []
    ds = Dataset.open(dataset) if mcap and dataset is not None else None
    for path in sorted((run / "mcap").rglob("*.mcap")) if ds is not None else []:
        original = cast(Dataset, ds).mcap_path(path.stem)
        try:  # the stage copies an ingest MCAP by chunk: its floor is that copy plus the appended messages
            logs.append(PredictionFloor(path, original))
        except ValueError:
            logs.append(mcap_records(path))
    rates = []
    with tempfile.TemporaryDirectory() as tmp:
        for _ in range(max(repeats, 3)):
            t0 = time.perf_counter()
            for i, table in enumerate(tables):
                pq.write_table(table, Path(tmp) / f"{i}.parquet", compression=codec)
            for i, log in enumerate(logs):
                if isinstance(log, PredictionFloor):
                    log.write(Path(tmp) / f"{i}.mcap")
                else:
                    rewrite_as_stage(Path(tmp) / f"{i}.mcap", log, NATIVE_COMPRESSION_THREADS)
            rates.append(samples / (time.perf_counter() - t0))
    return round(statistics.median(rates), 1)


TARGETS = (  # issue 35: (name, result path, measured key, reference, target, floor of this machine or None)
    ("full model with EN, AV1: share of backbone-alone rate", "env_net_argoverse1", "ratio_to_backbone", None, 0.6,
     "kernels_floor_ratio_to_backbone"),
    ("network without EN, ETH/UCY K=20: share of matmul floor", "no_env_net_ethucy", "samples_per_s",
     "floor.bound_samples_per_s", 0.6, "cells_share_of_matmul_floor"),
    ("constant velocity, ETH/UCY, Parquet only: samples/s", "cv_ethucy_no_mcap", "samples_per_s", None, 20_000,
     "parquet_write_alone_samples_per_s"),
    ("constant velocity, all of ETH/UCY, Parquet only: samples/s", "cv_ethucy_all_no_mcap", "samples_per_s", None,
     20_000, "parquet_write_alone_samples_per_s"),
    ("constant velocity, ETH/UCY, Parquet + MCAP: samples/s", "cv_ethucy", "samples_per_s", None, 5_000,
     "outputs_write_alone_samples_per_s"),
    ("constant velocity, all of ETH/UCY, Parquet + MCAP: samples/s", "cv_ethucy_all", "samples_per_s", None, 5_000,
     "outputs_write_alone_samples_per_s"),
    ("constant velocity, AV1 with rasters in the MCAP: samples/s", "cv_argoverse1", "samples_per_s", None, 2_000,
     "outputs_write_alone_samples_per_s"),
)


def targets(result: dict[str, Any]) -> list[dict[str, Any]]:
    """Each issue-35 target beside what this run measured (a ratio where the target is one) and whether it is met;
    where the run measured a floor (writing the same table alone), the measured figure's share of it too, and for
    a short run, its share of that floor plus the run's fixed cost."""
    rows = []
    for name, path, key, reference, target, floor in TARGETS:
        if path not in result:
            continue
        measured = float(result[path][key])
        if reference is not None:
            ref: Any = result[path]
            for part in reference.split("."):
                ref = ref[part]
            measured /= float(ref)
        row = {"target": name, "measured": round(measured, 3), "required": target, "met": measured >= target}
        if floor is not None and floor in result[path]:
            row["floor"] = result[path][floor]
            row["share_of_floor"] = round(measured / float(result[path][floor]), 3)
        bound = result[path].get("fixed_cost_plus_write_samples_per_s")
        if bound is not None and reference is None:  # a short run: its fixed cost counts against it too
            row["bound_with_fixed_cost"] = bound
            row["share_of_bound"] = round(measured / float(bound), 3)
        rows.append(row)
    return rows


def run_mcap_rows(quick: bool = False) -> dict[str, Any]:
    """Only the constant-velocity rows (the MCAP writer's: AV1 with rasters, ETH/UCY with and without MCAP), as
    ``run`` measures them: ``python -m benchmarks.bench_predict --mcap-rows``."""
    from logpipe.maps import MapSource
    from logpipe.raster.rasteriser import RasterSpec
    from logpipe.stages.ingest import IngestOptions, ingest
    from logpipe.stages.rasterise import rasterise_dataset

    repeats = 1 if quick else 3
    result: dict[str, Any] = {"load_avg_1m": round(os.getloadavg()[0], 2), "repeats": repeats}
    with tempfile.TemporaryDirectory() as tmp_name:
        tmp = Path(tmp_name)
        av1, eth = tmp / "av1", tmp / "eth"
        ingest([SHARED / "argoverse1" / "data"], IngestOptions(out=av1))
        rasterise_dataset(av1, MapSource(roots=(SHARED / "argoverse1" / "maps",)), rotate=True,
                          spec=RasterSpec(rotate=True))
        result["cv_argoverse1"] = _cv_row(av1, tmp / "cv_av1", repeats)
        ingest([SHARED / "ethucy"], IngestOptions(out=eth))
        result.update(_cv_ethucy_rows(eth, tmp, ["split=eth/test"] if quick else ["split=hotel/test"], repeats))
    result["targets"] = targets(result)
    return result


if __name__ == "__main__":
    print(json.dumps((run_mcap_rows if "--mcap-rows" in sys.argv else run)(quick="--quick" in sys.argv), indent=2))
