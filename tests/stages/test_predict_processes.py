"""``logpipe predict --workers N`` with a network: the batches are forecast in N local worker processes, each
loading the model once, and the run writes the same bytes as one process (Parquet, MCAPs and manifest)."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import pytest

from logpipe.dataset.sample_filter import parse_filter
from logpipe.prediction.options import PROCESS_MIN_SAMPLES, PredictOptions
from logpipe.stages.ingest import IngestOptions, ingest
from logpipe.stages.predict import predict_dataset

DATA = Path(__file__).resolve().parents[1] / "data"
SHIPPED = Path(__file__).resolve().parents[2] / "model" / "checkpoints"
ETH_CHECKPOINT = SHIPPED / "ethucy" / "eth"


def test_eth_network_in_two_processes_writes_the_bytes_of_one(folder_digests: Callable[[Path], dict[str, str]],
                                                              tmp_path: Path) -> None:
    # A shard per input file: the selected eth/test logs lie in one of three, so the planning skips shards too.
    ingest([DATA / "ethucy"], IngestOptions(out=tmp_path / "eth", batch_files=1))
    assert len(list((tmp_path / "eth" / "tracks").glob("*.parquet"))) == 3
    # Small batches: the work is cut into several items, so both processes forecast and the driver interleaves them.
    settings = {"checkpoint": ETH_CHECKPOINT, "batch_size": 3, "threads": 1,
                "sample_filter": parse_filter(["split=eth/test", "time=:200000000000"])}
    one = predict_dataset(tmp_path / "eth", tmp_path / "one", workers=1, **settings)
    two = predict_dataset(tmp_path / "eth", tmp_path / "two", workers=2, **settings)
    assert one["device"] == "cpu" and two["device"] is None  # None: each worker process chose its own
    assert two["samples"] == one["samples"] >= 10 and two["rows"] == one["rows"] > 0 and two["mcap_files"] > 0
    files = folder_digests(tmp_path / "one")
    assert any(name.endswith(".mcap") for name in files) and "manifest.json" in files
    assert folder_digests(tmp_path / "two") == files


@pytest.mark.parametrize(("checkpoint", "predictor"),
                         [(None, "residual"), (SHIPPED / "argoverse" / "paper", "zhu2020")])
def test_driving_model_over_rasters_in_two_processes_writes_the_bytes_of_one(
        folder_digests: Callable[[Path], dict[str, str]], driving_rasterised: Path, tmp_path: Path,
        checkpoint: Path | None, predictor: str) -> None:
    data = driving_rasterised
    # The shipped Argoverse checkpoints, predict's default and the paper's network (both read the rasters with an
    # environment net); their MCAPs carry the raster images.
    settings = {"checkpoint": checkpoint, "batch_size": 1, "threads": 1}
    one = predict_dataset(data, tmp_path / "one", workers=1, **settings)
    two = predict_dataset(data, tmp_path / "two", workers=2, **settings)
    assert one["predictor"] == predictor and one["raster_run"] is not None
    assert two["samples"] == one["samples"] == 2 and two["mcap_files"] == one["mcap_files"] == 2
    assert folder_digests(tmp_path / "two") == folder_digests(tmp_path / "one")


def _shard_jobs_only(monkeypatch: pytest.MonkeyPatch) -> None:
    """Workers predict whole shards from one shard with logs per worker on (the bundled data has few shards), and
    the batch-forecast path fails the test if taken."""
    from logpipe.model import ray_predict
    from logpipe.stages import predict

    monkeypatch.setattr(ray_predict, "SHARDS_PER_WORKER", 1)

    def refused(*args: object, **kwargs: object) -> None:
        raise AssertionError("the workers forecast batches cut by the stage instead of predicting whole shards")

    monkeypatch.setattr(predict, "process_forecasts", refused)
    monkeypatch.setattr(predict, "ray_forecasts", refused)


def test_eth_shard_jobs_in_two_processes_write_the_bytes_of_one(folder_digests: Callable[[Path], dict[str, str]],
                                                                tmp_path: Path,
                                                                monkeypatch: pytest.MonkeyPatch) -> None:
    # Three shards with selected logs: each worker cuts, forecasts and writes whole shards (Parquet and MCAPs).
    ingest([DATA / "ethucy"], IngestOptions(out=tmp_path / "eth", batch_files=1))
    settings = {"checkpoint": ETH_CHECKPOINT, "batch_size": 5, "threads": 1,
                "sample_filter": parse_filter(["time=:30000000000"])}
    one = predict_dataset(tmp_path / "eth", tmp_path / "one", workers=1, **settings)
    _shard_jobs_only(monkeypatch)
    two = predict_dataset(tmp_path / "eth", tmp_path / "two", workers=2, **settings)
    assert one["shards"] == two["shards"] == 3 and two["device"] is None
    assert two["samples"] == one["samples"] >= 30 and two["rows"] == one["rows"] > 0 and two["mcap_files"] == 3
    assert two["targets"] == one["targets"] and two["model_seconds"] > 0  # the workers' counts reach the summary
    assert folder_digests(tmp_path / "two") == folder_digests(tmp_path / "one")


def test_driving_shard_jobs_carry_their_own_rasters(folder_digests: Callable[[Path], dict[str, str]],
                                                   tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from logpipe.maps import MapSource
    from logpipe.stages.rasterise import rasterise_dataset

    # A shard per sequence, so each worker gets one shard and only that shard's raster (the default model's
    # environment net reads it).
    driving = DATA / "driving"
    ingest([driving / "20.csv", driving / "32.csv"], IngestOptions(out=tmp_path / "av1", batch_files=1))
    rasterise_dataset(tmp_path / "av1", MapSource(files={"MIA": driving / "MIA_lane_centerlines_crop_20.npz",
                                                         "PIT": driving / "PIT_lane_centerlines_crop_32.npz"}),
                      rotate=True)
    one = predict_dataset(tmp_path / "av1", tmp_path / "one", workers=1, batch_size=1, threads=1)
    _shard_jobs_only(monkeypatch)
    from logpipe.model import ray_predict

    shipped: list[int] = []
    original = ray_predict._in_processes

    def counting(work: list[tuple[str, Callable[[], object], object]], workers: int) -> object:
        shipped.extend(len(job.run.cutter.raster_ids) for _, _, job in work)  # type: ignore[attr-defined]
        return original(work, workers)

    monkeypatch.setattr(ray_predict, "_in_processes", counting)
    two = predict_dataset(tmp_path / "av1", tmp_path / "two", workers=2, batch_size=1, threads=1)
    assert one["predictor"] == "residual" and one["shards"] == 2 and shipped == [1, 1]
    assert two["samples"] == one["samples"] == 2 and two["mcap_files"] == 2
    assert folder_digests(tmp_path / "two") == folder_digests(tmp_path / "one")


@pytest.mark.parametrize(("options", "samples", "on_cpu", "expected"), [
    (PredictOptions(workers=3), 1, True, 3),  # asked for: always, however small the run
    (PredictOptions(workers=1), 10**6, True, 0),  # one worker: this process
    (PredictOptions(workers=3), 10**6, False, 0),  # a GPU is not shared between processes
    (PredictOptions(workers=3, backend="ray"), 10**6, True, 0),  # Ray's actors instead
    (PredictOptions(threads=2), 10**6, True, 0),  # threads asked for, workers not: this process on them
])
def test_when_a_network_forecasts_in_worker_processes(options: PredictOptions, samples: int, on_cpu: bool,
                                                       expected: int) -> None:
    assert options.forecast_processes(samples, on_cpu=on_cpu, environment_net=True) == expected


def test_by_default_processes_start_only_when_the_run_amortises_them(monkeypatch: pytest.MonkeyPatch) -> None:
    from logpipe.prediction import options

    monkeypatch.setattr(options, "default_workers", lambda: 2)
    for env in (True, False):
        least = 2 * PROCESS_MIN_SAMPLES[env]
        assert PredictOptions().forecast_processes(least, on_cpu=True, environment_net=env) == 2
        assert PredictOptions().forecast_processes(least - 1, on_cpu=True, environment_net=env) == 0  # make demo
    # A network without the environment net forecasts a sample far faster: more samples pay for the start-up.
    assert PROCESS_MIN_SAMPLES[False] > PROCESS_MIN_SAMPLES[True]
    monkeypatch.setattr(options, "default_workers", lambda: 1)
    assert PredictOptions().forecast_processes(10**6, on_cpu=True, environment_net=True) == 0


def test_the_help_states_the_default_thresholds() -> None:
    from typer.testing import CliRunner

    from logpipe.cli import app

    result = CliRunner().invoke(app, ["predict", "--help"], terminal_width=400)
    text = " ".join(result.output.replace("│", " ").split())
    assert f"{PROCESS_MIN_SAMPLES[True]} samples per core with the environment net" in text
    assert f"{PROCESS_MIN_SAMPLES[False]:,} without" in text


def test_workers_get_only_the_selected_samples_rasters_and_no_input_list(
        folder_digests: Callable[[Path], dict[str, str]], driving_rasterised: Path, tmp_path: Path) -> None:
    from logpipe.dataset.reader import Dataset
    from logpipe.model.ray_predict import _planned_items
    from logpipe.stages.predict import _prepare

    data = driving_rasterised
    first = sorted(Dataset.open(data).logs().column("log_id").to_pylist())[0]
    chosen = PredictOptions(sample_filter=parse_filter([f"log={first}"]), batch_size=1, threads=1)
    run, *_ = _prepare(data, tmp_path / "unused", chosen)
    assert run.job.cutter.rasters is not None and run.job.cutter.rasters.index.num_rows == 2
    items, setup = _planned_items(run.job, list(run.logs), run.samples, run.job.dataset.shard_paths, 2, 1, "cpu")
    shipped = setup.args[0]  # the ForecastJob each worker gets
    assert shipped.cutter.rasters.index.column("sample_id").to_pylist() == run.samples.sample_ids().to_pylist()
    assert shipped.cutter.raster_ids == frozenset(run.samples.sample_ids().to_pylist())
    assert "inputs" not in shipped.dataset.manifest and len(Dataset.open(data).manifest["inputs"]) == 2
    assert [row["sample_id"] for _, batches in items for batch in batches for _, row in batch] == \
        run.samples.sample_ids().to_pylist()
    # And the run over that selection writes the bytes of one process.
    one = predict_dataset(data, tmp_path / "one", chosen, workers=1)
    two = predict_dataset(data, tmp_path / "two", chosen, workers=2)
    assert one["samples"] == two["samples"] == 1
    assert folder_digests(tmp_path / "two") == folder_digests(tmp_path / "one")
