"""The ``fully_observed_no_ego`` target rule (issue 33): every fully observed track but the AV, whose future is
the model's planned-trajectory input (ETF). The presets keep their own rules."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path
from typing import Any

import pyarrow.parquet as pq
import pytest

from logpipe.dataset.reader import Dataset
from logpipe.stages.ingest import IngestOptions, ingest
from logpipe.types import PROTOCOLS, SampleProtocol

AV = "00000000-0000-0000-0000-000000000000"


def _targets(root: Path) -> list[list[str]]:
    return [list(r) for r in pq.read_table(root / "samples").column("target_track_ids").to_pylist()]


def _full_tracks(csv: Path) -> set[str]:
    import pandas as pd

    frame = pd.read_csv(csv)
    per_track = frame.groupby("TRACK_ID")["TIMESTAMP"].nunique()
    return set(per_track[per_track == 50].index)


def test_no_ego_rule_drops_only_the_av(bundled: Path, tmp_path: Path) -> None:
    av1 = replace(PROTOCOLS["argoverse"], name="argoverse-custom")

    def run(out: Path, targets: str) -> Any:
        options = IngestOptions(out=out, workers=1, write_mcap=False, protocol=replace(av1, targets=targets))
        return ingest([bundled / "argoverse1"], options)

    all_full, no_ego = run(tmp_path / "a", "fully_observed"), run(tmp_path / "b", "fully_observed_no_ego")
    assert all_full["samples"] == no_ego["samples"] == 6
    with_av, without = _targets(tmp_path / "a"), _targets(tmp_path / "b")
    for a, b in zip(with_av, without, strict=True):
        assert AV in a and AV not in b
        assert sorted(set(a) - {AV}) == sorted(b)
    expected = sum(len(_full_tracks(p) - {AV}) for p in sorted((bundled / "argoverse1").glob("*.csv")))
    assert sum(map(len, without)) == expected
    # The AV stays in the scene as the ego (EMF and ETF read it), just not as a target.
    sample = next(Dataset.open(tmp_path / "b").iter_scene_samples())
    assert sample.ego_index >= 0 and not sample.target_mask[sample.ego_index]
    assert sample.target_mask.sum() > 1


def test_no_ego_rule_in_sliding_windows(bundled: Path, tmp_path: Path) -> None:
    # Sliding windows over the same CSVs (the path the AV2 sensor logs take).
    proto = replace(PROTOCOLS["rosbag"], name="custom", stride=5, targets="fully_observed_no_ego")
    ingest([bundled / "argoverse1"], IngestOptions(out=tmp_path / "s", workers=1, write_mcap=False, protocol=proto))
    targets = _targets(tmp_path / "s")
    assert targets and all(AV not in t for t in targets)


@pytest.mark.parametrize("name", sorted(PROTOCOLS))
def test_presets_keep_their_rule(name: str) -> None:
    # Shipped checkpoints and results were built with these; the new rule is opt-in only.
    assert PROTOCOLS[name].targets == ("focal" if name.startswith("argoverse") else "fully_observed")


def test_target_types_keep_only_those_classes(bundled: Path, tmp_path: Path) -> None:
    # AV1 labels only the AV and the AGENT as vehicles (OTHERS are "unknown"): vehicles but the ego = the AGENT.
    proto = replace(PROTOCOLS["argoverse"], name="argoverse-custom", targets="fully_observed_no_ego",
                    target_types=("vehicle",))
    ingest([bundled / "argoverse1"], IngestOptions(out=tmp_path / "v", workers=1, write_mcap=False, protocol=proto))
    focal = pq.read_table(tmp_path / "v" / "samples").column("focal_track_id").to_pylist()
    assert _targets(tmp_path / "v") == [[f] for f in focal]
    # The manifest round-trips the rule (a JSON list back to a tuple).
    assert Dataset.open(tmp_path / "v").protocol == proto


def test_target_types_stay_out_of_preset_manifests() -> None:
    for proto in PROTOCOLS.values():
        assert "target_types" not in proto.to_dict()
        assert SampleProtocol(**proto.to_dict()) == proto


@pytest.mark.shared
def test_av2_sliding_windows_of_vehicles(shared: Path, tmp_path: Path) -> None:
    # The AV2 scenario and sensor logs as 20 + 30-step windows every second (issue 33 item 1).
    proto = replace(PROTOCOLS["rosbag"], name="custom", targets="fully_observed_no_ego", target_types=("vehicle",))
    summary = ingest([shared / "av2"], IngestOptions(out=tmp_path / "av2", workers=1, write_mcap=False,
                                                     protocol=proto))
    assert summary["samples"] == 51
    tracks = pq.read_table(tmp_path / "av2" / "tracks", columns=["log_id", "track_id", "object_type", "role"])
    kind = {(r["log_id"], r["track_id"]): (r["object_type"], r["role"]) for r in tracks.to_pylist()}
    rows = pq.read_table(tmp_path / "av2" / "samples").to_pylist()
    labels = {kind[(r["log_id"], t)] for r in rows for t in r["target_track_ids"]}
    assert {k for k, _ in labels} == {"vehicle"} and ("vehicle", "ego") not in labels
