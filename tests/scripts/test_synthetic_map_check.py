"""``scripts/synthetic_map_check.py``: the EN gain, its interval and how much of it the turning targets can carry."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from scripts.synthetic_map_check import TURN_DEG, _dilution, gain_interval


def test_gain_is_one_minus_the_ratio_of_summed_fde_and_its_interval_covers_it() -> None:
    rng = np.random.default_rng(0)
    base = rng.uniform(1.0, 3.0, 400)
    cluster = np.repeat(np.arange(100), 4)
    same = gain_interval(base.copy(), base, cluster)
    assert same["gain"] == 0.0 and same["low"] == 0.0 == same["high"]
    half = gain_interval(base * 0.5, base, cluster)
    assert abs(half["gain"] - 0.5) < 1e-12 and half["low"] <= 0.5 <= half["high"]
    noisy = gain_interval(base * rng.uniform(0.6, 1.0, 400), base, cluster)
    assert noisy["low"] < noisy["gain"] < noisy["high"] and noisy["windows"] == 100


def test_dilution_weighs_the_turning_gain_by_the_turning_share_of_the_error() -> None:
    def row(fde: float, agents: int) -> dict[str, float]:
        return {"minFDE": fde, "agents": agents}

    rows = {"all targets": {"no EN (v4)": row(2.5, 10)},
            f"turning > {TURN_DEG:g} deg": {"no EN (v4)": row(5.0, 2), "gain": {"gain": 0.2}}}
    text = _dilution(rows)  # turning: 10 of 25 summed metres; 20 % of that is 8 % of all
    assert "carry 40 %" in text and "would give 8.0 %" in text


def test_argoverse_md_shows_every_run_and_the_last_ones_verdict(tmp_path: Path) -> None:
    from scripts.reproduce_argoverse import SYNTHETIC_RUNS, synthetic_section

    assert "Not run yet" in synthetic_section(tmp_path)[-1]

    def row(full: float, base: float, gain: float, low: float) -> dict[str, Any]:
        return {"full": {"minFDE": full, "agents": 10}, "no EN (v4)": {"minFDE": base, "agents": 10},
                "gain": {"gain": gain, "low": low, "high": gain + 0.01}}

    def result(low: float) -> dict[str, Any]:
        return {"windows": 4000, "targets": 29702, "k": 6,
                "checkpoints": {"full": {"step": 3000}, "no EN (v4)": {"step": 2500}},
                "rows": {"all targets": row(2.0, 2.5, 0.2, low), "turning > 20 deg": row(4.0, 5.0, 0.3, 0.25)}}

    first, second = SYNTHETIC_RUNS[0][0], SYNTHETIC_RUNS[1][0]
    (tmp_path / f"{first}.json").write_text(json.dumps(result(0.16)))
    lines = synthetic_section(tmp_path)
    assert any(line.startswith(f"| [{first}]") and "| 2.00 / 2.50 | 20.0 % [16.0, 21.0] | 30.0 % [25.0, 31.0] | — |"
               in line for line in lines)
    assert any("**met**" in line for line in lines)  # the interval's low end clears 15 %
    (tmp_path / f"{second}.json").write_text(json.dumps(result(0.14)))
    lines = synthetic_section(tmp_path)
    assert [line.split(" |")[0] for line in lines if line.startswith("| [")] == [f"| [{first}]({first}.md)",
                                                                             f"| [{second}]({second}.md)"]
    assert any(f"`{second}`): **NOT met**" in line for line in lines)  # the later run gives the verdict
    assert lines[-1].endswith(f"({second}/fork.png)")
