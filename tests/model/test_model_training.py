"""Training loop: overfitting, determinism, resume, checkpoints and configs."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch
from safetensors.torch import load_file

from logpipe.errors import LogpipeError
from logpipe.model.checkpoint.format import CheckpointError, CheckpointMismatchError
from logpipe.model.synthetic import make_scenes
from logpipe.model.zhu2020.checkpoint import load_checkpoint
from logpipe.model.zhu2020.config import ConfigError, Features, ModelConfig, TrainConfig, load_config, save_config
from logpipe.model.zhu2020.fit import fit
from logpipe.model.zhu2020.predictor import NetPredictor
from logpipe.model.zhu2020.train_inputs import TrainingError

MODEL = ModelConfig(
    features=Features(True, True, False, False, False),
    embed_dim=16,
    gru_dim=16,
    lstm_dim=16,
    noise_dim=2,
    obs_len=4,
    pred_len=3,
)


def _data(n: int, seed: int) -> list:  # type: ignore[type-arg]
    return make_scenes(n, seed=seed, min_agents=2, max_agents=4, obs_len=4, pred_len=3)


def _cfg(**kw: object) -> TrainConfig:
    base = {
        "model": MODEL,
        "steps": 20,
        "batch_size": 4,
        "num_modes": 3,
        "val_modes": 3,
        "eval_every": 10,
        "log_every": 5,
        "num_threads": 1,
    }
    base.update(kw)
    return TrainConfig(**base)  # type: ignore[arg-type]


def test_overfits_a_few_samples(tmp_path: Path) -> None:
    data = _data(4, 0)
    cfg = _cfg(
        steps=300,
        lr=5e-3,
        batch_size=4,
        num_modes=1,
        val_modes=1,
        eval_every=100,
        log_every=50,
        model=replace(MODEL, noise_dim=0),
    )
    res = fit(data, data, cfg, tmp_path, progress=False)
    lines = [json.loads(x) for x in res.log_path.read_text().splitlines()]
    losses = [x["loss"] for x in lines if x["event"] == "train"]
    assert losses[-1] < 0.01 * losses[0] and losses[-1] < 0.01  # metres^2 per target step
    assert res.best_val_ade < 0.1
    assert res.best_checkpoint is not None


def test_same_seed_same_weights_and_resume_continues_exactly(tmp_path: Path) -> None:
    train, val = _data(12, 1), _data(4, 2)
    a = fit(train, val, _cfg(steps=20), tmp_path / "a", progress=False)
    b = fit(train, val, _cfg(steps=20), tmp_path / "b", progress=False)
    wa, wb = (
        load_file(str(a.last_checkpoint / "weights.safetensors")),
        load_file(str(b.last_checkpoint / "weights.safetensors")),
    )
    assert all(torch.equal(wa[k], wb[k]) for k in wa)
    c = fit(train, val, _cfg(steps=20, seed=5), tmp_path / "c", progress=False)
    wc = load_file(str(c.last_checkpoint / "weights.safetensors"))
    assert not all(torch.equal(wa[k], wc[k]) for k in wa)
    # 20 + 20 resumed steps == 40 uninterrupted steps
    full = fit(train, val, _cfg(steps=40), tmp_path / "full", progress=False)
    with pytest.raises(TrainingError):
        fit(train, val, _cfg(steps=40), tmp_path / "a", progress=False)
    resumed = fit(train, val, _cfg(steps=40), tmp_path / "a", resume=True, progress=False)
    assert resumed.steps == 40
    # the run's clock spans both parts: the first part's wall time comes back from the training state
    assert a.resumed_at_step is None and a.total_elapsed_s == a.elapsed_s
    assert resumed.resumed_at_step == 20
    state = json.loads((a.last_checkpoint / "train_state.json").read_text())
    assert state["elapsed_s"] == pytest.approx(resumed.total_elapsed_s, abs=0.5)
    assert resumed.total_elapsed_s >= resumed.elapsed_s + 0.9 * a.elapsed_s
    wf, wr = (
        load_file(str(full.last_checkpoint / "weights.safetensors")),
        load_file(str(resumed.last_checkpoint / "weights.safetensors")),
    )
    for k in wf:
        torch.testing.assert_close(wr[k], wf[k], rtol=0, atol=0)
    with pytest.raises(CheckpointMismatchError):
        fit(train, val, _cfg(steps=60, model=replace(MODEL, lstm_dim=8)), tmp_path / "a", resume=True, progress=False)


def test_checkpoint_round_trip_and_mismatch_errors(tmp_path: Path) -> None:
    train, val = _data(8, 3), _data(4, 4)
    res = fit(train, val, _cfg(steps=10), tmp_path, progress=False, dataset_kind="ethucy", manifest_hash="h1")
    assert res.best_checkpoint is not None
    meta = json.loads((res.best_checkpoint / "meta.json").read_text())
    assert meta["dataset_kind"] == "ethucy" and meta["manifest_hash"] == "h1"
    assert meta["logpipe_version"] and meta["normalisation"]["frame"] == "world"
    loaded = load_checkpoint(res.best_checkpoint, expect_kind="ethucy", expect_config=res.config.model)
    assert loaded.meta.config == res.config
    # the loaded net predicts exactly what evaluation saw
    pa = NetPredictor(loaded.net).predict(val, 3, seed=0)
    pb = NetPredictor.from_checkpoint(res.best_checkpoint, expect_kind="ethucy").predict(val, 3, seed=0)
    for x, y in zip(pa, pb, strict=True):
        np.testing.assert_array_equal(x, y)
    with pytest.raises(CheckpointMismatchError, match="dataset kind"):
        load_checkpoint(res.best_checkpoint, expect_kind="argoverse")
    with pytest.raises(CheckpointMismatchError, match="lstm_dim"):
        load_checkpoint(res.best_checkpoint, expect_config=replace(res.config.model, lstm_dim=32))
    with pytest.raises(CheckpointMismatchError, match="manifest"):
        load_checkpoint(res.best_checkpoint, expect_manifest_hash="other")
    assert issubclass(CheckpointMismatchError, LogpipeError)
    weights = res.best_checkpoint / "weights.safetensors"
    weights.write_bytes(weights.read_bytes()[:-8] + b"\0" * 8)
    with pytest.raises(CheckpointError, match="sha256"):
        load_checkpoint(res.best_checkpoint)
    with pytest.raises(CheckpointError):
        load_checkpoint(tmp_path / "nowhere")


def test_config_files_round_trip_and_reject_typos(tmp_path: Path) -> None:
    cfg = _cfg(val_max_samples=None, model=replace(MODEL, backbone_weights="r18.safetensors", frame="ego"))
    for name in ("c.json", "c.toml"):
        save_config(cfg, tmp_path / name)
        assert load_config(tmp_path / name) == cfg
    (tmp_path / "bad.toml").write_text("[train]\nstepz = 3\n")
    with pytest.raises(ConfigError, match="stepz"):
        load_config(tmp_path / "bad.toml")
    (tmp_path / "bad2.json").write_text('{"model": {"features": {"environmnet": false}}}')
    with pytest.raises(ConfigError, match="environmnet"):
        load_config(tmp_path / "bad2.json")
    (tmp_path / "p.toml").write_text(
        "[model]\npred_len = 30\nobs_len = 20\n[model.features]\nenvironment = false\n[train]\nsteps = 7\n"
    )
    loaded = load_config(tmp_path / "p.toml")
    assert loaded.steps == 7 and loaded.model.pred_len == 30 and not loaded.model.features.environment
    with pytest.raises(ConfigError):
        ModelConfig(frame="polar")  # type: ignore[arg-type]


def test_fit_resolves_features_and_checks_lengths(tmp_path: Path) -> None:
    res = fit(
        _data(4, 5), None, _cfg(steps=2, model=replace(MODEL, features=Features())), tmp_path / "r", progress=False
    )
    # no ego and no raster in the data: EMF, ETF and EF are switched off (the paper's ETH/UCY setting)
    assert res.config.model.features == Features(True, True, False, False, False)
    assert res.best_checkpoint is None and (res.last_checkpoint / "meta.json").exists()
    # ego and rasters present: everything stays on and C comes from the rasters
    mapped = make_scenes(
        4,
        seed=7,
        min_agents=2,
        max_agents=4,
        obs_len=4,
        pred_len=3,
        with_ego=True,
        with_raster=True,
        channels=3,
        size=64,
    )
    res2 = fit(mapped, mapped, _cfg(steps=2, model=replace(MODEL, features=Features())), tmp_path / "m", progress=False)
    assert res2.config.model.features == Features() and res2.config.model.raster_channels == 3
    assert np.isfinite(res2.best_val_ade)
    with pytest.raises(ConfigError, match="obs_len"):
        fit(_data(4, 5), None, _cfg(model=replace(MODEL, obs_len=8)), tmp_path / "s", progress=False)


def test_fit_streams_an_iterable(tmp_path: Path) -> None:
    data = _data(10, 6)
    res = fit(iter(data), iter(data[:3]), _cfg(steps=50, shuffle_buffer=4, eval_every=1), tmp_path, progress=False)
    assert res.steps == 2  # a one-shot stream of 10 scenes gives 2 full batches of 4
    vals = [json.loads(x) for x in res.log_path.read_text().splitlines() if '"val"' in x]
    assert len(vals) == 2 and all(v["targets"] > 0 for v in vals)  # a one-shot val stream is kept


@pytest.mark.parametrize("reduce", ["scene", "agent"])
def test_select_then_backprop_gives_the_eq_23_gradient(reduce: str) -> None:
    from logpipe.model.zhu2020.batching import collate
    from logpipe.model.zhu2020.network import TrajectoryNet
    from logpipe.model.zhu2020.step_loss import best_of_h_step_loss

    cfg = replace(MODEL, features=Features(True, True, False, False, False))
    torch.manual_seed(0)
    net = TrajectoryNet(cfg)
    batch = collate(make_scenes(3, seed=9, min_agents=2, max_agents=5, obs_len=4, pred_len=3), cfg)
    grads = []
    for select in (False, True):
        net.zero_grad()
        loss = best_of_h_step_loss(net, batch, 6, torch.Generator().manual_seed(1), reduce, select)
        loss.backward()
        grads.append((loss.detach(), [p.grad.clone() for p in net.parameters() if p.grad is not None]))
    torch.testing.assert_close(grads[0][0], grads[1][0])
    assert len(grads[0][1]) == len(grads[1][1]) > 0
    for a, b in zip(grads[0][1], grads[1][1], strict=True):
        torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-6)


def test_early_stop_waits_for_min_steps(tmp_path: Path) -> None:
    # lr far below float32 resolution: the weights never change, so no validation after the first is better
    train, val = _data(8, 11), _data(3, 12)
    kw = {"steps": 20, "lr": 1e-30, "eval_every": 1, "early_stop_patience": 2}
    eager = fit(train, val, _cfg(**kw), tmp_path / "eager", progress=False)
    assert eager.stopped_early and eager.steps == 3 and eager.best_step == 1
    patient = fit(train, val, _cfg(early_stop_min_steps=7, **kw), tmp_path / "patient", progress=False)
    assert patient.stopped_early and patient.steps == 7 and patient.best_step == 1
    with pytest.raises(ConfigError, match="early_stop_min_steps"):
        _cfg(early_stop_min_steps=-1)


def test_warm_start_from_noise_lstm_starts_at_its_predictions(tmp_path: Path) -> None:
    from logpipe.model.zhu2020.batching import collate
    from logpipe.model.zhu2020.checkpoint import warm_start
    from logpipe.model.zhu2020.config import ALL_OFF
    from logpipe.model.zhu2020.network import TrajectoryNet

    train, val = _data(8, 21), _data(3, 22)
    noise_lstm = fit(train, val, _cfg(model=replace(MODEL, features=ALL_OFF)), tmp_path / "nl", progress=False)
    source = load_checkpoint(noise_lstm.last_checkpoint).net
    net = TrajectoryNet(MODEL)
    done = warm_start(net, noise_lstm.last_checkpoint)
    assert set(done.widened) == {"encoder.weight_ih", "decoder.weight_ih"}
    assert done.kept and all(k.startswith(("ain.", "attention.")) for k in done.kept)
    assert done.differences == ()  # the same model config but for the features
    assert warm_start(TrajectoryNet(replace(MODEL, disp_scale_m=0.5)), noise_lstm.last_checkpoint).differences == (
        f"model.disp_scale_m: expected 0.5, checkpoint has {MODEL.disp_scale_m!r}",)
    width = MODEL.embed_dim  # the displacement embedding leads the LSTM input
    assert not net.encoder.weight_ih[:, width:].any() and net.encoder.weight_ih[:, width:].numel() > 0
    batch = collate(val, MODEL)
    noise = torch.randn(4, int(batch.active.sum()), MODEL.noise_dim, generator=torch.Generator().manual_seed(3))
    with torch.no_grad():
        mine = net.decode(batch, net.encode(batch), noise).positions
        theirs = source.decode(batch, source.encode(batch), noise).positions
    assert torch.equal(mine, theirs)

    # fit(init_from=...) starts there and logs it; weights that cannot move (lr 1e-30) stay the source's
    run = fit(train, val, _cfg(lr=1e-30, steps=2, eval_every=2), tmp_path / "ws", progress=False,
              init_from=noise_lstm.last_checkpoint)
    start = json.loads(run.log_path.read_text().splitlines()[0])
    assert start["event"] == "start" and start["init_from"]["widened"] == list(done.widened)
    after = load_file(str(run.last_checkpoint / "weights.safetensors"))
    before = load_file(str(noise_lstm.last_checkpoint / "weights.safetensors"))
    assert torch.equal(after["out.weight"], before["out.weight"])
    assert torch.equal(after["decoder.weight_ih"][:, :width], before["decoder.weight_ih"])

    with pytest.raises(CheckpointError, match="shape"):
        warm_start(TrajectoryNet(replace(MODEL, lstm_dim=8)), noise_lstm.last_checkpoint)


def test_weight_average_is_validated_kept_as_best_and_resumes(tmp_path: Path) -> None:
    train, val = _data(12, 31), _data(4, 32)
    decay = 0.9
    kw = {"steps": 4, "eval_every": 1, "early_stop_patience": 0, "ema_decay": decay}
    runs = {}
    for steps in (1, 2, 3, 4):  # the raw weights after each step, from otherwise identical runs
        runs[steps] = fit(train, val, _cfg(**{**kw, "steps": steps}), tmp_path / f"s{steps}", progress=False)
    raw = [load_file(str(runs[n].last_checkpoint / "weights.safetensors")) for n in (1, 2, 3, 4)]
    # the average by hand: the first step's weights, then avg <- decay * avg + (1 - decay) * raw
    expected = dict(raw[0])
    for weights in raw[1:]:
        expected = {k: decay * expected[k] + (1 - decay) * weights[k] for k in expected}
    kept = load_file(str(runs[4].last_checkpoint / "averaged.safetensors"))
    for k in expected:
        torch.testing.assert_close(kept[f"module.{k}"], expected[k], rtol=1e-5, atol=1e-7)
    # validation scores the average, and best/ holds the average of its step
    log = [json.loads(x) for x in runs[4].log_path.read_text().splitlines()]
    best_step = runs[4].best_step
    best = load_file(str(runs[4].best_checkpoint / "weights.safetensors"))  # type: ignore[operator]
    at_best = load_file(str(runs[best_step].last_checkpoint / "averaged.safetensors"))
    assert all(torch.equal(best[k], at_best[f"module.{k}"]) for k in best)
    averaged_net = load_checkpoint(runs[4].best_checkpoint).net  # type: ignore[arg-type]
    from logpipe.model.zhu2020.evaluation import evaluate

    err = evaluate(averaged_net, val, num_modes=3, seed=0)
    logged = next(x["val_ade"] for x in log if x["event"] == "val" and x["step"] == best_step)
    assert err.ade == pytest.approx(logged)
    assert not all(torch.equal(raw[-1][k], kept[f"module.{k}"]) for k in raw[-1])
    # a resumed run continues the average exactly
    resumed = fit(train, val, _cfg(**kw), tmp_path / "s2", resume=True, progress=False)
    again = load_file(str(resumed.last_checkpoint / "averaged.safetensors"))
    assert all(torch.equal(again[k], kept[k]) for k in kept)
    with pytest.raises(ConfigError, match="ema_decay"):
        _cfg(ema_decay=1.0)
