"""The k-means reduction of scripts.subset_check on forecasts whose clusters are known."""

from __future__ import annotations

import numpy as np

from scripts.subset_check import farthest_points, kmeans_centres, reduced


def test_kmeans_finds_separated_clusters_per_row() -> None:
    rng = np.random.default_rng(0)
    centres = rng.uniform(-50, 50, size=(3, 4, 2))  # 3 rows, 4 clusters each, far apart
    members = rng.integers(0, 4, size=(3, 60))
    members[:, :4] = np.arange(4)  # every cluster has a member
    x = np.take_along_axis(centres, members[..., None], axis=1) + rng.normal(0, 0.01, size=(3, 60, 2))
    found = kmeans_centres(x, 4)
    for row in range(3):
        nearest = np.linalg.norm(found[row][:, None] - centres[row][None], axis=-1).min(axis=0)
        assert nearest.max() < 0.05  # every true centre has a found centre on it


def test_farthest_points_are_distinct_and_start_at_the_mean() -> None:
    x = np.array([[[10.0, 0.0], [0.5, 0.5], [-10.0, 0.0], [0.0, 9.0], [0.0, -9.0], [1.0, 0.0]]])
    pick = farthest_points(x, 4)[0]  # the mean is (0.25, 0.083)
    assert pick[0] == 1
    assert len(set(pick.tolist())) == 4
    assert set(pick[1:].tolist()) <= {0, 2, 3, 4}  # the far corners before the near point (1, 0)


def test_reduced_keeps_shape_and_a_lone_forecast() -> None:
    pred = np.zeros((2, 30, 12, 2))
    pred[:, 0] = 5.0  # one far-off sample: k-means must keep it as its own centre
    out = reduced(pred, 20)
    assert out.shape == (2, 20, 12, 2)
    assert np.any(np.all(np.isclose(out, 5.0), axis=(2, 3)), axis=1).all()
