"""``--device auto|cpu|cuda``: resolving the option, moving batches, and CPU results that do not depend on how the
CPU was asked for. Only the CPU path runs on a machine without a GPU; the CUDA test skips there with a reason."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest
import torch
from typer.testing import CliRunner

from logpipe.cli import app
from logpipe.model.synthetic import make_scenes
from logpipe.model.training.device import DeviceError, autocast, autocast_dtype, grad_scaler, resolve_device
from logpipe.model.zhu2020.batching import collate
from logpipe.model.zhu2020.config import Features, ModelConfig, TrainConfig
from logpipe.model.zhu2020.fit import fit
from logpipe.model.zhu2020.predictor import NetPredictor
from logpipe.types import SceneSample

runner = CliRunner()
NO_GPU = not torch.cuda.is_available()

MODEL = ModelConfig(features=Features(True, True, True, True, True), embed_dim=8, gru_dim=8, lstm_dim=8, noise_dim=2,
                    obs_len=4, pred_len=3, raster_channels=2, step_output="agent_velocity_change", mode_gate=True,
                    constant_velocity_modes=1)


def _scenes(n: int, seed: int) -> list[SceneSample]:
    """Scenes with an ego and a 2-channel raster, so every part of the network (AIN, EMF/ETF, environment net) runs."""
    scenes: list[SceneSample] = make_scenes(n, seed=seed, min_agents=2, max_agents=4, obs_len=4, pred_len=3,
                                            with_ego=True, with_raster=True, channels=2, size=32, extent_m=40.0)
    return scenes


def _without_gpu(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)


def test_resolve_device_choices_and_errors(monkeypatch: pytest.MonkeyPatch) -> None:
    assert resolve_device("cpu") == torch.device("cpu")
    assert resolve_device(torch.device("cpu")) == torch.device("cpu")
    with pytest.raises(DeviceError, match=r"--device must be one of auto, cpu, cuda, got 'gpu'"):
        resolve_device("gpu")
    _without_gpu(monkeypatch)
    assert resolve_device("auto") == torch.device("cpu")
    # what torch reports: this venv's CPU-only build, or a CUDA build that sees no GPU
    reason = "CPU-only build" if torch.version.cuda is None else "usable GPUs"
    with pytest.raises(DeviceError, match=rf"--device cuda: torch cannot use a GPU here \(torch .*{reason}\)"):
        resolve_device("cuda")
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    assert resolve_device("auto") == torch.device("cuda")
    assert resolve_device("cuda") == torch.device("cuda")


def test_precision_is_fp32_on_cpu_and_autocast_only_on_cuda(monkeypatch: pytest.MonkeyPatch) -> None:
    cpu = torch.device("cpu")
    assert autocast_dtype(cpu) is None and grad_scaler(cpu) is None
    with autocast(cpu):
        assert not torch.is_autocast_enabled("cpu")  # the CPU path keeps fp32 arithmetic
    cuda = torch.device("cuda")
    monkeypatch.setattr(torch.cuda, "is_bf16_supported", lambda *a, **k: True)
    assert autocast_dtype(cuda) == torch.bfloat16 and grad_scaler(cuda) is None  # bf16 needs no loss scaling
    monkeypatch.setattr(torch.cuda, "is_bf16_supported", lambda *a, **k: False)
    assert autocast_dtype(cuda) == torch.float16


def test_batch_to_moves_every_tensor_field() -> None:
    batch = collate(_scenes(3, 0), MODEL)
    tensors = {f.name for f in dataclasses.fields(batch) if isinstance(getattr(batch, f.name), torch.Tensor)}
    assert {"positions", "valid", "scene", "raster", "frame_to_px", "px_per_m"} <= tensors
    moved = batch.to("meta")  # a device without data: proves where every field went, no GPU needed
    for f in dataclasses.fields(batch):
        before, after = getattr(batch, f.name), getattr(moved, f.name)
        if f.name in tensors:
            assert after.device.type == "meta", f.name
            assert (after.shape, after.dtype) == (before.shape, before.dtype), f.name
            assert before.device.type == "cpu", f.name  # the original batch is not changed
        else:  # host-side bookkeeping (frames, offsets, sample rows) stays as it is
            assert after is before, f.name
    same = batch.to("cpu")
    assert all(getattr(same, name) is getattr(batch, name) for name in tensors)  # no copies on the CPU


def test_cpu_fit_and_predict_do_not_depend_on_how_the_cpu_is_asked_for(tmp_path: Path,
                                                                       monkeypatch: pytest.MonkeyPatch) -> None:
    _without_gpu(monkeypatch)
    train, val = _scenes(8, 1), _scenes(4, 2)
    cfg = TrainConfig(model=MODEL, steps=4, batch_size=4, num_modes=3, val_modes=3, eval_every=2, log_every=1,
                      num_threads=1, augment_rotate=True, loss_min_over="agent", ema_decay=0.9)
    runs = {name: fit(train, val, cfg, tmp_path / name, progress=False, **kw)
            for name, kw in (("default", {}), ("cpu", {"device": "cpu"}), ("auto", {"device": "auto"}))}
    logs = {name: [{k: v for k, v in json.loads(line).items() if k != "time" and not k.endswith("_s")}
                   for line in run.log_path.read_text().splitlines()] for name, run in runs.items()}
    assert {run.device for run in runs.values()} == {"cpu"}
    assert logs["default"][0]["event"] == "start" and logs["default"][0]["device"] == "cpu"
    assert runs["cpu"].weights_sha256 == runs["default"].weights_sha256 == runs["auto"].weights_sha256
    assert logs["cpu"] == logs["default"] == logs["auto"]  # same losses and validation ADE/FDE, bit for bit
    checkpoint = runs["default"].last_checkpoint
    plain = NetPredictor.from_checkpoint(checkpoint).predict(val, 3, seed=4)
    auto = NetPredictor.from_checkpoint(checkpoint, device="auto")
    assert auto.device == torch.device("cpu") and auto.with_noise_scale(1.0).device == auto.device
    for a, b in zip(plain, auto.predict(val, 3, seed=4), strict=True):
        assert np.array_equal(a, b, equal_nan=True)


def test_cli_train_and_predict_take_device_and_report_it(bundled: Path, tmp_path: Path,
                                                         monkeypatch: pytest.MonkeyPatch) -> None:
    _without_gpu(monkeypatch)
    data = tmp_path / "e"
    assert runner.invoke(app, ["ingest", str(bundled / "ethucy"), "--out", str(data), "--no-mcap"]).exit_code == 0
    config = tmp_path / "c.toml"
    config.write_text("[train]\nsteps = 2\neval_every = 2\nval_max_samples = 8\nnum_threads = 1\n"
                      "[model]\nembed_dim = 8\ngru_dim = 8\nlstm_dim = 8\n")
    base = ["train", str(data), "--train-split", "eth/train", "--val-split", "hotel/test", "--config", str(config),
            "--json"]
    summaries = {}
    for name, extra in (("auto", []), ("cpu", ["--device", "cpu"])):
        result = runner.invoke(app, [*base, "--out", str(tmp_path / name), *extra])
        assert result.exit_code == 0, result.output
        summaries[name] = json.loads(result.stdout)
    assert summaries["auto"]["device"] == summaries["cpu"]["device"] == "cpu"
    sha = {name: json.loads((Path(s["last_checkpoint"]) / "meta.json").read_text())["weights_sha256"]
           for name, s in summaries.items()}
    assert sha["auto"] == sha["cpu"]
    for bad, message in (("gpu", "--device must be one of auto, cpu, cuda"), ("cuda", "--device cuda: torch cannot")):
        result = runner.invoke(app, [*base, "--out", str(tmp_path / f"bad_{bad}"), "--device", bad])
        assert result.exit_code == 2 and message in result.output, result.output
        assert not (tmp_path / f"bad_{bad}").exists()  # refused before a run folder is made

    checkpoint = summaries["cpu"]["last_checkpoint"]
    tables = []
    for name, extra in (("pred_auto", []), ("pred_cpu", ["--device", "cpu"])):
        result = runner.invoke(app, ["predict", str(data), "--checkpoint", checkpoint, "--filter", "split=eth/test",
                                     "--modes", "3", "--no-mcap", "--out", str(tmp_path / name), "--json", *extra])
        assert result.exit_code == 0, result.output
        assert json.loads(result.stdout)["device"] == "cpu"
        tables.append(pq.read_table(tmp_path / name / "predictions" / "part-00000.parquet"))
    assert tables[0].num_rows > 0 and tables[0].equals(tables[1])
    cv = runner.invoke(app, ["predict", str(data), "--predictor", "cv", "--filter", "split=eth/test", "--no-mcap",
                             "--out", str(tmp_path / "cv"), "--device", "cuda", "--json"])
    assert cv.exit_code == 0, cv.output  # a baseline runs in numpy: no GPU needed, none reported
    assert json.loads(cv.stdout)["device"] is None
    typo = runner.invoke(app, ["predict", str(data), "--predictor", "cv", "--no-mcap", "--out", str(tmp_path / "x"),
                               "--device", "gpu"])
    assert typo.exit_code == 2 and "--device must be one of" in typo.output


@pytest.mark.skipif(NO_GPU, reason="no CUDA device here: only the CPU path can be tested on this machine")
def test_cuda_fit_and_predict_run_under_autocast_and_match_the_cpu(tmp_path: Path) -> None:
    train, val = _scenes(8, 1), _scenes(4, 2)
    cfg = TrainConfig(model=MODEL, steps=4, batch_size=4, num_modes=3, val_modes=3, eval_every=2, log_every=1,
                      num_threads=1, loss_min_over="agent", ema_decay=0.9)
    run = fit(train, val, cfg, tmp_path / "cuda", progress=False, device="cuda")
    assert run.device == "cuda" and np.isfinite(run.best_val_ade)
    on_cpu = NetPredictor.from_checkpoint(run.last_checkpoint).predict(val, 3, seed=4)
    on_gpu = NetPredictor.from_checkpoint(run.last_checkpoint, device="cuda").predict(val, 3, seed=4)
    for a, b in zip(on_cpu, on_gpu, strict=True):
        # same noise z (drawn on the CPU), arithmetic in bf16/fp16: metres agree to rounding
        assert np.array_equal(np.isnan(a), np.isnan(b))
        assert np.allclose(a, b, atol=0.25, equal_nan=True)
