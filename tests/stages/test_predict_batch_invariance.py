"""A forecast depends only on (checkpoint, settings, seed, sample): ``logpipe predict`` writes the same predictions,
bit for bit, at any ``--batch-size`` (issue 35 item 2; how: ``logpipe.model.training.row_blocks``), with the shipped
networks on real data: ETH/UCY without maps, and the driving model over AV1 lane rasters with its environment net."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from logpipe.dataset.reader import Dataset
from logpipe.dataset.sample_filter import parse_filter
from logpipe.model.zhu2020.predictor import NetPredictor
from logpipe.stages.ingest import IngestOptions, ingest
from logpipe.stages.predict import predict_dataset

DATA = Path(__file__).resolve().parents[1] / "data"
ETH_CHECKPOINT = Path(__file__).resolve().parents[2] / "model" / "checkpoints" / "ethucy" / "eth"


def _table(out: Path) -> pa.Table:
    return pa.concat_tables(pq.read_table(p) for p in sorted((out / "predictions").glob("*.parquet")))


def _same_at_every_batch_size(dataset: Path, tmp_path: Path, sizes: tuple[int, ...], **settings: object) -> int:
    tables = [_table(_predicted(dataset, tmp_path / f"b{size}", size, **settings)) for size in sizes]
    for size, table in zip(sizes[1:], tables[1:], strict=True):
        assert table.equals(tables[0]), f"batch size {size} changed the forecasts of batch size {sizes[0]}"
    return tables[0].num_rows


def _predicted(dataset: Path, out: Path, batch_size: int, **settings: object) -> Path:
    predict_dataset(dataset, out, batch_size=batch_size, write_mcap=False, threads=1, **settings)
    return out


@pytest.mark.slow
def test_eth_forecasts_do_not_depend_on_the_batch(tmp_path: Path) -> None:
    # The checkpoint's own test scene (253 samples, single- and multi-agent): the whole bundle took 3 minutes of the
    # suite at batch size 1 and exercises the same kernels.
    ingest([DATA / "ethucy"], IngestOptions(out=tmp_path / "eth"))
    rows = _same_at_every_batch_size(tmp_path / "eth", tmp_path, (1, 3, 64), checkpoint=ETH_CHECKPOINT,
                                     sample_filter=parse_filter(["split=eth/test"]))
    assert rows > 7000


def test_driving_forecasts_over_rasters_do_not_depend_on_the_batch(driving_rasterised: Path, tmp_path: Path) -> None:
    assert _same_at_every_batch_size(driving_rasterised, tmp_path, (1, 2)) > 0


@pytest.mark.parametrize("alone_index", [0, 5])
def test_a_sample_alone_and_among_others_gets_the_same_bits(alone_index: int) -> None:
    """The network itself: each sample alone against all of them in one batch (single- and multi-agent ones)."""
    import tempfile

    with tempfile.TemporaryDirectory() as tmp:
        ingest([DATA / "ethucy"], IngestOptions(out=Path(tmp) / "eth"))
        samples = list(Dataset.open(Path(tmp) / "eth").iter_scene_samples())[:24]
    net = NetPredictor.from_checkpoint(ETH_CHECKPOINT)
    together = net.predict(samples, 20, seed=0)
    for i in range(alone_index, len(samples), 5):
        alone = net.predict([samples[i]], 20, seed=0)[0]
        np.testing.assert_array_equal(alone, together[i])
