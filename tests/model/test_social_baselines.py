"""The social baselines (issue 63): Social-LSTM's pooling grid and Gaussian NLL, Social-GAN's max-pool over relative
positions and its variety loss, window scenes, checkpoints that round-trip and refuse damage, and the whole path
through the CLI (train a few steps on the bundled ETH/UCY sample, predict, score)."""

from __future__ import annotations

import json
import math
import shutil
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch
from typer.testing import CliRunner

from logpipe.cli import app
from logpipe.dataset.reader import Dataset
from logpipe.model.checkpoint.format import CheckpointError
from logpipe.model.checkpoint.weights_folder import WeightsMeta, save_weights_folder
from logpipe.model.social import split_samples
from logpipe.model.social_gan.config import SocialGanConfig, preset_config
from logpipe.model.social_gan.fit import variety_loss
from logpipe.model.social_gan.net import Generator, PoolingModule, max_pool_pairs
from logpipe.model.social_gan.predictor import SocialGanPredictor
from logpipe.model.social_lstm.config import SocialLstmConfig
from logpipe.model.social_lstm.net import SocialLstm, bivariate_nll, grid_cells, sample_gaussian, social_tensor
from logpipe.model.social_lstm.predictor import SocialLstmPredictor
from logpipe.model.training.social_batch import predict_scene, stack, training_scene, within_pairs
from logpipe.stages.ingest import IngestOptions, ingest
from logpipe.types import SceneSample

ETHUCY = Path(__file__).resolve().parents[1] / "data" / "ethucy"
runner = CliRunner()


def test_grid_cells_put_each_neighbour_in_its_cell_and_leave_the_far_ones_out() -> None:
    # a 2 m grid of 8 x 8 cells (0.25 m each) centred on the agent, x fastest
    relative = torch.tensor([[0.0, 0.0], [-0.99, -0.99], [0.99, -0.99], [0.3, 0.6], [-0.99, 0.99], [1.0, 0.0],
                             [0.0, -1.2], [5.0, 5.0]])
    cell, inside = grid_cells(relative, 2.0, 8)
    assert inside.tolist() == [True, True, True, True, True, False, False, False]
    assert cell[:5].tolist() == [4 * 8 + 4, 0, 7, 6 * 8 + 5, 7 * 8 + 0]


def test_the_social_tensor_sums_neighbours_hidden_states_per_cell_within_the_window() -> None:
    config = SocialLstmConfig(grid_size=2, neighbourhood_m=2.0, hidden_dim=3)
    # window 0: agent 0 at the origin, agents 1 and 2 up-right of it (same cell), agent 3 far; window 1: agent 4
    # where agent 1 is, but in another window
    positions = torch.tensor([[0.0, 0.0], [0.5, 0.5], [0.2, 0.9], [9.0, 9.0], [0.5, 0.5]])
    hidden = torch.arange(15, dtype=torch.float32).reshape(5, 3)
    pair_i, pair_j = (torch.from_numpy(a) for a in within_pairs(np.array([0, 4, 5])))
    tensor = social_tensor(hidden, positions, pair_i, pair_j, config).reshape(5, 4, 3)
    up_right = 1 * 2 + 1
    assert torch.equal(tensor[0, up_right], hidden[1] + hidden[2])  # summed, agent 3 too far, agent 4 elsewhere
    assert torch.equal(tensor[0].sum(dim=0), hidden[1] + hidden[2])
    assert torch.equal(tensor[1, 0], hidden[0])  # agent 0 is down-left of agent 1; agent 2 is up-left (cell 2)
    assert torch.equal(tensor[1, 2], hidden[2])
    assert not tensor[3].any() and not tensor[4].any()  # nobody near; its own state is never pooled


