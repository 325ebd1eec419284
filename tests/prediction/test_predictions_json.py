"""The ``logpipe.Predictions`` JSON of forecasts whose modes are one broadcast mode (constant velocity) is the same
text as orjson writes for the full array, each mode formatted once."""

from __future__ import annotations

import numpy as np
import pytest

from logpipe.mcap.forecast_scene import TargetForecasts
from logpipe.prediction.mcap_logs import array_json, dumps


@pytest.mark.parametrize(("targets", "modes", "steps"), [(7, 20, 12), (1, 3, 1), (0, 6, 12), (4, 2, 0)])
def test_broadcast_modes_write_the_same_json_as_the_full_array(targets: int, modes: int, steps: int) -> None:
    rng = np.random.default_rng(targets * 100 + modes)
    one = rng.normal(size=(targets, 1, steps, 2)) * 10.0 ** rng.integers(-6, 6, size=(targets, 1, steps, 2))
    one[rng.random(one.shape) < 0.1] = np.nan  # orjson writes null; so must the repeated text
    futures = np.broadcast_to(one, (targets, modes, steps, 2))
    forecasts = TargetForecasts([], [0], [], [], np.zeros((targets, 1, 2)), np.zeros((targets, 0, 2)), futures,
                                np.zeros((targets, modes))).with_columns()
    columns = forecasts.arrays()
    assert columns["x"].strides[1] == 0  # stays broadcast: one mode copied, not K
    for axis in ("x", "y"):
        full = np.ascontiguousarray(futures[..., "xy".index(axis)])
        assert dumps({axis: array_json(columns[axis])}) == dumps({axis: full})
        # A sample's rows (``TargetForecasts.part``) keep the broadcast and the equality.
        half = forecasts.columns[axis][targets // 2 :] if forecasts.columns else None
        assert half is not None
        assert dumps(array_json(half)) == dumps(np.ascontiguousarray(full[targets // 2 :]))


def test_arrays_that_are_not_broadcast_pass_through() -> None:
    values = np.arange(24, dtype=np.float64).reshape(2, 3, 4)
    assert array_json(values) is values
    single = np.broadcast_to(np.ones((2, 1, 4)), (2, 1, 4))
    assert array_json(single) is single
