"""Issue 33, item 1: ``--window`` on ingest / index (AV2 sensor logs as sliding windows under the ``argoverse2``
preset) and ``logpipe train`` over several datasets at once (splits in each, one checkpoint recording every
format, the manifests and the union of the recordings; a several-format checkpoint fits each of its formats)."""

from __future__ import annotations

import hashlib
import json
from collections import defaultdict
from pathlib import Path

import pyarrow as pa
import pyarrow.compute as pc
import pyarrow.parquet as pq
import pytest
from typer.testing import CliRunner

import logpipe
from logpipe.cli import app
from logpipe.dataset.reader import Dataset
from logpipe.errors import DatasetError, LogpipeError
from logpipe.model.checkpoint.format import CheckpointMismatchError, TrainingData, combined_manifest_hash, kind_accepts
from logpipe.model.registry import check_fit, choose_predictor
from logpipe.model.zhu2020.checkpoint import load_checkpoint
from logpipe.model.zhu2020.meta import read_meta

runner = CliRunner()
CONFIG = "[train]\nsteps = 2\neval_every = 2\nbatch_size = 2\nnum_modes = 2\nval_modes = 2\nval_max_samples = 8\n" \
         "num_threads = 1\n"
AV2_SLIDING = ["--protocol", "argoverse2", "--obs", "20", "--pred", "30", "--window", "sliding", "--stride", "10",
               "--targets", "fully_observed_no_ego", "--target-types", "vehicle,bus_truck"]


def _starts(root: Path) -> dict[str, list[int]]:
    """Window start steps of each log, from the sample index."""
    table = pq.read_table(root / "samples")
    starts: dict[str, list[int]] = defaultdict(list)
    for log, start in zip(table.column("log_id").to_pylist(), table.column("start_step").to_pylist(), strict=True):
        starts[str(log)].append(int(start))
    return {log: sorted(s) for log, s in starts.items()}


def _steps(root: Path) -> dict[str, int]:
    """Distinct timestamps of each log, read from the track shards (not from the sample index)."""
    ds = Dataset.open(root)
    times: dict[str, set[int]] = defaultdict(set)
    for shard in ds.shard_paths:
        table = pq.read_table(shard, columns=["log_id", "timestamp_ns"])
        for log, t in zip(table.column("log_id").to_pylist(), table.column("timestamp_ns").to_pylist(), strict=True):
            times[str(log)].add(int(t))
    return {log: len(t) for log, t in times.items()}


def _ingest(args: list[str]) -> dict[str, object]:
    result = runner.invoke(app, ["ingest", *args, "--no-mcap", "--workers", "1", "--json"])
    assert result.exit_code == 0, result.output
    summary: dict[str, object] = json.loads(result.stdout)
    return summary