def test_the_pooling_module_max_pools_over_relative_positions_and_hidden_states() -> None:
    values = torch.tensor([[1.0, 5.0], [3.0, 2.0], [0.0, 9.0], [4.0, 4.0]])
    pooled = max_pool_pairs(values, torch.tensor([0, 0, 1, 0]), 2)
    assert torch.equal(pooled, torch.tensor([[4.0, 5.0], [0.0, 9.0]]))

    torch.manual_seed(0)
    config = replace(preset_config("social_gan_20vp"), encoder_h_dim=4, bottleneck_dim=6, pool_hidden_dim=8,
                     pool_batch_norm=False)  # the published MLP: each pair's vector its own (no batch statistics)
    pool = PoolingModule(config)
    hidden = torch.randn(5, 4)
    end = torch.tensor([[0.0, 0.0], [1.0, 0.5], [-2.0, 1.0], [3.0, 3.0], [7.0, 7.0]])
    pair_i, pair_j = (torch.from_numpy(a) for a in within_pairs(np.array([0, 3, 5])))
    out = pool(hidden, end, pair_i, pair_j)
    # by hand: agent 0's vector is the max over j of MLP([embed(p_j - p_0), h_j]) over its window (agents 0..2)
    by_hand = torch.stack([pool.mlp_pre_pool(torch.cat([pool.spatial_embedding(end[j] - end[0]), hidden[j]]))
                           for j in range(3)]).max(dim=0).values
    assert torch.allclose(out[0], by_hand)
    # the same window shifted in the world pools the same (relative positions), its agents in another order too
    order = torch.tensor([2, 0, 1])
    one_window = (torch.from_numpy(a) for a in within_pairs(np.array([0, 3])))
    moved = pool(hidden[:3][order], end[:3][order] + 100.0, *one_window)
    assert torch.allclose(moved[1], out[0], atol=1e-6)
    # a neighbour moving changes the pooled vector; agents of another window never enter it
    end_moved = end.clone()
    end_moved[1] += 0.7
    assert not torch.allclose(pool(hidden, end_moved, pair_i, pair_j)[0], out[0])
    other = hidden.clone()
    other[3:] += 10.0
    assert torch.equal(pool(other, end, pair_i, pair_j)[:3], out[:3])


def test_the_nll_is_the_bivariate_gaussians() -> None:
    torch.manual_seed(1)
    params = torch.randn(50, 5)
    target = torch.randn(50, 2)
    mean, std, rho = params[:, :2], torch.exp(params[:, 2:4]), torch.tanh(params[:, 4])
    cov = torch.stack([torch.stack([std[:, 0] ** 2, rho * std[:, 0] * std[:, 1]], dim=1),
                       torch.stack([rho * std[:, 0] * std[:, 1], std[:, 1] ** 2], dim=1)], dim=1)
    expected = -torch.distributions.MultivariateNormal(mean, covariance_matrix=cov).log_prob(target)  # type: ignore[no-untyped-call]
    assert torch.allclose(bivariate_nll(params, target), expected, atol=1e-4)
    # the mean is the most likely point, and draws have the Gaussian's moments
    assert bool((bivariate_nll(params, mean) <= bivariate_nll(params, target)).all())
    one = torch.tensor([0.5, -1.0, math.log(0.4), math.log(1.5), math.atanh(0.6)])
    draws = sample_gaussian(one.expand(200_000, 5), torch.randn(200_000, 2))
    assert torch.allclose(draws.mean(dim=0), one[:2], atol=0.01)
    got = torch.cov(draws.T)
    assert torch.allclose(got, torch.tensor([[0.16, 0.6 * 0.4 * 1.5], [0.6 * 0.4 * 1.5, 2.25]]), atol=0.02)


def test_the_variety_loss_takes_each_windows_best_sample_jointly() -> None:
    # 3 samples, window 0 = agents 0, 1 and window 1 = agents 2, 3
    errors = torch.tensor([[1.0, 9.0, 4.0, 4.0],
                           [5.0, 4.0, 1.0, 9.0],   # window 0: 9 (best jointly); agent-wise minima would mix 0 and 2
                           [8.0, 2.0, 6.0, 6.0]])
    best, chosen = variety_loss(errors, torch.tensor([0, 0, 1, 1]), 2)
    assert chosen.tolist() == [1, 0]
    assert float(best) == pytest.approx(9.0 + 8.0)


def _sample(positions: np.ndarray, targets: list[bool], sample_id: str = "log:0") -> SceneSample:
    n, t = positions.shape[:2]
    return SceneSample(sample_id, positions, np.arange(t, dtype=np.int64), [str(i) for i in range(n)],
                       np.zeros(n, np.int64), np.array(targets), -1, 8)


