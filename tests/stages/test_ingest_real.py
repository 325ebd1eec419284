"""Ingest of the real Argoverse 1, ETH/UCY and ApolloScape files: exact row counts, roles, windows, times."""

from __future__ import annotations

import json
from decimal import Decimal
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
import pyarrow.parquet as pq
from jsonschema import Draft202012Validator
from mcap.reader import make_reader

from logpipe.contracts import arrow_schema, json_schema, tracks_schema
from logpipe.dataset.reader import Dataset
from logpipe.mcap.foxglove import MESSAGE_CLASSES
from logpipe.stages.index import reindex
from logpipe.stages.ingest import IngestOptions, ingest
from logpipe.types import PROTOCOLS


def data_lines(path: Path, header: int) -> int:
    return len([line for line in path.read_bytes().splitlines() if line.strip()]) - header


def test_argoverse1_real_files_keep_every_row_and_true_times(shared: Path, tmp_path: Path) -> None:
    src = shared / "argoverse1" / "data"
    summary = ingest([src], IngestOptions(out=tmp_path / "av1", batch_files=20, workers=2))
    expected_rows = sum(data_lines(p, 1) for p in src.glob("*.csv"))
    assert summary["rows"] == expected_rows == 61361
    assert summary["logs"] == summary["samples"] == 69
    ds = Dataset.open(tmp_path / "av1")
    assert len(ds.manifest["shards"]) == 4  # 69 files, 20 per shard
    tracks = ds.tracks()
    assert tracks.schema.names == tracks_schema().names
    roles = tracks.group_by("role").aggregate([("role", "count")]).to_pydict()
    assert dict(zip(roles["role"], roles["role_count"], strict=True)) == {"ego": 3450, "focal": 3450, "other": 54461}
    logs = ds.logs()
    cities = logs.column("map_id").to_pylist()
    assert cities.count("MIA") == 37 and cities.count("PIT") == 32
    # Exact decimal timestamps: compare one file with Decimal arithmetic on the CSV strings.
    text = (src / "2645.csv").read_text().splitlines()[1:]
    truth = sorted({int(Decimal(line.split(",")[0]) * 1_000_000_000) for line in text})
    got = np.unique(ds.log_tracks("2645").column("timestamp_ns").to_numpy())
    assert got.tolist() == truth
    for row in logs.to_pylist():
        times = np.unique(ds.log_tracks(row["log_id"]).column("timestamp_ns").to_numpy())
        assert row["median_dt_ns"] == int(np.median(np.diff(times)))
        assert (row["start_ns"], row["end_ns"], row["num_steps"]) == (times[0], times[-1], 50)
    samples = ds.samples()
    assert set(samples.column("current_step").to_pylist()) == {19}
    assert set(samples.column("end_step").to_pylist()) == {49}
    focal = tracks.filter(pc.equal(tracks.column("role"), "focal"))
    for row in samples.to_pylist()[:10]:
        agent = focal.filter(pc.equal(focal.column("log_id"), row["log_id"])).column("track_id")[0].as_py()
        assert row["target_track_ids"] == [agent] == [row["focal_track_id"]]
    irregular = sorted(samples.filter(pc.invert(samples.column("regular"))).column("log_id").to_pylist(), key=int)
    # The long-span files of the SOURCE note (10: 13 s, 16: 9 s, 14: 8.7 s ...) are flagged; 10 Hz files are not.
    assert {"10", "16", "14"} <= set(irregular)
    assert "2645" not in irregular and "1" not in irregular


SGAN_COUNTS = {  # scene, split -> (windows >= 2 peds, peds in them, windows >= 1 ped, peds), from SOURCE.md
    ("eth", "test"): (70, 181, 253, 364), ("eth", "train"): (2785, 29809, 3283, 30307),
    ("eth", "val"): (660, 5349, 733, 5422), ("hotel", "test"): (301, 1053, 445, 1197),
    ("hotel", "train"): (2594, 29152, 3118, 29676), ("hotel", "val"): (621, 5136, 688, 5203),
    ("univ", "test"): (947, 24334, 947, 24334), ("univ", "train"): (2076, 9231, 2719, 9874),
    ("univ", "val"): (530, 2708, 622, 2800), ("zara1", "test"): (602, 2253, 705, 2356),
    ("zara1", "train"): (2322, 28010, 2889, 28577), ("zara1", "val"): (605, 5118, 671, 5184),
    ("zara2", "test"): (921, 5833, 998, 5910),
}