def test_window_sliding_cuts_av2_logs_under_the_argoverse2_preset(shared: Path, tmp_path: Path) -> None:
    out = tmp_path / "av2"
    summary = _ingest([str(shared / "av2"), "--out", str(out), *AV2_SLIDING])
    protocol = Dataset.open(out).protocol
    assert (protocol.name, protocol.window, protocol.stride) == ("argoverse2-custom", "sliding", 10)
    # One window every 10 steps while 20 + 30 steps fit, in each of the 5 logs (the scenario and 4 sensor logs).
    steps = _steps(out)
    assert len(steps) == 5
    assert _starts(out) == {log: list(range(0, n - 50 + 1, 10)) for log, n in steps.items()}
    assert summary["samples"] == sum((n - 50) // 10 + 1 for n in steps.values()) == 51
    # index takes the option too: back to one window at step 0 per log, and again sliding.
    first = runner.invoke(app, ["index", str(out), "--window", "first", "--json"])
    assert first.exit_code == 0, first.output
    assert json.loads(first.stdout)["samples"] == 5 and _starts(out) == {log: [0] for log in steps}
    again = runner.invoke(app, ["index", str(out), "--window", "sliding", "--json"])
    assert json.loads(again.stdout)["samples"] == 51


def test_window_sliding_on_the_bundled_av1_csvs(bundled: Path, tmp_path: Path) -> None:
    out = tmp_path / "av1"
    _ingest([str(bundled / "argoverse1"), "--out", str(out), "--obs", "8", "--pred", "12", "--window", "sliding",
             "--stride", "10"])
    assert Dataset.open(out).protocol.name == "argoverse-custom"
    steps = _steps(out)
    assert len(steps) == 6 and _starts(out) == {log: list(range(0, n - 20 + 1, 10)) for log, n in steps.items()}


def test_an_unknown_window_is_refused(bundled: Path, tmp_path: Path) -> None:
    result = runner.invoke(app, ["ingest", str(bundled / "argoverse1"), "--out", str(tmp_path / "a"), "--window",
                                 "middle"])
    assert result.exit_code == 2
    assert "--window must be sliding or first, got 'middle'" in result.output
    assert not (tmp_path / "a").exists()


def _sources(root: Path, split: str) -> set[str]:
    """sha256 of the recordings behind ``split`` of a dataset, from its logs table."""
    ds = Dataset.open(root)
    try:
        keep = ds.logs_in_split(split)
    except DatasetError:
        return set()
    logs = ds.logs()
    return {str(s) for log, s in zip(logs.column("log_id").to_pylist(), logs.column("source_sha256").to_pylist(),
                                     strict=True) if log in keep}


def _split_samples(root: Path, split: str) -> int:
    ds = Dataset.open(root)
    try:
        keep = ds.logs_in_split(split)
    except DatasetError:
        return 0
    table = pq.read_table(root / "samples", columns=["log_id"])
    return int(pc.sum(pc.is_in(table.column("log_id").cast(pa.string()), value_set=pa.array(keep, pa.string())))
               .as_py())


def _sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


@pytest.fixture(scope="module")
def two_formats(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path, Path]:
    """The bundled ETH/UCY and ApolloScape files (cut at ETH/UCY's 8 + 12 steps) and a bundled AV1 dataset."""
    root = tmp_path_factory.mktemp("multi")
    bundled = Path(__file__).resolve().parents[1] / "data"
    _ingest([str(bundled / "ethucy"), "--out", str(root / "eth")])
    _ingest([str(bundled / "apolloscape"), "--out", str(root / "apo"), "--obs", "8", "--pred", "12"])
    _ingest([str(bundled / "argoverse1"), "--out", str(root / "av1")])
    return root / "eth", root / "apo", root / "av1"


def test_train_on_two_datasets_records_both(two_formats: tuple[Path, Path, Path], tmp_path: Path) -> None:
    eth, apo, av1 = two_formats
    config = tmp_path / "c.toml"
    config.write_text(CONFIG)
    # Default splits hash/train and hash/val in each dataset; ApolloScape's 2 logs hold no hash/val log.
    result = runner.invoke(app, ["train", str(eth), str(apo), "--out", str(tmp_path / "run"), "--config",
                                 str(config), "--steps", "2", "--json"])
    assert result.exit_code == 0, result.output
    summary = json.loads(result.stdout)
    assert summary["dataset"] == [str(eth), str(apo)] and summary["steps"] == 2
    per = summary["per_dataset"]
    assert [p["format"] for p in per] == ["ethucy", "apolloscape"]
    assert [p["train_samples"] for p in per] == [_split_samples(eth, "hash/train"), _split_samples(apo, "hash/train")]
    assert [p["val_samples"] for p in per] == [_split_samples(eth, "hash/val"), 0]
    assert summary["train_samples"] == sum(p["train_samples"] for p in per) > 0

    meta = read_meta(Path(summary["last_checkpoint"]))
    assert meta.dataset_kind == "apolloscape+ethucy"
    manifests = [_sha256(eth / "manifest.json"), _sha256(apo / "manifest.json")]
    assert meta.manifest_hash == combined_manifest_hash(manifests) and meta.manifest_hash not in manifests
    assert meta.training_data is not None
    assert (meta.training_data.train_split, meta.training_data.val_split) == ("hash/train", "hash/val")
    assert set(meta.training_data.train_sources) == _sources(eth, "hash/train") | _sources(apo, "hash/train")
    assert set(meta.training_data.val_sources) == _sources(eth, "hash/val")

    # The kind check: each of its formats passes, a third does not.
    folder = Path(summary["last_checkpoint"])
    for kind in ("ethucy", "apolloscape"):
        assert load_checkpoint(folder, expect_kind=kind).meta.dataset_kind == "apolloscape+ethucy"
    with pytest.raises(CheckpointMismatchError, match="dataset kind: expected 'argoverse1'"):
        load_checkpoint(folder, expect_kind="argoverse1")
    for root, fits in ((eth, True), (apo, True), (av1, False)):
        ds = Dataset.open(root)
        problems = check_fit(ds, choose_predictor(ds, folder, None), ds.logs())
        assert any(p.startswith("dataset kind:") for p in problems) is not fits, problems
    # predict over ApolloScape with it: no kind error, and its training recordings are flagged.
    pred = logpipe.predict(apo, out=tmp_path / "pred", checkpoint=folder, modes=2, mcap=False)
    assert any("trained on (split hash/train)" in w for w in pred["warnings"])
    with pytest.raises(LogpipeError, match="dataset kind"):
        logpipe.predict(av1, out=tmp_path / "pred_av1", checkpoint=folder, modes=2, mcap=False)


def test_train_streams_several_datasets_one_after_the_other(two_formats: tuple[Path, Path, Path],
                                                            tmp_path: Path) -> None:
    from logpipe.model.training.run_folder import ChainedScenes

    eth, apo, _ = two_formats
    chained = ChainedScenes([[1, 2], [], [3]])
    assert list(chained) == list(chained) == [1, 2, 3]  # re-iterable: fit reads it every epoch
    config = tmp_path / "c.toml"
    config.write_text(CONFIG)
    summary = logpipe.train([apo, eth], out=tmp_path / "run", config=config, train_split="all", val_split="none",
                            loader_workers=1)
    assert summary["steps"] == 2 and summary["train_samples"] == "streamed"
    assert [p["train_samples"] for p in summary["per_dataset"]] == ["streamed", "streamed"]
    assert read_meta(Path(summary["last_checkpoint"])).dataset_kind == "apolloscape+ethucy"


def test_single_dataset_checkpoint_meta_is_unchanged(two_formats: tuple[Path, Path, Path], tmp_path: Path) -> None:
    _, apo, _ = two_formats
    config = tmp_path / "c.toml"
    config.write_text(CONFIG)
    summary = logpipe.train(apo, out=tmp_path / "run", config=config, train_split="all", val_split="none")
    assert summary["dataset"] == str(apo) and "per_dataset" not in summary and summary["raster_run"] is None
    meta = read_meta(Path(summary["last_checkpoint"]))
    assert meta.dataset_kind == "apolloscape"
    assert meta.manifest_hash == _sha256(apo / "manifest.json")
    assert meta.training_data == TrainingData.of(Dataset.open(apo), "all", None)
    assert meta.training_data is not None and set(meta.training_data.train_sources) == _sources(apo, "all")


def test_datasets_that_cannot_train_together_are_refused(bundled: Path, two_formats: tuple[Path, Path, Path],
                                                         tmp_path: Path) -> None:
    eth, apo, _ = two_formats
    with pytest.raises(DatasetError, match="no log in split 'nope/train'") as err:
        logpipe.train([eth, apo], out=tmp_path / "r1", train_split="nope/train", val_split="none")
    assert str(eth) in str(err.value) and str(apo) in str(err.value)
    six = tmp_path / "apo6"
    _ingest([str(bundled / "apolloscape"), "--out", str(six)])  # ApolloScape's own 6 + 6 steps
    with pytest.raises(LogpipeError, match=r"apo6: samples of 6\+6 steps"):
        logpipe.train([eth, six], out=tmp_path / "r2", train_split="all", val_split="none")
    with pytest.raises(LogpipeError, match="given twice"):
        logpipe.train([eth, eth], out=tmp_path / "r3", train_split="all", val_split="none")
    assert not any((tmp_path / name).exists() for name in ("r1", "r2", "r3"))


def test_every_dataset_needs_the_same_raster_run_for_the_environment_net(bundled: Path, tmp_path: Path) -> None:
    maps = bundled / "maps"
    a, b = tmp_path / "a", tmp_path / "b"
    _ingest([str(maps / "2645.csv"), "--out", str(a)])
    _ingest([str(maps / "3861.csv"), "--out", str(b)])
    mia = f"MIA={maps / 'MIA_lane_centerlines_crop_2645.npz'}"
    pit = f"PIT={maps / 'PIT_lane_centerlines_crop_3861.npz'}"

    def rasterise(folder: Path, *extra: str) -> str:
        result = runner.invoke(app, ["rasterise", str(folder), "--map", mia, "--map", pit, *extra, "--json"])
        assert result.exit_code == 0, result.output
        return str(json.loads(result.stdout)["run_id"])

    config = tmp_path / "c.toml"
    config.write_text(CONFIG)
    run = rasterise(a, "--rotate")
    with pytest.raises(LogpipeError, match=f"^{b}: no raster run, but {a} has one"):
        logpipe.train([a, b], out=tmp_path / "r1", config=config, train_split="all", val_split="none")
    assert rasterise(b) != run  # not rotated: another run
    with pytest.raises(LogpipeError, match="raster runs made with different settings"):
        logpipe.train([a, b], out=tmp_path / "r2", config=config, train_split="all", val_split="none")
    assert rasterise(b, "--rotate") == run  # b now holds both runs: --raster-run picks one in each dataset
    summary = logpipe.train([a, b], out=tmp_path / "r3", raster_run=run, config=config, train_split="all",
                            val_split="none")
    assert summary["environment_net"] is True and summary["raster_run"] == [run, run]
    meta = read_meta(Path(summary["last_checkpoint"]))
    assert meta.dataset_kind == "argoverse1"  # two datasets of one format: that format
    assert meta.manifest_hash == combined_manifest_hash([_sha256(a / "manifest.json"), _sha256(b / "manifest.json")])


def test_train_on_av1_and_av2_sliding_windows(shared: Path, bundled: Path, tmp_path: Path) -> None:
    av1, av2 = tmp_path / "av1", tmp_path / "av2"
    _ingest([str(bundled / "argoverse1"), "--out", str(av1), "--targets", "fully_observed_no_ego"])
    _ingest([str(shared / "av2"), "--out", str(av2), *AV2_SLIDING])
    config = tmp_path / "c.toml"
    config.write_text(CONFIG)
    summary = logpipe.train([av1, av2], out=tmp_path / "run", config=config, steps=2)
    per = summary["per_dataset"]
    assert [p["train_samples"] for p in per] == [_split_samples(av1, "hash/train"), _split_samples(av2, "hash/train")]
    assert per[1]["val_samples"] == _split_samples(av2, "hash/val")
    meta = read_meta(Path(summary["last_checkpoint"]))
    assert meta.dataset_kind == "argoverse1+argoverse2"
    assert meta.training_data is not None
    assert set(meta.training_data.train_sources) == _sources(av1, "hash/train") | _sources(av2, "hash/train")
    for root in (av1, av2):
        ds = Dataset.open(root)
        assert check_fit(ds, choose_predictor(ds, Path(summary["last_checkpoint"]), None), ds.logs()) == []


def test_kind_accepts_each_format_of_a_combined_kind_and_nothing_else() -> None:
    assert kind_accepts("argoverse1", "argoverse1") and not kind_accepts("argoverse1", "argoverse2")
    for kind in ("argoverse1", "argoverse2", "argoverse1+argoverse2"):
        assert kind_accepts("argoverse1+argoverse2", kind)
    for kind in ("argoverse", "ethucy", "argoverse1+", "argoverse2+argoverse1", ""):
        assert not kind_accepts("argoverse1+argoverse2", kind)
    assert not kind_accepts("argoverse1", "argoverse1+argoverse2")
    one, two = "a" * 64, "b" * 64
    assert combined_manifest_hash([one]) == one
    assert combined_manifest_hash([one, two]) != combined_manifest_hash([two, one])
