"""The learning curve's data selection (``scripts/driving_curve.py``): the test half of US-101 is never trained on,
``same:N`` adds exactly N further US-101 clusters, ``other:F`` keeps a share of the other locations and no US-101."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pytest

from scripts.driving_curve import HELD, held_clusters, training_rows
from scripts.driving_targets import VAL_SHARE, hash_fraction


@dataclass
class _Targets:
    """The three things the selection reads of ``driving_targets.Targets``."""

    location: np.ndarray
    cluster: np.ndarray

    def validation(self) -> np.ndarray:
        return np.array([hash_fraction(f"val:{c}") < VAL_SHARE for c in self.cluster])


@pytest.fixture
def targets() -> _Targets:
    locations = [HELD] * 24 + ["AV2"] * 40 + ["USA_Lanker"] * 40
    clusters = [f"{loc}:{i // 2}" for i, loc in enumerate(locations)]  # two targets per cluster
    return _Targets(np.array(locations), np.array(clusters))


def test_the_test_half_is_never_trained_on(targets: _Targets) -> None:
    test, addable = held_clusters(targets)  # type: ignore[arg-type]
    val = set(targets.cluster[targets.validation()])
    assert test and addable and not set(test) & set(addable) and not (set(test) | set(addable)) & val
    assert len(test) == (len(test) + len(addable)) // 2
    for point in ("same:0", "same:1", "same:all", "other:0.5"):
        rows = training_rows(targets, point, addable)  # type: ignore[arg-type]
        assert not set(targets.cluster[rows]) & (set(test) | val), point


def test_each_point_adds_what_it_names(targets: _Targets) -> None:
    _, addable = held_clusters(targets)  # type: ignore[arg-type]
    others = set(training_rows(targets, "same:0", addable).tolist())  # type: ignore[arg-type]
    assert all(targets.location[i] != HELD for i in others)
    two = training_rows(targets, "same:2", addable)  # type: ignore[arg-type]
    assert set(targets.cluster[two]) - set(targets.cluster[list(others)]) == set(addable[:2])
    half = training_rows(targets, "other:0.5", addable)  # type: ignore[arg-type]
    assert set(half.tolist()) < others and HELD not in set(targets.location[half])
