"""The best kinematic baseline: each method's best setting on real training targets, the best of them, replayed."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from logpipe.dataset.reader import Dataset
from logpipe.model.kinematic import best_baseline
from logpipe.model.kinematic.adaptive_prior import adaptive_fit
from logpipe.model.kinematic.kalman import KalmanCV
from logpipe.stages.ingest import IngestOptions, ingest
from logpipe.stages.train import scene_samples

DATA = Path(__file__).resolve().parents[1] / "data" / "commonroad"


@pytest.fixture(scope="module")
def tracks(tmp_path_factory: pytest.TempPathFactory) -> tuple[np.ndarray, np.ndarray]:
    """(observed (N, 20, 2), future (N, 30, 2)) of every target of the bundled CommonRoad scenarios."""
    out = tmp_path_factory.mktemp("best") / "ds"
    ingest([DATA], IngestOptions(out=out, write_mcap=False))
    samples = scene_samples(Dataset.open(out), "all")
    rows = [s.positions[np.asarray(s.target_mask, bool)] for s in samples]
    both = np.concatenate(rows)
    return both[:, :20], both[:, 20:]


def test_each_method_gets_its_best_setting_and_the_best_method_wins(tracks: tuple[np.ndarray, np.ndarray]) -> None:
    observed, future = tracks
    per_method = best_baseline.choose_per_method(observed, future)
    assert set(per_method) == {"cv", "least_squares_cv", "kalman", "adaptive_prior"}
    errors = best_baseline.final_errors(observed, future)
    for method, record in per_method.items():
        mine = [float(e.mean()) for name, e in errors.items() if name.split("(")[0] == method]
        assert record["train_fde"] == pytest.approx(min(mine), abs=1e-4)  # no setting of its grid does better
        replayed = best_baseline.forecast(record, observed, 30)
        fde = float(np.linalg.norm(replayed[:, -1] - future[:, -1], axis=-1).mean())
        assert fde == pytest.approx(record["train_fde"], abs=1e-4)
    best = best_baseline.choose(per_method)
    assert best["train_fde"] == min(r["train_fde"] for r in per_method.values())
    kalman = per_method["kalman"]
    np.testing.assert_allclose(best_baseline.forecast(kalman, observed, 30), KalmanCV(
        pred_len=30, accel_std=kalman["accel_std"], meas_std=kalman["meas_std"]).filter_tracks(observed))


def test_the_prior_candidates_include_the_models_own(tracks: tuple[np.ndarray, np.ndarray]) -> None:
    observed, _ = tracks
    own = {"method": "adaptive_prior", "horizon": 3, "backtest": 8}
    assert own in best_baseline.candidates(20)
    np.testing.assert_array_equal(best_baseline.forecast(own, observed, 30), adaptive_fit(observed).forecast(30))
    # windows longer than the observation are not candidates; neither are backtests that need more steps
    assert all(c.get("history", 0) <= 8 and c.get("backtest", 0) <= 6 for c in best_baseline.candidates(8))
    with pytest.raises(ValueError, match="unknown kinematic baseline"):
        best_baseline.forecast({"method": "magic"}, observed, 30)
