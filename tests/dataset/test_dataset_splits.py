"""Split expressions of ``Dataset.logs_in_split`` on the bundled ETH/UCY sample (real Social-GAN files)."""

from __future__ import annotations

from pathlib import Path

import pytest

from logpipe.dataset.reader import Dataset, DatasetError
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
