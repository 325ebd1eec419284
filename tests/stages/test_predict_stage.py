"""``predict_dataset`` on small datasets: exact constant-velocity output, the table contract, filters,
determinism, resuming, and checkpoint/dataset mismatches reported before any work."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from logpipe.contracts import arrow_schema
from logpipe.dataset.sample_filter import SampleFilter, parse_filter
from logpipe.errors import LogpipeError
from logpipe.model.zhu2020.checkpoint import save_checkpoint
from logpipe.model.zhu2020.config import Features, ModelConfig, TrainConfig
from logpipe.model.zhu2020.network import TrajectoryNet
from logpipe.prediction.runs import PredictionRun
from logpipe.stages.ingest import IngestOptions, ingest
from logpipe.stages.predict import predict_dataset

FRAME_STEP = 10  # ETH/UCY frame numbers advance by 10 per 0.4 s step
SUMMARY_KEYS = [
    "dataset", "out", "predictor", "checkpoint_id", "num_modes", "seed", "checkpoint", "raster_run", "inference",
    "warnings", "protocol", "logs_selected", "samples_selected", "shards_skipped_done", "samples", "targets", "rows",
    "targets_unobserved", "samples_without_targets", "targets_out_of_distribution", "targets_fallback", "mcap_files",
    "original_messages", "model_seconds", "io_seconds", "io_wait_seconds", "io_busy_seconds", "device", "backend",
    "shards", "rows_total", "samples_total", "targets_total", "already_done", "predictor_reason", "seconds",
    "samples_per_s",
]


def _straight_walkers(folder: Path) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """An ETH/UCY text file with three pedestrians on straight lines at constant speed (30 steps)."""
    walkers = {
        "1": (np.array([1.5, -2.25]), np.array([0.5, 0.25])),
        "2": (np.array([-3.0, 4.0]), np.array([-0.3, 0.0])),
        "3": (np.array([10.0, 10.0]), np.array([0.0, -0.75])),
    }
    lines = []
    for step in range(30):
        for ped, (start, vel) in walkers.items():
            x, y = start + step * vel
            lines.append(f"{step * FRAME_STEP}\t{ped}.0\t{x:.2f}\t{y:.2f}")
    path = folder / "lines" / "test" / "lines.txt"
    path.parent.mkdir(parents=True)
    path.write_text("\n".join(lines) + "\n")
    return walkers


@pytest.fixture(scope="module")
def lines_dataset(tmp_path_factory: pytest.TempPathFactory) -> Path:
    root = tmp_path_factory.mktemp("lines")
    _straight_walkers(root / "in")
    ingest([root / "in"], IngestOptions(out=root / "ds"))
    return root / "ds"


def test_constant_velocity_predictions_of_straight_tracks_are_exact(lines_dataset: Path, tmp_path: Path) -> None:
    summary = predict_dataset(lines_dataset, tmp_path / "out", predictor="cv", write_mcap=False)
    assert summary["samples"] == 11 and summary["num_modes"] == 20  # 30 steps, windows of 8 + 12
    assert list(summary) == SUMMARY_KEYS  # the --json contract: keys and their order
    assert summary["samples_per_s"] == round(11 / summary["seconds"], 1) and json.dumps(summary)
    table = pq.read_table(tmp_path / "out" / "predictions" / "part-00000.parquet")
    assert table.schema.equals(arrow_schema("predictions", pred_len=12))  # the contract exactly (metadata aside)
    assert table.num_rows == 11 * 3 * 20 == summary["rows"]  # a row per (sample, agent, mode)
    run = PredictionRun.open(tmp_path / "out")
    assert (run.meta.protocol, run.meta.obs_len, run.meta.pred_len, run.meta.num_modes) == ("ethucy", 8, 12, 20)
    assert PredictionRun.open(tmp_path / "out" / "predictions" / "part-00000.parquet").meta == run.meta
    assert run.meta.predictor == "cv" and run.meta.checkpoint_id.startswith("cv:")  # constants: metadata only
    rows = table.to_pydict()
    # Positions were written with 2 decimals: the expected line is through those exact observed values.
    for i, step in ((i, step) for i in range(0, table.num_rows, 7) for step in range(1, 13)):
        start_step = int(rows["sample_id"][i].split(":")[1])
        ped = rows["track_id"][i]
        start, vel = {"1": ([1.5, -2.25], [0.5, 0.25]), "2": ([-3.0, 4.0], [-0.3, 0.0]),
                      "3": ([10.0, 10.0], [0.0, -0.75])}[ped]
        now = start_step + 7
        cur = np.round(np.array(start) + now * np.array(vel), 2)
        prev = np.round(np.array(start) + (now - 1) * np.array(vel), 2)
        expected = cur + (cur - prev) * step
        assert rows["x"][i][step - 1] == pytest.approx(expected[0], abs=1e-9)
        assert rows["y"][i][step - 1] == pytest.approx(expected[1], abs=1e-9)
        assert rows["timestamp_ns"][i][step - 1] == (now + step) * 400_000_000  # true step times
        assert rows["score"][i] == pytest.approx(1 / 20)
    assert sorted(set(rows["mode"])) == list(range(20))


def test_rerun_resumes_and_other_settings_are_refused(lines_dataset: Path, tmp_path: Path) -> None:
    out = tmp_path / "out"
    first = predict_dataset(lines_dataset, out, predictor="cv_sampler", seed=3, modes=4)
    part = out / "predictions" / "part-00000.parquet"
    before = part.read_bytes()
    again = predict_dataset(lines_dataset, out, predictor="cv_sampler", seed=3, modes=4)
    assert again["shards_skipped_done"] == 1 and again["samples"] == 0 and again["rows_total"] == first["rows"]
    assert part.read_bytes() == before
    with pytest.raises(LogpipeError, match="other settings"):
        predict_dataset(lines_dataset, out, predictor="cv_sampler", seed=4, modes=4)
    assert not list(out.glob(".staging-*"))


def test_same_seed_same_output_other_seed_differs(lines_dataset: Path, tmp_path: Path) -> None:
    tables = []
    for name, seed in (("a", 7), ("b", 7), ("c", 8)):
        predict_dataset(lines_dataset, tmp_path / name, predictor="cv_sampler", seed=seed, write_mcap=False)
        tables.append(pq.read_table(tmp_path / name / "predictions" / "part-00000.parquet"))
    assert tables[0].equals(tables[1])
    assert not np.array_equal(*(t.column("x").combine_chunks().flatten().to_numpy() for t in (tables[0], tables[2])))


def test_filters_select_logs_times_and_types(lines_dataset: Path, tmp_path: Path) -> None:
    f = parse_filter(["log=lines", "time=4400000000:6000000000", "type=pedestrian"])
    assert f == SampleFilter(("lines",), None, 4_400_000_000, 6_000_000_000, ("pedestrian",))
    summary = predict_dataset(lines_dataset, tmp_path / "a", predictor="linear", sample_filter=f, write_mcap=False)
    assert summary["samples"] == 5  # current steps 11..15 (times 4.4 s .. 6.0 s)
    none = predict_dataset(lines_dataset, tmp_path / "b", predictor="cv", write_mcap=False,
                           sample_filter=parse_filter(["type=vehicle"]))
    assert none["samples"] == 0 and none["samples_without_targets"] == 11
    for bad in (["time=abc"], ["type=robot"], ["colour=red"], ["log"]):
        with pytest.raises(LogpipeError):
            parse_filter(bad)
    with pytest.raises(LogpipeError, match="no logs"):
        predict_dataset(lines_dataset, tmp_path / "c", predictor="cv", sample_filter=SampleFilter(("nope",)))


def _small_net_config(**overrides: object) -> ModelConfig:
    base: dict[str, object] = {"embed_dim": 16, "gru_dim": 16, "lstm_dim": 16, "noise_dim": 4,
                               "features": Features(True, True, False, False, False)}
    base.update(overrides)
    return ModelConfig(**base)  # type: ignore[arg-type]


def _checkpoint(folder: Path, cfg: ModelConfig, kind: str) -> Path:
    net = TrajectoryNet(cfg)
    return save_checkpoint(folder, net, TrainConfig(model=cfg), dataset_kind=kind, manifest_hash="x", step=0)


def test_checkpoint_runs_and_mismatches_fail_before_any_output(lines_dataset: Path, tmp_path: Path) -> None:
    good = _checkpoint(tmp_path / "good", _small_net_config(), "ethucy")
    summary = predict_dataset(lines_dataset, tmp_path / "out", checkpoint=good, modes=3, write_mcap=False)
    table = pq.read_table(tmp_path / "out" / "predictions" / "part-00000.parquet")
    assert summary["predictor"] == "zhu2020" and table.num_rows == 11 * 3 * 3
    assert _recorded_ids(tmp_path / "out") == {json.loads((good / "meta.json").read_text())["weights_sha256"]}
    assert np.isfinite(table.column("x").combine_chunks().flatten().to_numpy()).all()

    wrong = _checkpoint(tmp_path / "wrong", _small_net_config(obs_len=20, pred_len=30), "argoverse1")
    with pytest.raises(LogpipeError, match=r"dataset kind.*obs/pred lengths"):
        predict_dataset(lines_dataset, tmp_path / "never", checkpoint=wrong)
    env = _checkpoint(tmp_path / "env", _small_net_config(features=Features(True, True, False, False, True)),
                      "ethucy")
    with pytest.raises(LogpipeError, match="environment net"):
        predict_dataset(lines_dataset, tmp_path / "never", checkpoint=env)
    from logpipe.model import registry

    shipped: list[Path] = []
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(registry, "shipped_checkpoints", lambda kind: shipped)
        fallback = predict_dataset(lines_dataset, tmp_path / "fallback", write_mcap=False)  # none shipped: Kalman
        assert fallback["predictor"] == "kalman" and fallback["samples"] > 0
        assert "no shipped model serves dataset kind 'ethucy'" in fallback["predictor_reason"]
        shipped += [tmp_path / "eth", good.rename(tmp_path / "lines")]
        with pytest.raises(LogpipeError, match="several shipped checkpoints"):
            predict_dataset(lines_dataset, tmp_path / "never")
        picked = predict_dataset(lines_dataset, tmp_path / "by_split", sample_filter=parse_filter(["split=lines/test"]),
                                 modes=2, write_mcap=False)
        assert picked["predictor"] == "zhu2020" and picked["samples"] == 11
    with pytest.raises(LogpipeError, match="unknown --predictor"):
        predict_dataset(lines_dataset, tmp_path / "never", predictor="oracle")
    assert not (tmp_path / "never").exists()


def _window_by_rows(tracks: pa.Table, row: dict[str, Any]) -> dict[str, Any]:
    """A sample's window read row by row from the table (the reference ``LogWindows`` is checked against)."""
    start, end = int(row["start_step"]), int(row["end_step"])
    names: list[str] = []
    xy: dict[tuple[str, int], tuple[float, float]] = {}
    times: dict[int, int] = {}
    types: dict[str, str] = {}
    egos: list[str] = []
    for r in tracks.to_pylist():
        if start <= r["step"] <= end:
            track = str(r["track_id"])
            if track not in names:
                names.append(track)
            xy[track, r["step"] - start] = (r["x"], r["y"])
            times[r["step"] - start] = r["timestamp_ns"]
            types[track] = r["object_type"]
            if r["role"] == "ego":
                egos.append(track)
    return {"names": names, "xy": xy, "times": times, "types": types, "egos": egos}


