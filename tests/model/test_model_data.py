"""The DataLoader over shards yields exactly the samples of the in-memory path, split across workers."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from logpipe.dataset.reader import Dataset
from logpipe.model.training.scene_stream import scene_loader
from logpipe.stages.ingest import IngestOptions, ingest
from logpipe.stages.train import scene_samples

BUNDLED = Path(__file__).resolve().parents[1] / "data"


def test_loader_streams_the_same_samples_as_memory(tmp_path: Path) -> None:
    # Three shards so that two workers each read some of them.
    ingest([BUNDLED / "ethucy"], IngestOptions(out=tmp_path / "e", batch_files=1, write_mcap=False))
    dataset = Dataset.open(tmp_path / "e")
    assert len(dataset.shard_paths) == 3
    in_memory = {s.sample_id: s for s in scene_samples(dataset, "eth/train")}
    streamed = list(scene_loader(dataset.root, dataset.logs_in_split("eth/train"), workers=2))
    assert sorted(s.sample_id for s in streamed) == sorted(in_memory)
    for sample in streamed[:50]:
        expected = in_memory[sample.sample_id]
        np.testing.assert_array_equal(sample.positions, expected.positions)
        assert isinstance(sample.positions, np.ndarray) and sample.track_ids == expected.track_ids
    again = list(scene_loader(dataset.root, dataset.logs_in_split("eth/train"), workers=2))
    assert len(again) == len(streamed)  # re-iterable, one pass per epoch
