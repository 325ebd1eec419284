"""Constant-velocity ADE/FDE on real ETH/UCY data, checked against an independent computation: a plain
loop over the raw ``frame ped x y`` text file that shares no code with logpipe's dataset, sample index,
baselines or metrics."""

from __future__ import annotations

import math
import shutil
from pathlib import Path

import pytest

from logpipe.dataset.reader import Dataset
from logpipe.model.kinematic.constant_velocity import ConstantVelocity
from logpipe.prediction.runs import PredictionMeta
from logpipe.prediction.table import samples_table
from logpipe.stages.ingest import IngestOptions, ingest
from logpipe.stages.score import score
from logpipe.stages.train import scene_samples
from logpipe.storage.io import write_parquet

OBS, PRED = 8, 12

pytestmark = pytest.mark.shared


def _cv_by_hand(path: Path, min_peds: int) -> tuple[int, float, float]:
    """(agent-windows, mean ADE, mean FDE) of constant velocity under Social-GAN's windowing.

    Windows are 20 consecutive distinct frame ids of the file; a pedestrian counts when it has a row in all
    20; windows with fewer than ``min_peds`` such pedestrians are skipped. The forecast continues the last
    observed displacement; errors are Euclidean distances in metres.
    """
    tracks: dict[float, dict[float, tuple[float, float]]] = {}
    for line in path.read_text().splitlines():
        if not line.strip():
            continue
        frame, ped, x, y = (float(v) for v in line.split())
        tracks.setdefault(frame, {})[ped] = (x, y)
    frames = sorted(tracks)
    n = 0
    ade_sum = fde_sum = 0.0
    for start in range(len(frames) - (OBS + PRED) + 1):
        window = frames[start : start + OBS + PRED]
        peds = set(tracks[window[0]])
        for f in window[1:]:
            peds &= set(tracks[f])
        if len(peds) < min_peds:
            continue
        for ped in peds:
            (x0, y0), (x1, y1) = tracks[window[OBS - 2]][ped], tracks[window[OBS - 1]][ped]
            errors = []
            for k in range(1, PRED + 1):
                tx, ty = tracks[window[OBS - 1 + k]][ped]
                errors.append(math.hypot(x1 + k * (x1 - x0) - tx, y1 + k * (y1 - y0) - ty))
            ade_sum += sum(errors) / PRED
            fde_sum += errors[-1]
            n += 1
    return n, ade_sum / n, fde_sum / n


@pytest.mark.parametrize("scene,file", [("zara1", "crowds_zara01.txt"), ("eth", "biwi_eth.txt")])
def test_constant_velocity_matches_a_hand_loop_over_the_raw_file(shared: Path, tmp_path: Path, scene: str,
                                                                 file: str) -> None:
    shutil.copytree(shared / "ethucy" / scene / "test", tmp_path / "raw" / scene / "test")  # memberships from paths
    ingest([tmp_path / "raw"], IngestOptions(out=tmp_path / "ds", format="ethucy", write_mcap=False))
    ds = Dataset.open(tmp_path / "ds")
    samples = scene_samples(ds, f"{scene}/test")
    meta = PredictionMeta(predictor="cv", checkpoint_id="constant_velocity", protocol="ethucy", obs_len=OBS,
                          pred_len=PRED, num_modes=1)
    table = samples_table(meta, samples, ConstantVelocity(pred_len=PRED).predict(samples, 1, 0))
    write_parquet(table, tmp_path / "cv.parquet")
    for min_peds in (1, 2):
        n, ade, fde = _cv_by_hand(shared / "ethucy" / scene / "test" / file, min_peds)
        report = score([tmp_path / "cv.parquet"], ds.root, tmp_path / f"r{min_peds}", split=f"{scene}/test",
                       min_agents=min_peds, plots=False)
        o = report["methods"]["cv"]["overall"]
        assert o["agents"] == n
        assert o["k1"]["ade"] == pytest.approx(ade, rel=1e-9)
        assert o["k1"]["fde"] == pytest.approx(fde, rel=1e-9)
    # Social-GAN-literal test sizes quoted by others (google/next-prediction#42): ETH 181, ZARA1 2253.
    assert _cv_by_hand(shared / "ethucy" / scene / "test" / file, 2)[0] == {"zara1": 2253, "eth": 181}[scene]
