"""``LogWindows.of_logs`` (a shard's columns converted once, each log a view of them) cuts the same samples as a
``LogWindows`` of the log's own rows, on shards ingest writes from the bundled ETH/UCY files (several logs of one
shard share track ids) and Argoverse 1 CSVs (real files)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pyarrow as pa
import pytest

from logpipe.dataset.reader import Dataset
from logpipe.dataset.shards import log_slices
from logpipe.dataset.windows import LogWindows
from logpipe.prediction.model_inputs import log_windows
from logpipe.stages.ingest import IngestOptions, ingest
from logpipe.storage.io import read_table

BUNDLED = Path(__file__).resolve().parents[1] / "data"


@pytest.fixture(scope="module", params=["ethucy", "argoverse1"])
def dataset(request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory) -> Dataset:
    out = tmp_path_factory.mktemp("windows") / request.param
    ingest([BUNDLED / request.param], IngestOptions(out=out, write_mcap=False, workers=1))
    return Dataset.open(out)


def test_views_of_a_shard_cut_the_samples_of_each_logs_own_rows(dataset: Dataset) -> None:
    rows_by_log: dict[str, list[dict[str, object]]] = {}
    for row in dataset.samples().to_pylist():
        rows_by_log.setdefault(str(row["log_id"]), []).append(row)
    checked = shared_ids = 0
    for path in dataset.shard_paths:
        shard = LogWindows.of_logs(read_table(path))
        assert list(shard) == list(log_slices(read_table(path)))
        ids = [set(w.track_ids()) for w in shard.values()]
        shared_ids += sum(len(a & b) for i, a in enumerate(ids) for b in ids[i + 1 :])
        for log_id, viewed in shard.items():
            own = LogWindows(dataset.log_tracks(log_id))
            assert viewed.track_ids() == own.track_ids()
            for row in rows_by_log.get(log_id, []):
                a, b = viewed.sample(row, dataset.protocol.obs_len), own.sample(row, dataset.protocol.obs_len)
                assert a.track_ids == b.track_ids and a.ego_index == b.ego_index
                np.testing.assert_array_equal(a.positions, b.positions)  # NaN where unobserved, bit for bit
                np.testing.assert_array_equal(a.timestamps_ns, b.timestamps_ns)
                np.testing.assert_array_equal(a.object_types, b.object_types)
                np.testing.assert_array_equal(a.target_mask, b.target_mask)
                assert a.target_mask.any()
                checked += 1
    assert checked == dataset.samples().num_rows > 0
    assert shared_ids > 0  # the case a shard-wide track numbering must survive


def test_a_log_id_dictionary_repeating_a_value_gives_one_run_per_log(dataset: Dataset) -> None:
    table = read_table(dataset.shard_paths[0])
    ids = table.column("log_id").combine_chunks()
    names = ids.to_pylist()
    # Every row its own dictionary entry: the values repeat, the codes never do.
    repeated = pa.DictionaryArray.from_arrays(pa.array(np.arange(len(names), dtype=np.int32)), pa.array(names))
    as_dictionary = table.set_column(table.schema.get_field_index("log_id"), "log_id", repeated)
    assert log_slices(as_dictionary) == log_slices(table)


def test_log_windows_gives_the_asked_logs_of_a_shard_in_the_asked_order(dataset: Dataset) -> None:
    table = read_table(dataset.shard_paths[0])
    ids = list(log_slices(table))
    assert len(ids) >= 3
    assert [log_id for log_id, _ in log_windows(table, ids[::-1])] == ids[::-1]
    # A few logs of the shard: only their rows are converted, and they cut what the log's own rows cut.
    picked = dict(log_windows(table, [ids[-1], "absent", ids[0]]))
    assert list(picked) == [ids[-1], ids[0]]
    row = next(r for r in dataset.samples().to_pylist() if r["log_id"] == ids[-1])
    a = picked[ids[-1]].sample(row, dataset.protocol.obs_len)
    b = LogWindows(dataset.log_tracks(ids[-1])).sample(row, dataset.protocol.obs_len)
    assert a.track_ids == b.track_ids
    np.testing.assert_array_equal(a.positions, b.positions)
    assert list(log_windows(table, ["absent"])) == []