def _counts_by_membership(ds: Dataset, scene: str, split: str) -> tuple[int, int]:
    logs = ds.logs()
    member = [f"{scene}/{split}" in m for m in logs.column("memberships").to_pylist()]
    ids = set(np.array(logs.column("log_id").to_pylist())[member].tolist())
    samples = ds.samples()
    samples = samples.filter(pc.is_in(samples.column("log_id"), value_set=pa.array(sorted(ids))))
    return samples.num_rows, sum(len(t) for t in samples.column("target_track_ids").to_pylist())


def test_ethucy_leave_one_scene_out_windows_match_social_gan(shared: Path, tmp_path: Path) -> None:
    src = shared / "ethucy"
    out = tmp_path / "ethucy"
    summary = ingest([src], IngestOptions(out=out, write_mcap=False))
    unique = {}
    for p in src.rglob("*.txt"):
        unique[p.read_bytes()] = p
    assert summary["rows"] == sum(data_lines(p, 0) for p in unique.values())
    assert summary["logs"] == len(unique)  # identical copies under several scenes are one log
    ds = Dataset.open(out)
    hotel_train = ds.logs().filter(pc.equal(ds.logs().column("log_id"), "biwi_hotel_train")).to_pylist()[0]
    assert hotel_train["memberships"] == ["eth/train", "univ/train", "zara1/train", "zara2/train"]
    for (scene, split), (_, _, windows, peds) in SGAN_COUNTS.items():
        assert _counts_by_membership(ds, scene, split) == (windows, peds), (scene, split)
    reindex(out, PROTOCOLS["ethucy"].__class__(**{**PROTOCOLS["ethucy"].to_dict(), "min_targets": 2}))
    ds = Dataset.open(out)
    for (scene, split), (windows, peds, _, _) in SGAN_COUNTS.items():
        assert _counts_by_membership(ds, scene, split) == (windows, peds), (scene, split)


def test_apolloscape_real_files_types_and_reappearing_ids(shared: Path, tmp_path: Path) -> None:
    src = shared / "apolloscape"
    summary = ingest([src], IngestOptions(out=tmp_path / "apollo", write_mcap=False))
    assert summary["rows"] == 71197 and summary["logs"] == 53
    tracks = Dataset.open(tmp_path / "apollo").tracks()
    by_code = tracks.group_by("source_type").aggregate([("source_type", "count")]).to_pydict()
    assert dict(zip(by_code["source_type"], by_code["source_type_count"], strict=True)) == {
        "1": 25373, "2": 5572, "3": 18043, "4": 11417, "5": 10792}
    kinds = tracks.group_by("object_type").aggregate([("object_type", "count")]).to_pydict()
    assert dict(zip(kinds["object_type"], kinds["object_type_count"], strict=True))["bus_truck"] == 5572
    # 231 tracks disappear and reappear under the same id: their steps have gaps.
    steps = tracks.group_by(["log_id", "track_id"]).aggregate(
        [("step", "min"), ("step", "max"), ("step", "count")]).to_pydict()
    gaps = sum(hi - lo + 1 != n for lo, hi, n in zip(steps["step_min"], steps["step_max"], steps["step_count"],
                                                       strict=True))
    assert gaps == 231
    assert tracks.column("heading").null_count == 0


def test_bundled_samples_ingest_without_shared(bundled: Path, tmp_path: Path) -> None:
    for name, logs, rows in (("argoverse1", 6, None), ("ethucy", 3, None), ("apolloscape", 2, 846 + 200)):
        summary = ingest([bundled / name], IngestOptions(out=tmp_path / name))
        assert summary["logs"] == logs
        if rows is not None:
            assert summary["rows"] == rows
        assert summary["samples"] > 0


