"""``scripts/synthetic_av2_rasters.py``: AV2 lanes converted to lanelets draw nearly the same lane channels as the
real map JSON, and a drivable area that misses what only the AV2 drivable polygons cover."""

from __future__ import annotations

from pathlib import Path

import pytest

from scripts.synthetic_av2_rasters import compare


@pytest.mark.shared
def test_lanelet_conversion_keeps_the_lanes(shared: Path) -> None:
    folder = shared / "av2" / "sensor_logs" / "adcf7d18-0510-35b0-a2fa-b4cea13a6d76" / "map"
    path = next(folder.glob("log_map_*.json"))
    result = compare(path, every=400)
    iou = result["iou"]
    assert isinstance(iou, dict) and result["windows"] >= 10
    assert min(iou[c] for c in ("lane_up", "lane_left", "lane_down", "lane_right")) > 0.9
    assert iou["lane_boundary"] > 0.95
    assert 0.5 < iou["drivable_area"] < 0.95  # the real polygons cover more than the lanes: the one real loss
