"""Av2Adapter on the real AV2 scenario and sensor logs (figures from ../shared/data/av2/SOURCE.md)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import pyarrow.parquet as pq
import pytest

from logpipe.errors import SourceError
from logpipe.formats.av2 import Av2Adapter
from logpipe.types import PROTOCOLS, SourceFile

AV2 = Path(__file__).resolve().parents[2].parent / "shared" / "data" / "av2"
pytestmark = [pytest.mark.shared, pytest.mark.skipif(not AV2.is_dir(), reason="needs ../shared/data/av2")]
SCENARIO = "0a1e6f0a-1817-4a98-b02e-db8c9327d151"


def src(path: Path) -> SourceFile:
    return SourceFile(str(path), path.name, "0" * 64, 0)


def read(path: Path) -> tuple[pd.DataFrame, dict[str, object], str | None]:
    parsed = Av2Adapter().read([src(path)], keep_going=False)
    return parsed.tracks.to_pandas(), parsed.logs[0].attributes, parsed.logs[0].map_id


def test_scenario() -> None:
    df, attrs, city = read(AV2 / f"scenario_{SCENARIO}.parquet")
    assert Av2Adapter.default_protocol == PROTOCOLS["argoverse2"]
    assert len(df) == 2434 and df.track_id.nunique() == 58 and set(df.log_id) == {SCENARIO}
    assert city == "austin"
    times = np.sort(df.timestamp_ns.unique())
    assert len(times) == 110 and np.all(np.diff(times) == 100_000_000)
    assert times[0] == 315986559459579000  # start_timestamp, without float64 noise
    roles = df.groupby("track_id").role.agg(set)
    assert roles["138951"] == {"focal"} and roles["AV"] == {"ego"}
    assert (df.role == "focal").sum() == 110 and (df.role == "ego").sum() == 110
    assert attrs["focal_track_id"] == "138951" and attrs["observed_steps"] == 50
    counts = df.object_type.value_counts().to_dict()
    assert counts == {"vehicle": 1774, "pedestrian": 329, "unknown": 167 + 142 + 22}
    assert set(df[df.object_type == "unknown"].source_type) == {"static", "riderless_bicycle", "background"}
    focal = df[df.role == "focal"]
    assert focal.x.between(-425.3, -421.7).all() and focal.y.between(1413.5, 1447.5).all()
    assert df.vx.notna().all() and df.heading.notna().all()


@pytest.mark.parametrize(
    ("log", "city", "tracks", "sweeps", "ego_x", "ego_y"),
    [
        ("adcf7d18-0510-35b0-a2fa-b4cea13a6d76", "PIT", 146, 156, (1468.9, 1506.7), (211.5, 225.5)),
        ("7fab2350-7eaf-3b7e-a39d-6937a4c1bede", "PIT", 114, 156, (5172.7, 5236.3), (2384.0, 2419.1)),
        ("3bffdcff-c3a7-38b6-a0f2-64196d130958", "PIT", 115, 156, (5007.2, 5090.9), (2466.2, 2482.9)),
        ("3b3570b4-7b0b-3268-a571-b0889dbf40b6", "MIA", 119, 157, (711.0, 744.0), (2231.4, 2256.1)),
    ],
)
def test_sensor_logs(log: str, city: str, tracks: int, sweeps: int, ego_x: tuple[float, float],
                     ego_y: tuple[float, float]) -> None:  # fmt: skip
    df, attrs, map_id = read(AV2 / "sensor_logs" / log)
    assert map_id == city and attrs["sweeps"] == sweeps
    ego = df[df.role == "ego"]
    assert len(ego) == sweeps and set(ego.track_id) == {"ego"}
    with_ego = attrs["annotations_file"] == "annotations_with_ego.feather"
    assert ego.length.notna().all() if with_ego else ego.length.isna().all()  # size from the EGO_VEHICLE boxes
    # SOURCE.md gives the range of all ~170 Hz poses; the sweeps (10 Hz, 15.5 of 15.9 s) sample most of it
    for col, (lo, hi) in (("x", ego_x), ("y", ego_y)):
        assert lo - 0.1 <= ego[col].min() and ego[col].max() <= hi + 0.1
        assert ego[col].max() - ego[col].min() > 0.8 * (hi - lo)
    others = df[df.role == "other"]
    assert others.track_id.nunique() == tracks and "EGO_VEHICLE" not in set(others.source_type)
    # every box is at a sweep time, where the ego has a row
    assert set(others.timestamp_ns) <= set(ego.timestamp_ns)
    # boxes were in the ego frame: once in the city frame, static objects stand still while the ego drives
    static = others[others.source_type.isin(["BOLLARD", "CONSTRUCTION_CONE", "SIGN"])]
    spread = static.groupby("track_id")[["x", "y"]].agg(lambda v: v.max() - v.min()).max(axis=1)
    assert len(spread) > 0 and spread.median() < 0.3
    raw = pd.read_feather(next((AV2 / "sensor_logs" / log).glob("annotations*.feather")))
    raw_spread = raw[raw.track_uuid.isin(spread.index)].groupby("track_uuid").tx_m.agg(lambda v: v.max() - v.min())
    assert raw_spread.median() > 3.0  # ... although they moved by metres in the ego frame


def test_discover() -> None:
    found = Av2Adapter().discover(AV2)
    assert found[0].name == f"scenario_{SCENARIO}.parquet" and len(found) == 5


def test_bad_inputs(tmp_path: Path) -> None:
    table = pq.read_table(AV2 / f"scenario_{SCENARIO}.parquet")
    pq.write_table(table.drop_columns(["object_category"]), tmp_path / "scenario_x.parquet")
    with pytest.raises(SourceError) as info:
        Av2Adapter().read([src(tmp_path / "scenario_x.parquet")], keep_going=False)
    assert info.value.field == "object_category"
    data = (AV2 / f"scenario_{SCENARIO}.parquet").read_bytes()
    (tmp_path / "scenario_cut.parquet").write_bytes(data[: len(data) // 2])
    parsed = Av2Adapter().read([src(tmp_path / "scenario_cut.parquet"), src(AV2 / f"scenario_{SCENARIO}.parquet")],
                               keep_going=True)  # fmt: skip
    assert len(parsed.logs) == 1 and len(parsed.failures) == 1
    assert parsed.failures[0].file == "scenario_cut.parquet" and "not a readable parquet" in parsed.failures[0].reason
