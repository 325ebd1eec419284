"""Split expressions of ``Dataset.logs_in_split`` on the bundled ETH/UCY sample (real Social-GAN files)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from logpipe.dataset.locations import track_sharing_groups
from logpipe.dataset.reader import HASH_SPLITS, Dataset, DatasetError, hash_fraction
from logpipe.stages.ingest import IngestOptions, ingest

BUNDLED = Path(__file__).resolve().parents[1] / "data"


@pytest.fixture(scope="module")
def dataset(tmp_path_factory: pytest.TempPathFactory) -> Dataset:
    out = tmp_path_factory.mktemp("splits") / "e"
    ingest([BUNDLED / "ethucy"], IngestOptions(out=out, write_mcap=False))
    return Dataset.open(out)


def test_plain_terms(dataset: Dataset) -> None:
    assert dataset.logs_in_split("eth/train") == ["crowds_zara01_train"]
    assert dataset.logs_in_split("hotel/test") == ["biwi_hotel"]
    assert dataset.logs_in_split("biwi_eth") == ["biwi_eth"]  # a log id is a term too
    assert sorted(dataset.logs_in_split("all")) == ["biwi_eth", "biwi_hotel", "crowds_zara01_train"]


def test_union_and_difference_read_left_to_right_in_log_table_order(dataset: Dataset) -> None:
    everything = dataset.logs_in_split("all")
    union = dataset.logs_in_split("biwi_hotel+biwi_eth")
    assert union == [i for i in everything if i in {"biwi_hotel", "biwi_eth"}]
    assert dataset.logs_in_split("all-eth/test") == [i for i in everything if i != "biwi_eth"]
    assert dataset.logs_in_split("all-eth/test-hotel/test") == ["crowds_zara01_train"]
    assert dataset.logs_in_split("eth/train-crowds_zara01_train+biwi_eth") == ["biwi_eth"]


def test_errors_name_the_term(dataset: Dataset) -> None:
    with pytest.raises(DatasetError, match=r"'nosuch' \(of 'eth/train-nosuch'\)"):
        dataset.logs_in_split("eth/train-nosuch")
    with pytest.raises(DatasetError, match="leaves no log"):
        dataset.logs_in_split("eth/train-crowds_zara01_train")
    with pytest.raises(DatasetError, match="no log in split 'eth/val'"):
        dataset.logs_in_split("eth/val")


def test_groups_are_joined_transitively_and_named_by_their_first_log() -> None:
    shares = '{"shared_tracks": {"%s": {}}}'
    ids = ["a", "b", "c", "d", "e"]
    attributes = [None, shares % "a", None, shares % "b", '{"shared_tracks": {"c": {}, "a": {}}}']
    groups = track_sharing_groups(ids, attributes)
    assert groups == {"a": "a", "b": "a", "c": "a", "d": "a", "e": "a"}
    assert track_sharing_groups(["x", "y"], ['{"location": "X"}', None]) == {"x": "x", "y": "y"}


def test_the_hash_split_keeps_real_recordings_that_share_tracks_together(tmp_path: Path, shared: Path) -> None:
    # USA_Peach-4_1 and 4_2 show some of the same cars; alone, 4_1 hashes into test and 4_2 into train.
    folder = shared / "commonroad" / "ngsim" / "USA_Peach"
    inputs = tmp_path / "in"
    inputs.mkdir()
    for name in ("USA_Peach-4_1_T-1.xml", "USA_Peach-4_2_T-1.xml", "USA_Peach-3_1_T-1.xml"):
        (inputs / name).write_bytes((folder / name).read_bytes())
    ingest([inputs], IngestOptions(out=tmp_path / "ds", write_mcap=False))
    ds = Dataset.open(tmp_path / "ds")
    first, later = "USA_Peach-4_1_T-1", "USA_Peach-4_2_T-1"
    assert first in json.loads(next(r["attributes"] for r in ds.logs().to_pylist() if r["log_id"] == later))[
        "shared_tracks"]
    own = {log: next(k for k, (lo, hi) in HASH_SPLITS.items() if lo <= hash_fraction(log) < hi)
           for log in (first, later)}
    assert own == {first: "test", later: "train"}  # what a split by log alone would do
    assert ds.logs_in_split("hash/test") == [first, later]
    assert ds.logs_in_split("hash/train") == ["USA_Peach-3_1_T-1"]