def test_log_windows_cut_each_sample_as_its_rows_say(tmp_path: Path) -> None:
    from logpipe.dataset.reader import Dataset, scene_sample
    from logpipe.dataset.windows import LogWindows
    from logpipe.types import OBJECT_TYPES

    bundled = Path(__file__).resolve().parents[2] / "tests" / "data"
    ingest([bundled / "ethucy"], IngestOptions(out=tmp_path / "eth"))
    ingest([bundled / "argoverse1"], IngestOptions(out=tmp_path / "av1"))
    checked = 0
    for name in ("eth", "av1"):
        dataset = Dataset.open(tmp_path / name)
        rows = dataset.samples().to_pylist()
        for log_id, tracks in dataset.iter_logs():
            windows = LogWindows(tracks)
            for row in [r for r in rows if r["log_id"] == log_id][::15]:
                got, want = windows.sample(row, dataset.protocol.obs_len), _window_by_rows(tracks, row)
                assert got.track_ids == want["names"] and got.sample_id == row["sample_id"]
                seen = ~np.isnan(got.positions[..., 0])
                assert int(seen.sum()) == len(want["xy"])
                for (track, step), (x, y) in want["xy"].items():
                    assert tuple(got.positions[got.track_ids.index(track), step]) == (x, y)
                assert {s: int(got.timestamps_ns[s]) for s in want["times"]} == want["times"]
                assert [OBJECT_TYPES[t] for t in got.object_types] == [want["types"][n] for n in got.track_ids]
                assert got.target_mask.tolist() == [n in row["target_track_ids"] for n in got.track_ids]
                ego = min((got.track_ids.index(e) for e in want["egos"]), default=-1)
                assert (got.ego_index, got.obs_len) == (ego, dataset.protocol.obs_len)
                same = scene_sample(tracks, row, dataset.protocol)  # the dataset's reader cuts through it
                np.testing.assert_array_equal(same.positions, got.positions)
                checked += 1
    assert checked > 30