def test_window_scenes_keep_whole_tracks_for_training_and_current_agents_for_prediction() -> None:
    rng = np.random.default_rng(0)
    positions = rng.normal(size=(4, 20, 2))
    positions[1, 15:] = np.nan  # leaves before the end: not trained on, predicted
    positions[2, :3] = np.nan  # arrives late: history filled with its first position
    positions[3, 7] = np.nan  # not observed now: its forecast is NaN
    train = training_scene(_sample(positions, [True, True, True, True]))
    assert train is not None and train.positions.shape == (20, 1, 2)  # agent 0 alone is there throughout
    scene = predict_scene(_sample(positions, [True, False, True, True]))
    assert scene.positions.shape == (8, 3, 2) and scene.targets.tolist() == [0, 2, -1]
    assert np.array_equal(scene.positions[:3, 2], np.repeat(positions[2, 3][None], 3, axis=0))
    assert np.isfinite(scene.positions).all()


def _meta(kind: str, config: dict[str, object]) -> WeightsMeta:
    return WeightsMeta(model_kind=kind, config=config, dataset_kind="ethucy", manifest_hash="0" * 64, obs_len=8,
                       pred_len=12, step=3)


@pytest.fixture(scope="module")
def samples(tmp_path_factory: pytest.TempPathFactory) -> list[SceneSample]:
    """The bundled ETH/UCY sample ingested; its eth/test windows."""
    out = tmp_path_factory.mktemp("social") / "ds"
    ingest([ETHUCY], IngestOptions(out=out, write_mcap=False))
    windows: list[SceneSample] = split_samples([Dataset.open(out)], "eth/test")[0]
    return windows[:40]


@pytest.mark.parametrize("kind", ["social_gan", "social_lstm"])
def test_checkpoints_round_trip_and_refuse_damage(kind: str, samples: list[SceneSample], tmp_path: Path) -> None:
    torch.manual_seed(0)
    folder = tmp_path / "ckpt"
    if kind == "social_gan":
        gan_config = replace(SocialGanConfig(pooling=True), best_k=5)
        net: torch.nn.Module = Generator(gan_config)
        state = {f"generator.{k}": v for k, v in net.state_dict().items()}
        save_weights_folder(folder, state, _meta(kind, gan_config.to_dict()))
        loaded: SocialGanPredictor | SocialLstmPredictor = SocialGanPredictor.from_checkpoint(folder)
        fresh: SocialGanPredictor | SocialLstmPredictor = SocialGanPredictor(net, loaded.meta)
    else:
        lstm_config = SocialLstmConfig(hidden_dim=16, embedding_dim=8)
        net = SocialLstm(lstm_config)
        save_weights_folder(folder, dict(net.state_dict()), _meta(kind, lstm_config.to_dict()))
        loaded = SocialLstmPredictor.from_checkpoint(folder)
        fresh = SocialLstmPredictor(net, loaded.meta)
    got, want = loaded.predict(samples, 5, seed=3), fresh.predict(samples, 5, seed=3)
    assert all(np.array_equal(a, b, equal_nan=True) for a, b in zip(got, want, strict=True))
    # a forecast depends on its sample and seed only, not on its batch mates
    alone = [loaded.predict([s], 5, seed=3)[0] for s in samples[:6]]
    assert all(np.allclose(a, b, atol=1e-5, equal_nan=True) for a, b in zip(alone, got[:6], strict=True))
    assert not np.allclose(loaded.predict(samples[:1], 5, seed=4)[0], got[0], equal_nan=True)

    edited = tmp_path / "edited"
    shutil.copytree(folder, edited)
    meta = json.loads((edited / "meta.json").read_text())
    meta["config"]["pred_len"] = 11
    (edited / "meta.json").write_text(json.dumps(meta))
    with pytest.raises(CheckpointError, match="checksum"):
        type(loaded).from_checkpoint(edited)
    damaged = tmp_path / "damaged"
    shutil.copytree(folder, damaged)
    raw = bytearray((damaged / "weights.safetensors").read_bytes())
    raw[-5] ^= 0xFF
    (damaged / "weights.safetensors").write_bytes(bytes(raw))
    with pytest.raises(CheckpointError, match="sha256"):
        type(loaded).from_checkpoint(damaged)
    with pytest.raises(CheckpointError, match="not a"):
        (SocialLstmPredictor if kind == "social_gan" else SocialGanPredictor).from_checkpoint(folder)


