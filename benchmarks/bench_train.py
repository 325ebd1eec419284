"""Training throughput against the floor of the model's own heavy kernels, in the same run (issue 55 item 3).

Rows: one training step (forward, eq. 23's best-of-H loss with select-then-backprop, backward, Adam step) of batch
8 on synthetic scenes shaped like the data: the ETH/UCY network without the environment net (PF + TF, 8 + 12
steps, 8-30 agents) and the driving model with it (all features, 20 + 30 steps, 5-15 agents with ego, 7 x 224 x
224 rasters, backbone trained). Floor: forward + backward of the heavy kernels that step runs, each as torch's own
op alone, replaying the same rows batch by batch: ``nn.LSTMCell`` for LSTM_E and LSTM_D (the H modes without
autograd, then the picked mode with it, as ``model.zhu2020.step_loss`` decodes), ``nn.GRUCell`` for the AIN GRU, and for
the driving model the backbone on the batch's rasters and the environment net's gathers (``F.embedding_bag``) and
W_v projection recorded from the step itself. Nothing else: embeddings, pooling, attention, the loss, the
optimizer, collation. Model and floor alternate in each round (medians of rounds, wall time), on the threads torch
uses; ``share_of_floor`` = model / floor.

Settings measured beside (same run, same scenes): one torch thread against two, and for the driving model the
backbone in bf16 autocast (channels-last) against fp32 where the CPU has native bf16 (``native_bf16``, detected at
run time; elsewhere the model runs fp32 whatever the config says and the row says so).

Run: ``.venv/bin/python -m benchmarks.bench_train [--quick]`` (prints JSON).
"""

from __future__ import annotations

import contextlib
import json
import os
import statistics
import sys
import time
from dataclasses import dataclass, field, replace
from typing import Any
from unittest import mock

import numpy as np
import torch
from torch.nn import functional as F  # noqa: N812

from logpipe.model.synthetic import make_scenes
from logpipe.model.zhu2020.backbone import native_bf16
from logpipe.model.zhu2020.batching import Batch, collate
from logpipe.model.zhu2020.config import ModelConfig
from logpipe.model.zhu2020.environment import EnvironmentNet
from logpipe.model.zhu2020.network import TrajectoryNet
from logpipe.model.zhu2020.step_loss import best_of_h_step_loss
from logpipe.types import SceneSample

MODES_H = 20
BATCH = 8


@dataclass
class StepCalls:
    """What one training step ran, for the floor to replay: per batch its (agents, decoded rows, scenes) and
    raster, and the environment kernels' calls with whether autograd was on."""

    shapes: list[tuple[int, int, int]] = field(default_factory=list)
    rasters: list[torch.Tensor | None] = field(default_factory=list)
    bags: list[tuple[torch.Tensor, tuple[int, ...], torch.Tensor | None, bool]] = field(default_factory=list)
    products: list[tuple[int, int, int, bool]] = field(default_factory=list)


def _batches(cfg: ModelConfig, scenes: list[SceneSample]) -> list[Batch]:
    return [collate(scenes[lo : lo + BATCH], cfg) for lo in range(0, len(scenes) - BATCH + 1, BATCH)]


def _model_step(cfg: ModelConfig) -> Any:
    """A function running one training step on a batch (the net and optimizer made once)."""
    torch.manual_seed(0)
    net = TrajectoryNet(cfg, load_backbone=False).train()
    opt = torch.optim.Adam(net.parameters(), lr=5e-4)

    def step(batch: Batch, seed: int) -> None:
        loss = best_of_h_step_loss(net, batch, MODES_H, torch.Generator().manual_seed(seed), "scene", True)
        opt.zero_grad()
        loss.backward()  # type: ignore[no-untyped-call]
        opt.step()

    return step