def test_mcap_channels_decode_and_validate(bundled: Path, tmp_path: Path) -> None:
    ingest([bundled / "argoverse1"], IngestOptions(out=tmp_path / "av1"))
    ds = Dataset.open(tmp_path / "av1")
    tracks = ds.log_tracks("2645")
    agents = Draft202012Validator(json_schema("logpipe.AgentStates"))
    counts: dict[str, int] = {}
    rows = entities = 0
    assert ds.mcap_path("2645") == tmp_path / "av1" / "mcap" / "part-00000" / "2645.mcap"
    with ds.mcap_path("2645").open("rb") as fh:
        for schema, channel, message in make_reader(fh).iter_messages():
            counts[channel.topic] = counts.get(channel.topic, 0) + 1
            if schema.name == "logpipe.AgentStates":
                data = json.loads(message.data)
                agents.validate(data)
                rows += len(data["track_id"])
                assert message.log_time == data["timestamp_ns"]
                continue
            # Foxglove channels: Protobuf, decoded by Foxglove's own classes (tests/mcap/test_foxglove.py checks more).
            assert (schema.encoding, channel.message_encoding) == ("protobuf", "protobuf")
            decoded = MESSAGE_CLASSES[schema.name].FromString(message.data)
            if schema.name == "foxglove.SceneUpdate":
                entities += len(decoded.entities)
    assert counts == {"/logpipe/agents": 50, "/logpipe/scene": 50, "/logpipe/ego_pose": 50, "/logpipe/tf": 51}
    assert rows == entities == tracks.num_rows


def test_rerun_skips_and_fresh_runs_are_byte_identical(bundled: Path, tmp_path: Path) -> None:
    first = ingest([bundled / "argoverse1"], IngestOptions(out=tmp_path / "a", batch_files=2))
    before = {p.name: p.stat().st_mtime_ns for p in (tmp_path / "a").iterdir()}
    again = ingest([bundled / "argoverse1"], IngestOptions(out=tmp_path / "a", batch_files=2))
    assert again["inputs_skipped_already_ingested"] == 6 and again["inputs_ingested"] == 0
    assert {p.name: p.stat().st_mtime_ns for p in (tmp_path / "a").iterdir()} == before
    ingest([bundled / "argoverse1"], IngestOptions(out=tmp_path / "b", batch_files=2, workers=2))
    for shard in first["shards_written"]:
        assert (tmp_path / "a" / shard).read_bytes() == (tmp_path / "b" / shard).read_bytes()
    assert (tmp_path / "a" / "manifest.json").read_bytes() == (tmp_path / "b" / "manifest.json").read_bytes()
    assert not list((tmp_path / "a").glob(".staging-*"))


def test_new_inputs_extend_an_existing_dataset(bundled: Path, tmp_path: Path) -> None:
    src = tmp_path / "src"
    src.mkdir()
    for p in sorted((bundled / "argoverse1").glob("*.csv"))[:3]:
        (src / p.name).write_bytes(p.read_bytes())
    ingest([src], IngestOptions(out=tmp_path / "ds"))
    for p in sorted((bundled / "argoverse1").glob("*.csv"))[3:]:
        (src / p.name).write_bytes(p.read_bytes())
    summary = ingest([src], IngestOptions(out=tmp_path / "ds"))
    assert summary["inputs_ingested"] == 3 and summary["inputs_skipped_already_ingested"] == 3
    ds = Dataset.open(tmp_path / "ds")
    assert [s["file"] for s in ds.manifest["shards"]] == ["tracks/part-00000.parquet", "tracks/part-00001.parquet"]
    assert ds.logs().num_rows == ds.samples().num_rows == 6


def test_written_tables_match_schema_files(bundled: Path, tmp_path: Path) -> None:
    ingest([bundled / "apolloscape"], IngestOptions(out=tmp_path / "ap"))
    ds = Dataset.open(tmp_path / "ap")
    files = {"tracks": ds.manifest["shards"][0]["file"], "logs": ds.manifest["tables"]["logs"]["file"],
             "samples": ds.manifest["tables"]["samples"]["file"]}
    for name, file in files.items():
        written = pq.read_schema(tmp_path / "ap" / file)
        expected = arrow_schema(name)
        assert [(f.name, f.type, f.nullable) for f in written] == [(f.name, f.type, f.nullable) for f in expected]


def test_scene_sample_cuts_the_window(bundled: Path, tmp_path: Path) -> None:
    ingest([bundled / "argoverse1"], IngestOptions(out=tmp_path / "av1"))
    ds = Dataset.open(tmp_path / "av1")
    sample = next(ds.iter_scene_samples())
    assert sample.positions.shape[1:] == (50, 2)
    assert sample.obs_len == 20 and sample.target_mask.sum() == 1 and sample.ego_index >= 0
    target = int(np.flatnonzero(sample.target_mask)[0])
    assert np.isfinite(sample.positions[target]).all()
    assert np.all(np.diff(sample.timestamps_ns) > 0)