def test_social_lstm_k1_is_the_mean_and_larger_k_samples(samples: list[SceneSample]) -> None:
    torch.manual_seed(0)
    predictor = SocialLstmPredictor(SocialLstm(SocialLstmConfig(hidden_dim=16, embedding_dim=8)), _meta("x", {}))
    mean = predictor.predict(samples[:5], 1, seed=0)
    sampled = predictor.predict(samples[:5], 4, seed=0)
    assert all(m.shape[1] == 1 and s.shape[1] == 4 for m, s in zip(mean, sampled, strict=True))
    assert all(np.array_equal(predictor.predict(samples[:5], 1, seed=9)[i], mean[i]) for i in range(5))
    spread = [float(np.nanstd(s, axis=1).mean()) for s in sampled if s.size]
    assert min(spread) > 0


def test_stacked_windows_pair_only_agents_of_the_same_window() -> None:
    tracks = [np.zeros((20, 2, 2)), np.zeros((20, 3, 2))]
    batch = stack(tracks)
    pairs = set(zip(batch.pair_i.tolist(), batch.pair_j.tolist(), strict=True))
    assert pairs == {(i, j) for i in range(2) for j in range(2)} | {(i, j) for i in range(2, 5) for j in range(2, 5)}
    assert batch.scene_of.tolist() == [0, 0, 1, 1, 1]