def _record(cfg: ModelConfig, batches: list[Batch]) -> StepCalls:
    """One training step per batch with the environment kernels spied on."""
    calls = StepCalls()
    step = _model_step(cfg)
    bag, project = F.embedding_bag, EnvironmentNet.project

    def bag_spy(indices: Any, weight: Any, *args: Any, **kw: Any) -> Any:
        per_sample = kw.get("per_sample_weights")
        calls.bags.append((indices, tuple(weight.shape), None if per_sample is None else per_sample.detach(),
                           torch.is_grad_enabled()))
        return bag(indices, weight, *args, **kw)

    def project_spy(env: Any, fmap: Any) -> Any:
        b, c, h, w = fmap.shape
        calls.products.append((b * h * w, c, env.embed.weight.numel() // c, torch.is_grad_enabled()))
        return project(env, fmap)

    with contextlib.ExitStack() as stack:
        stack.enter_context(mock.patch.object(F, "embedding_bag", bag_spy))
        stack.enter_context(mock.patch.object(EnvironmentNet, "project", project_spy))
        for i, batch in enumerate(batches):
            step(batch, i)
            calls.shapes.append((batch.positions.shape[0], int(batch.active.sum()), batch.size))
            calls.rasters.append(batch.raster)
    return calls


def _floor_step(cfg: ModelConfig, calls: StepCalls) -> Any:
    """A function running the heavy kernels of every recorded step, forward and backward, alone."""
    torch.manual_seed(0)
    net = TrajectoryNet(cfg, load_backbone=False).train()
    hid, lstm_e, lstm_d, gru = cfg.lstm_dim, net.encoder, net.decoder, net.ain.gru
    backbone = net.env.backbone if net.env is not None and not cfg.freeze_backbone else None
    inputs = [(torch.randn(n, lstm_e.input_size, requires_grad=True), torch.randn(r, lstm_d.input_size),
               torch.randn(s, gru.input_size if gru is not None else 0)) for n, r, s in calls.shapes]
    bags = [(idx, torch.randn(shape, requires_grad=grad), per, grad) for idx, shape, per, grad in calls.bags]
    products = [(torch.randn(rows, c, requires_grad=grad), torch.randn(c, n, requires_grad=grad), grad)
                for rows, c, n, grad in calls.products]

    def recur(n: int, r: int, s: int, x_e: torch.Tensor, x_d: torch.Tensor, x_g: torch.Tensor) -> torch.Tensor:
        state = (x_e.new_zeros(n, hid), x_e.new_zeros(n, hid))
        h_g = x_g.new_zeros(s, gru.hidden_size) if gru is not None else None
        for _ in range(cfg.obs_len):  # encoding, with autograd
            state = lstm_e(x_e, state)
            h_g = gru(x_g, h_g) if gru is not None else None
        total = state[0].sum() + (h_g.sum() if h_g is not None else 0.0)
        with torch.no_grad():  # the H modes, without autograd
            dec = (state[0].repeat(MODES_H, 1)[: r * MODES_H], state[1].repeat(MODES_H, 1)[: r * MODES_H])
            x_h = x_d.repeat(MODES_H, 1)
            g_h = h_g.repeat(MODES_H, 1) if h_g is not None else None
            for _ in range(cfg.pred_len - 1):
                dec = lstm_d(x_h, dec)
                g_h = gru(x_g.repeat(MODES_H, 1), g_h) if gru is not None else None
        dec = (state[0][:r], state[1][:r])  # the picked mode, with autograd
        for _ in range(cfg.pred_len - 1):
            dec = lstm_d(x_d, dec)
            h_g = gru(x_g, h_g) if gru is not None else None
        return total + dec[0].sum() + (h_g.sum() if h_g is not None else 0.0)

    def run() -> None:
        total: torch.Tensor = torch.zeros(())
        for (n, r, s), (x_e, x_d, x_g), raster in zip(calls.shapes, inputs, calls.rasters, strict=True):
            total = total + recur(n, r, s, x_e, x_d, x_g)
            if backbone is not None and raster is not None:
                total = total + backbone(raster * 2.0 - 1.0).sum()
        for idx, weight, per, grad in bags:
            with torch.set_grad_enabled(grad):
                out = F.embedding_bag(idx, weight, per_sample_weights=per, mode="sum")
            total = total + out.sum() if grad else total
        for a, b, grad in products:
            with torch.set_grad_enabled(grad):
                out = torch.mm(a, b)
            total = total + out.sum() if grad else total
        total.backward()  # type: ignore[no-untyped-call]

    return run


def _rounds(model: Any, floor: Any, samples: int, rounds: int) -> dict[str, Any]:
    """Model and floor alternating, one warm-up each, ``rounds`` timed rounds (wall); medians and the ratio."""
    model()
    floor()
    times: dict[str, list[float]] = {"model": [], "floor": []}
    for _ in range(rounds):
        for name, fn in (("model", model), ("floor", floor)):
            t0 = time.perf_counter()
            fn()
            times[name].append(time.perf_counter() - t0)
    rate = {k: samples / statistics.median(v) for k, v in times.items()}
    return {"samples_per_s": round(rate["model"], 2), "floor_samples_per_s": round(rate["floor"], 2),
            "share_of_floor": round(rate["model"] / rate["floor"], 3),
            "rounds_ratio": [round(f / m, 3) for m, f in zip(times["model"], times["floor"], strict=True)]}


def _row(cfg: ModelConfig, scenes: list[SceneSample], rounds: int) -> dict[str, Any]:
    batches = _batches(cfg, scenes)
    calls = _record(cfg, batches)
    step = _model_step(cfg)

    def model() -> None:
        for i, batch in enumerate(batches):
            step(batch, i)

    return _rounds(model, _floor_step(cfg, calls), BATCH * len(batches), rounds)


def _scenes(quick: bool) -> tuple[list[SceneSample], list[SceneSample]]:
    n = 16 if quick else 32
    plain = make_scenes(n, seed=0, min_agents=8, max_agents=30)
    mapped = make_scenes(n // 2, seed=4, min_agents=5, max_agents=15, obs_len=20, pred_len=30, with_ego=True,
                         with_raster=True, channels=7)
    # Each sample its own raster (the synthetic stripes are the same in every scene), as on real data.
    mapped = [replace(s, raster=None if s.raster is None else np.roll(s.raster, 3 * i, axis=2))
              for i, s in enumerate(mapped)]
    return plain, mapped


def run(quick: bool = False) -> dict[str, Any]:
    """Measure and return the figures (JSON-able)."""
    from logpipe.executor import default_workers

    rounds = 3 if quick else 5
    plain_scenes, mapped_scenes = _scenes(quick)
    eth = ModelConfig().resolved(has_ego=False, has_map=False)
    driving = ModelConfig(obs_len=20, pred_len=30, raster_channels=7, backbone_bf16=True)
    bf16 = native_bf16()
    previous = torch.get_num_threads()
    result: dict[str, Any] = {"torch": torch.__version__, "cpu_capability": torch.backends.cpu.get_cpu_capability(),
                              "native_bf16": bf16, "load_avg_1m_at_start": round(os.getloadavg()[0], 2),
                              "batch": BATCH, "modes_H": MODES_H, "rounds": rounds}
    try:
        threads = default_workers()
        torch.set_num_threads(threads)
        result["threads"] = threads
        result["train_eth_no_env"] = _row(eth, plain_scenes, rounds)
        result["train_driving_env"] = _row(driving, mapped_scenes, rounds)
        result["train_driving_env"]["backbone"] = "bf16 autocast, channels-last" if bf16 else "fp32 (no native bf16)"
        if bf16:  # the same model with its backbone in fp32: what bf16 autocast buys here
            result["train_driving_env_fp32_backbone"] = _row(replace(driving, backbone_bf16=False), mapped_scenes,
                                                             rounds)
        torch.set_num_threads(1)
        result["train_eth_no_env_1_thread"] = _row(eth, plain_scenes, rounds)
    finally:
        torch.set_num_threads(previous)
    result["load_avg_1m_at_end"] = round(os.getloadavg()[0], 2)
    result["targets"] = [
        {"target": name, "measured": result[key]["share_of_floor"], "required": 0.5,
         "met": result[key]["share_of_floor"] >= 0.5, "floor": 1.0, "share_of_floor": result[key]["share_of_floor"]}
        for name, key in (("training, ETH/UCY without EN (batch 8): share of its kernels' floor", "train_eth_no_env"),
                          ("training, driving model with EN (batch 8): share of its kernels' floor",
                           "train_driving_env"))
    ]
    return result


if __name__ == "__main__":
    print(json.dumps(run(quick="--quick" in sys.argv), indent=2))