def test_background_writer_output_does_not_depend_on_batching(lines_dataset: Path, tmp_path: Path) -> None:
    """Batches spanning logs, one sample per batch, or everything in one batch: the same table and MCAPs."""
    import pyarrow.parquet as pq

    tables, mcaps = [], []
    for size in (1, 3, 1000):
        out = tmp_path / f"b{size}"
        predict_dataset(lines_dataset, out, predictor="cv", batch_size=size)
        tables.append(pq.read_table(sorted((out / "predictions").glob("*.parquet"))[0]))
        mcaps.append(sorted(p.relative_to(out) for p in (out / "mcap").rglob("*.mcap")))
    assert tables[0].num_rows > 0 and mcaps[0]
    for table, names in zip(tables[1:], mcaps[1:], strict=True):
        assert table.equals(tables[0])
        assert names == mcaps[0]


def _recorded_ids(run: Path) -> set[str]:
    """The checkpoint id the predictions file's own metadata records."""
    return {PredictionRun.open(run / "predictions" / "part-00000.parquet").meta.checkpoint_id}


def _weights_sha(checkpoint: Path) -> str:
    return str(json.loads((checkpoint / "meta.json").read_text())["weights_sha256"])


def test_constant_velocity_modes_are_the_cv_forecast_and_are_recorded(lines_dataset: Path, tmp_path: Path) -> None:
    """``constant_velocity_modes = 1``: mode 0 of every agent is what the constant-velocity baseline predicts, the
    other modes are not; the predictions name the setting; baselines and counts beyond K are refused."""
    net = _checkpoint(tmp_path / "net", _small_net_config(step_output="velocity_change"), "ethucy")
    predict_dataset(lines_dataset, tmp_path / "held", checkpoint=net, modes=3, constant_velocity_modes=1,
                    write_mcap=False)
    predict_dataset(lines_dataset, tmp_path / "cv", predictor="cv", modes=1, write_mcap=False)

    def positions(run: str, mode: int) -> dict[tuple[str, str, int], tuple[float, float]]:
        t = pq.read_table(tmp_path / run / "predictions" / "part-00000.parquet").to_pydict()
        return {(t["sample_id"][i], t["track_id"][i], s + 1): (t["x"][i][s], t["y"][i][s])
                for i in range(len(t["x"])) if t["mode"][i] == mode for s in range(len(t["x"][i]))}

    cv, held, learned = positions("cv", 0), positions("held", 0), positions("held", 1)
    assert held.keys() == cv.keys() and len(cv) == 11 * 3 * 12
    assert all(held[k] == pytest.approx(cv[k], abs=1e-4) for k in cv)
    assert max(abs(learned[k][0] - cv[k][0]) + abs(learned[k][1] - cv[k][1]) for k in cv) > 1e-2
    assert _recorded_ids(tmp_path / "held") == {f"{_weights_sha(net)} constant_velocity_modes=1"}
    with pytest.raises(LogpipeError, match="constant-velocity-modes"):
        predict_dataset(lines_dataset, tmp_path / "never", predictor="cv", constant_velocity_modes=1)
    with pytest.raises(LogpipeError, match=r"0\.\.3"):
        predict_dataset(lines_dataset, tmp_path / "never", checkpoint=net, modes=3, constant_velocity_modes=4)