@pytest.fixture(scope="module")
def cli_dataset(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The bundled ETH/UCY sample ingested through the CLI (read-only for the tests)."""
    dataset = tmp_path_factory.mktemp("social_cli") / "ds"
    assert runner.invoke(app, ["-q", "ingest", str(ETHUCY), "--out", str(dataset), "--no-mcap"]).exit_code == 0
    return dataset


@pytest.mark.parametrize("preset", ["social_lstm", "social_gan_20v", "social_gan_20vp"])
def test_train_predict_and_score_through_the_cli(preset: str, cli_dataset: Path, tmp_path: Path) -> None:
    dataset = cli_dataset
    table = "social_lstm" if preset == "social_lstm" else "social_gan"
    config = tmp_path / "small.toml"
    # a few small batches; Social-LSTM with a narrower LSTM (its published 128 makes predicting K = 20 slow here)
    small = "hidden_dim = 16\nembedding_dim = 8\n" if table == "social_lstm" else ""
    config.write_text(f"[{table}]\nbatch_size = 8\nval_every = 2\nval_windows = 10\n{small}")
    run = tmp_path / "run"
    result = runner.invoke(app, ["train", str(dataset), "--train-split", "eth/train", "--val-split", "none",
                                 "--preset", preset, "--config", str(config), "--steps", "4", "--out", str(run),
                                 "--json"])
    assert result.exit_code == 0, result.output
    summary = json.loads(result.stdout)
    assert summary["steps"] == 4 and summary["best_step"] in (2, 4)
    log = [json.loads(line) for line in (run / "train_log.jsonl").read_text().splitlines()]
    assert [r["step"] for r in log] == [2, 4] and all(math.isfinite(r["val_ade"]) for r in log)
    meta = json.loads((run / "best" / "meta.json").read_text())
    assert meta["model_kind"] == table and meta["config"]["pooling" if table == "social_gan" else "grid_size"] == (
        preset != "social_gan_20v" if table == "social_gan" else 8)

    predictions = tmp_path / "pred"
    result = runner.invoke(app, ["-q", "predict", str(dataset), "--checkpoint", str(run / "best"), "--filter",
                                 "split=eth/test", "--out", str(predictions), "--no-mcap", "--json"])
    assert result.exit_code == 0, result.output
    assert json.loads(result.stdout)["predictor"] == table
    result = runner.invoke(app, ["score", str(predictions), "--truth", str(dataset), "--split", "eth/test",
                                 "--out", str(tmp_path / "score"), "--no-plots", "--json"])
    assert result.exit_code == 0, result.output
    method = json.loads(result.stdout)["methods"][table]
    assert method["counts"]["agents_missing"] == 0 and method["counts"]["agents_expected"] > 0
    k20 = method["overall"]["k20"]
    assert 0 < k20["ade"] <= k20["ade_joint"] and math.isfinite(k20["fde_joint"])

    # options of the paper's network do not apply to these runs and checkpoints; a run is not overwritten
    result = runner.invoke(app, ["-q", "train", str(dataset), "--train-split", "eth/train", "--val-split", "none",
                                 "--preset", preset, "--loader-workers", "1", "--out", str(run)])
    assert result.exit_code == 2 and "--loader-workers" in result.output
    result = runner.invoke(app, ["-q", "train", str(dataset), "--train-split", "eth/train", "--val-split", "none",
                                 "--preset", preset, "--config", str(config), "--steps", "4", "--out", str(run)])
    assert result.exit_code == 2 and "--resume" in result.output and result.output.count("\n") == 1
    result = runner.invoke(app, ["-q", "predict", str(dataset), "--checkpoint", str(run / "best"), "--noise-scale",
                                 "2", "--out", str(tmp_path / "p2")])
    assert result.exit_code == 2 and "not to a" in result.output


@pytest.mark.parametrize(("inputs", "preset", "agents", "k"), [
    (["apolloscape"], "social_gan_20vp", "all", "k20"),
    (["driving/20.csv", "driving/32.csv"], "social_lstm", "focal", "k6"),
])
def test_the_other_dataset_kinds_train_and_predict(inputs: list[str], preset: str, agents: str, k: str,
                                                   tmp_path: Path) -> None:
    data = Path(__file__).resolve().parents[1] / "data"
    dataset = tmp_path / "ds"
    assert runner.invoke(app, ["-q", "ingest", *(str(data / p) for p in inputs), "--out", str(dataset),
                               "--no-mcap"]).exit_code == 0
    config = tmp_path / "small.toml"
    table = "social_lstm" if preset == "social_lstm" else "social_gan"
    config.write_text(f"[{table}]\nbatch_size = 4\nval_every = 2\nval_windows = 4\n"
                      + ("hidden_dim = 16\nembedding_dim = 8\n" if table == "social_lstm" else ""))
    run = tmp_path / "run"
    result = runner.invoke(app, ["-q", "train", str(dataset), "--train-split", "all", "--val-split", "none",
                                 "--preset", preset, "--config", str(config), "--steps", "2", "--out", str(run)])
    assert result.exit_code == 0, result.output
    meta = json.loads((run / "best" / "meta.json").read_text())
    protocol = Dataset.open(dataset).protocol
    assert (meta["obs_len"], meta["pred_len"]) == (protocol.obs_len, protocol.pred_len)  # the dataset's windows
    pred = tmp_path / "pred"
    assert runner.invoke(app, ["-q", "predict", str(dataset), "--checkpoint", str(run / "best"), "--out", str(pred),
                               "--no-mcap"]).exit_code == 0
    result = runner.invoke(app, ["score", str(pred), "--truth", str(dataset), "--agents", agents, "--no-plots",
                                 "--out", str(tmp_path / "score"), "--json"])
    assert result.exit_code == 0, result.output
    method = json.loads(result.stdout)["methods"][table]
    assert method["counts"]["agents_missing"] == 0 and math.isfinite(method["overall"][k]["ade"])


def test_the_loop_keeps_the_best_validation_and_stops_when_it_no_longer_improves(tmp_path: Path) -> None:
    from logpipe.model.training.window_loop import LoopSettings, run_loop

    ades = iter([3.0, 2.0, 2.5, 2.6, 2.7, 1.0])
    saved: list[tuple[str, int, float]] = []
    result = run_loop([np.zeros((20, 2, 2))] * 5, LoopSettings(steps=60, batch_size=2, val_every=10, patience=3,
                                                               seed=0), tmp_path,
                      step=lambda next_batch: {"loss": float(next_batch().positions.shape[1])},
                      validate=lambda: {"ade": next(ades)},
                      save=lambda folder, step, m, _: saved.append((folder.name, step, m.get("ade", -1.0))))
    assert result.stopped_early and result.steps == 50 and result.best_step == 20
    # last/ at every validation (resumable), best/ when it improves
    assert saved == [("best", 10, 3.0), ("last", 10, 3.0), ("best", 20, 2.0), ("last", 20, 2.0), ("last", 30, 2.5),
                     ("last", 40, 2.6), ("last", 50, 2.7)]
    log = [json.loads(line) for line in (tmp_path / "train_log.jsonl").read_text().splitlines()]
    assert [r["step"] for r in log] == [10, 20, 30, 40, 50] and log[0]["loss"] == 4.0  # 2 windows of 2 agents
    budget = run_loop([np.zeros((20, 1, 2))], LoopSettings(steps=100, batch_size=1, val_every=5, patience=0, seed=0,
                                                          time_budget_s=1e-9), tmp_path,
                      step=lambda next_batch: {"loss": 0.0}, validate=lambda: {"ade": 1.0},
                      save=lambda folder, step, m, _: None)
    assert budget.stopped_early and budget.steps == 5  # stops at the first validation past the budget
