"""``make bench`` reports every issue-35 target beside its measured value: ratios against the reference of the same
run where the target is a ratio, absolute rates otherwise."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest
from mcap.reader import make_reader
from mcap.writer import CompressionType, Writer

from benchmarks.bench_predict import TARGETS, targets
from benchmarks.mcap_floor import mcap_records, rewrite_mcap
from logpipe.mcap.merge import NewChannel, NewMessage, write_merged


def _result(env_ratio: float, plain: float, floor: float, cv_parquet: float, cv_mcap: float,
            cv_av1: float) -> dict[str, dict[str, object]]:
    return {
        "env_net_argoverse1": {"ratio_to_backbone": env_ratio, "floor_ratio_to_backbone": 0.9,
                               "cells_floor_ratio_to_backbone": 0.85, "kernels_floor_ratio_to_backbone": 0.8},
        "no_env_net_ethucy": {"samples_per_s": plain, "floor": {"bound_samples_per_s": floor},
                              "cells_share_of_matmul_floor": 0.5},
        "cv_ethucy_no_mcap": {"samples_per_s": cv_parquet, "parquet_write_alone_samples_per_s": 2 * cv_parquet,
                              "fixed_cost_plus_write_samples_per_s": 1.25 * cv_parquet},
        "cv_ethucy_all_no_mcap": {"samples_per_s": cv_parquet / 4},
        "cv_ethucy": {"samples_per_s": cv_mcap, "outputs_write_alone_samples_per_s": 4 * cv_mcap,
                      "fixed_cost_plus_write_samples_per_s": 2 * cv_mcap},
        "cv_ethucy_all": {"samples_per_s": cv_mcap / 2},
        "cv_argoverse1": {"samples_per_s": cv_av1},
    }


def test_every_target_is_reported_with_its_reference_ratio() -> None:
    rows = targets(_result(0.61, 300.0, 1000.0, 25_000.0, 4_999.0, 2_000.0))
    assert len(rows) == len(TARGETS)
    by_name = {r["target"]: r for r in rows}
    plain = by_name["network without EN, ETH/UCY K=20: share of matmul floor"]
    assert plain["measured"] == 0.3 and plain["required"] == 0.6 and not plain["met"]
    assert plain["floor"] == 0.5 and plain["share_of_floor"] == 0.6  # the recurrent cells' share, in one unit
    full = by_name["full model with EN, AV1: share of backbone-alone rate"]
    assert full["met"] and full["floor"] == 0.8 and full["share_of_floor"] == round(0.61 / 0.8, 3)
    assert by_name["constant velocity, ETH/UCY, Parquet only: samples/s"]["met"]
    assert not by_name["constant velocity, ETH/UCY, Parquet + MCAP: samples/s"]["met"]
    assert by_name["constant velocity, AV1 with rasters in the MCAP: samples/s"]["met"]  # the bound itself counts
    parquet = by_name["constant velocity, ETH/UCY, Parquet only: samples/s"]
    assert parquet["floor"] == 50_000.0 and parquet["share_of_floor"] == 0.5
    assert "floor" not in by_name["constant velocity, all of ETH/UCY, Parquet only: samples/s"]  # not measured
    assert by_name["constant velocity, ETH/UCY, Parquet + MCAP: samples/s"]["share_of_floor"] == 0.25
    # The short split's rows also stand against that floor plus the run's fixed cost; the others have none.
    assert parquet["bound_with_fixed_cost"] == 31_250.0 and parquet["share_of_bound"] == 0.8
    assert by_name["constant velocity, ETH/UCY, Parquet + MCAP: samples/s"]["share_of_bound"] == 0.5
    assert [r["target"] for r in rows if "bound_with_fixed_cost" in r] == [
        "constant velocity, ETH/UCY, Parquet only: samples/s", "constant velocity, ETH/UCY, Parquet + MCAP: samples/s"]


def test_the_output_floor_rewrites_the_same_mcap_content(tmp_path: Path) -> None:
    """The MCAP floor writes what the stage wrote: the same channels, messages (bytes, times, sequence numbers)
    and metadata, read back in file order and written again."""
    channels = [NewChannel("/a", "A", "jsonschema", b"{}", metadata={"frame_id": "world"}),
                NewChannel("/b", "B", "jsonschema", b'{"type":"object"}')]
    messages = [NewMessage(i % 2, 1_000 + i, 1_000 + i, f'{{"i":{i}}}'.encode()) for i in range(50)]
    original = tmp_path / "original.mcap"
    write_merged(original, [], channels, messages, metadata={"run": {"k": "v"}})
    records = mcap_records(original)
    assert len(records) == 1 + 2 + 2 + 50 + 1  # header, schemas, channels, messages, metadata
    again = tmp_path / "again.mcap"
    with again.open("wb") as fh:
        rewrite_mcap(Writer(fh, compression=CompressionType.ZSTD), records)

    def content(path: Path) -> tuple[list[tuple[Any, ...]], list[tuple[str, dict[str, str]]]]:
        with path.open("rb") as fh:
            reader = make_reader(fh)
            messages = [(c.topic, c.metadata, s.name if s else None, m.log_time, m.sequence, m.data)
                        for s, c, m in reader.iter_messages(log_time_order=False)]
            metadata = [(m.name, m.metadata) for m in reader.iter_metadata()]
        return messages, metadata

    assert content(again) == content(original)
    assert len(content(again)[0]) == 50


def test_paths_not_measured_are_left_out() -> None:
    partial = _result(0.5, 1.0, 1.0, 1.0, 1.0, 1.0)
    del partial["env_net_argoverse1"]
    assert [r["target"] for r in targets(partial)] == [t[0] for t in TARGETS[1:]]


def test_the_markdown_report_lists_every_target_with_its_floor() -> None:
    from benchmarks.run import render_targets

    rows = targets(_result(0.34, 300.0, 1000.0, 25_000.0, 3_000.0, 81.0))
    text = render_targets({"started": "2026-12-05T23:00:00Z", "python": "3.11.7", "machine": "x86_64",
                           "targets": rows}, "--out out/bench.json")
    table = [line for line in text.splitlines() if line.startswith("| ") and "---" not in line][1:]
    assert len(table) == len(rows)
    full = next(line for line in table if line.startswith("| full model"))
    assert full == "| full model with EN, AV1: share of backbone-alone rate | 0.34 | 0.6 | no | 0.8 | 0.42 | — | — |"
    assert ("| constant velocity, all of ETH/UCY, Parquet only: samples/s | 6,250.0 | 20,000 | no | — | — | — | — |"
            in table)
    assert ("| constant velocity, ETH/UCY, Parquet + MCAP: samples/s | 3,000.0 | 5,000 | no | 12,000.0 | 0.25 "
            "| 6,000.0 | 0.50 |") in table


def test_the_recurrent_cells_floor_does_no_more_matmul_work_than_the_network() -> None:
    """The cells floor is a bound: for the same batches, the GEMM work torch counts in it is at most the network's
    matmul work as the matmul floor counts it (full AV1 model and the ETH/UCY network without EN)."""
    import torch
    from torch.utils.flop_counter import FlopCounterMode

    from benchmarks.bench_predict import _macs_per_sample, _recurrent_cells_rate
    from logpipe.model.zhu2020.config import ModelConfig

    batches = [[(4, 3), (1, 1), (6, 2)], [(2, 2)]]
    for cfg, modes in ((ModelConfig(obs_len=20, pred_len=30, raster_channels=3), 6),
                       (ModelConfig().resolved(has_ego=False, has_map=False), 20)):
        threads = torch.get_num_threads()
        with FlopCounterMode(display=False) as counter:
            rate = _recurrent_cells_rate(cfg, batches, modes, repeats=1)  # a warm-up pass and three timed
        torch.set_num_threads(threads)
        cells_macs = counter.get_total_flops() / 2 / 4 / 4  # per pass, per sample
        network_macs = _macs_per_sample(cfg, batches, modes)["matmul_macs"]
        assert rate > 0
        assert 0.5 * network_macs < cells_macs <= network_macs


def test_the_empty_run_predicts_nothing_of_a_split_that_has_samples(bundled: Path, tmp_path: Path) -> None:
    """The fixed cost beside the small-split rows is a run of the same split that predicts nothing."""
    from benchmarks.bench_predict import _empty_run_seconds
    from logpipe.dataset.sample_filter import parse_filter
    from logpipe.stages.ingest import IngestOptions, ingest
    from logpipe.stages.predict import predict_dataset

    ingest([bundled / "ethucy"], IngestOptions(out=tmp_path / "d", workers=1, write_mcap=False))
    split = ["split=eth/test"]
    empty = parse_filter([*split, "time=:-1"])
    seconds = _empty_run_seconds(tmp_path / "d", tmp_path / "empty", 1, sample_filter=empty)
    full = predict_dataset(tmp_path / "d", tmp_path / "full", predictor="cv", write_mcap=False,
                           sample_filter=parse_filter(split))
    assert full["samples"] > 0 and seconds > 0
    with pytest.raises(AssertionError, match="selected samples"):
        _empty_run_seconds(tmp_path / "d", tmp_path / "not_empty", 1, sample_filter=parse_filter(split))


def test_the_training_floor_replays_the_steps_kernels_with_and_without_autograd() -> None:
    """bench_train's floor runs what one training step ran: the environment net's gathers and W_v products of the
    encoding and the picked mode with autograd, those of the H modes' decode without, and its replay runs them
    forward and backward (no timing here)."""
    from dataclasses import replace

    from benchmarks.bench_train import _batches, _floor_step, _record
    from logpipe.model.synthetic import make_scenes
    from logpipe.model.zhu2020.config import ModelConfig

    cfg = ModelConfig(obs_len=4, pred_len=3, raster_channels=3, backbone_bf16=False)
    scenes = make_scenes(8, seed=1, min_agents=3, max_agents=5, obs_len=4, pred_len=3, with_ego=True,
                         with_raster=True, channels=3, size=64)
    calls = _record(cfg, _batches(cfg, scenes))
    assert len(calls.shapes) == 1 and calls.rasters[0] is not None
    grads = {grad for *_, grad in calls.bags}
    assert grads == {True, False}  # the encoder and picked mode with autograd, the H modes without
    assert calls.products and all(grad for *_, grad in calls.products)  # W_v once per batch, trained
    _floor_step(cfg, calls)()
    plain = replace(cfg, features=replace(cfg.features, environment=False, ego_trajectory=False))
    no_env = _record(plain, _batches(plain, scenes))
    assert not no_env.bags and not no_env.products
    _floor_step(plain, no_env)()