def test_noise_scale_widens_the_modes_and_is_recorded(lines_dataset: Path, tmp_path: Path) -> None:
    """``noise_scale`` multiplies the noise z (scale 1 is the default draw); the spread of the K futures grows
    with it, the predictions name it, and it cannot be given to a baseline or be non-positive."""
    import torch

    from logpipe.dataset.reader import Dataset
    from logpipe.model.zhu2020.batching import collate
    from logpipe.model.zhu2020.predictor import NetPredictor
    from logpipe.stages.train import scene_samples

    good = _checkpoint(tmp_path / "good", _small_net_config(), "ethucy")
    samples = scene_samples(Dataset.open(lines_dataset), "lines/test")
    base = NetPredictor.from_checkpoint(good, expect_kind="ethucy")
    wide = NetPredictor.from_checkpoint(good, expect_kind="ethucy", noise_scale=3.0)
    one = NetPredictor.from_checkpoint(good, expect_kind="ethucy", noise_scale=1.0)
    a, b, c = (np.concatenate(p.predict(samples, 8, 5)) for p in (base, wide, one))
    assert np.array_equal(a, c)
    with torch.no_grad():  # the same draw of z, tripled, through the network
        batch = collate(samples, base.config)
        gen = torch.Generator().manual_seed(5)
        r = int(batch.active.sum())
        z = torch.randn(8, r, base.config.noise_dim, generator=gen)
        direct = base.net.decode_fast(batch, base.net.encode(batch), 3.0 * z)
        gen = torch.Generator().manual_seed(5)
        scaled = base.net(batch, 8, gen, fast=True, noise_scale=3.0)
    assert torch.allclose(direct.positions, scaled.positions)
    assert b.std(axis=1).mean() > a.std(axis=1).mean()
    predict_dataset(lines_dataset, tmp_path / "out", checkpoint=good, modes=3, noise_scale=2.5, write_mcap=False)
    assert _recorded_ids(tmp_path / "out") == {f"{_weights_sha(good)} noise_scale=2.5"}
    with pytest.raises(LogpipeError, match="noise-scale"):
        predict_dataset(lines_dataset, tmp_path / "never", predictor="cv", noise_scale=2.0)
    with pytest.raises(LogpipeError, match="positive"):
        NetPredictor.from_checkpoint(good, expect_kind="ethucy", noise_scale=0.0)


def test_context_max_neighbours_is_recorded_and_refused_where_it_cannot_apply(lines_dataset: Path,
                                                                             tmp_path: Path) -> None:
    """The neighbour cap is an inference setting of a network with a context radius: recorded in the predictions'
    checkpoint_id, refused for a baseline, a negative count and a network that pools the whole window."""
    ringed = _checkpoint(tmp_path / "ringed", _small_net_config(context_radius_m=2.0), "ethucy")
    predict_dataset(lines_dataset, tmp_path / "out", checkpoint=ringed, modes=2, context_max_neighbours=1,
                    write_mcap=False)
    assert _recorded_ids(tmp_path / "out") == {f"{_weights_sha(ringed)} context_max_neighbours=1"}
    with pytest.raises(LogpipeError, match="context-max-neighbours"):
        predict_dataset(lines_dataset, tmp_path / "never", predictor="cv", context_max_neighbours=1)
    with pytest.raises(LogpipeError, match=">= 0"):
        predict_dataset(lines_dataset, tmp_path / "never", checkpoint=ringed, context_max_neighbours=-1)
    whole = _checkpoint(tmp_path / "whole", _small_net_config(), "ethucy")
    with pytest.raises(LogpipeError, match="context_radius_m"):
        predict_dataset(lines_dataset, tmp_path / "never", checkpoint=whole, context_max_neighbours=1)
    assert not (tmp_path / "never").exists()


def test_checkpoint_settings_are_predicts_defaults_and_training_logs_warn(lines_dataset: Path,
                                                                         tmp_path: Path) -> None:
    from logpipe.dataset.reader import Dataset
    from logpipe.model.checkpoint.format import InferenceSettings, TrainingData
    from logpipe.model.zhu2020.meta import amend_meta

    folder = _checkpoint(tmp_path / "ck", _small_net_config(step_output="velocity_change"), "ethucy")
    amend_meta(folder, inference=InferenceSettings(num_modes=4, noise_scale=0.5, constant_velocity_modes=1,
                                                   chosen_on="lines/val"),
               training_data=TrainingData.of(Dataset.open(lines_dataset), "lines/test", None))
    stored = predict_dataset(lines_dataset, tmp_path / "stored", checkpoint=folder, write_mcap=False)
    assert stored["num_modes"] == 4  # the K the settings were chosen at
    assert stored["inference"] == {"noise_scale": 0.5, "constant_velocity_modes": 1, "context_max_neighbours": None,
                                   "source": "checkpoint", "chosen_on": "lines/val"}
    assert stored["warnings"] and "trained on (split lines/test): lines" in stored["warnings"][0]
    meta = PredictionRun.open(tmp_path / "stored").meta
    assert (meta.noise_scale, meta.constant_velocity_modes, meta.num_modes) == (0.5, 1, 4)
    assert meta.checkpoint_id.endswith(" noise_scale=0.5 constant_velocity_modes=1")

    # the same settings given as options give the same forecasts; --as-trained does not
    explicit = predict_dataset(lines_dataset, tmp_path / "explicit", checkpoint=folder, write_mcap=False,
                               as_trained=True, modes=4, noise_scale=0.5, constant_velocity_modes=1)
    assert explicit["inference"]["source"] == "as trained + options"
    same = PredictionRun.open(tmp_path / "explicit").dense().pred
    np.testing.assert_array_equal(same, PredictionRun.open(tmp_path / "stored").dense().pred)
    plain = predict_dataset(lines_dataset, tmp_path / "plain", checkpoint=folder, write_mcap=False, as_trained=True,
                            modes=4)
    assert plain["inference"]["noise_scale"] == 1.0 and plain["checkpoint_id"] == meta.checkpoint_sha256
    assert not np.array_equal(PredictionRun.open(tmp_path / "plain").dense().pred, same)
