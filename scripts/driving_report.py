"""``docs/results/driving_lolo.md`` from ``driving_lolo.json``: the leave-one-location-out tables with 95 %
bootstrap intervals over recording clusters, the turning targets, the EN comparison and the issue's criteria.

    python -m scripts.driving_report [--results docs/results/driving_lolo.json]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

import numpy as np

from logpipe.model.kinematic import best_baseline
from scripts.driving_targets import LOCATIONS
from scripts.locations import REPO

BOOTSTRAP = 2000
K1 = (("cv", "Constant velocity (last displacement)"),
      ("least_squares_cv", "Least-squares CV (window chosen on the training locations)"),
      ("kalman", "Kalman CV filter (noise chosen there)"),
      ("adaptive_prior", "Adaptive prior (its constants chosen there)"),
      ("model_prior", "The model's own prior (constants frozen since issue 57)"),
      ("best_kinematic", "**Best kinematic baseline** (the best of the four above on the training locations)"),
      ("no_en", "Residual model without EN, mean head (ours)"), ("full", "Residual model, full, mean head (ours)"),
      ("full_auto", "**Residual model, full, as `logpipe predict` runs it** (ours; physics at K = 1 on unseen roads)"))
K6 = (("cv_sampler", "CV sampler: mode 0 = CV, 5 draws, noise chosen on the training locations"),
      ("no_en", "Residual model without EN (ours)"), ("full", "Residual model, full (ours)"),
      ("full_auto", "**Residual model, full, as `logpipe predict` runs it** (ours: mode 0 physics, then its modes)"))
MINE = ("full", "no_en", "full_auto")


class Resampler:
    """Stratified cluster bootstrap: per replicate, each location's recording clusters drawn with replacement."""

    def __init__(self, location: np.ndarray, cluster: np.ndarray, rows: np.ndarray, seed: int = 0) -> None:
        rng = np.random.default_rng(seed)
        groups = []
        for loc in np.unique(location[rows]):
            mine = rows[location[rows] == loc]
            groups.append([mine[cluster[mine] == c] for c in np.unique(cluster[mine])])
        self.draws = [np.concatenate([g[i] for g in groups for i in rng.integers(0, len(g), len(g))])
                      for _ in range(BOOTSTRAP)]

    def interval(self, statistic: Any) -> list[float]:
        """2.5 and 97.5 percentiles of ``statistic(rows)`` over the replicates."""
        values = [statistic(d) for d in self.draws]
        return [float(np.percentile(values, 2.5)), float(np.percentile(values, 97.5))]


def _cell(v: np.ndarray, rows: np.ndarray, boot: Resampler | None) -> str:
    mean = float(np.nanmean(v[rows]))
    if boot is None:
        return f"{mean:.2f}"
    lo, hi = boot.interval(lambda r: float(np.nanmean(v[r])))
    return f"{mean:.2f} [{lo:.2f}, {hi:.2f}]"


def render(results: dict[str, Any]) -> str:
    """The markdown page."""
    pt = {k: np.asarray(v, np.float64) for k, v in results["per_target"].items()}
    location = np.asarray(results["location"])
    cluster = np.asarray(results["cluster"])
    turning = np.asarray(results["turning"], bool)
    held = [loc for loc in LOCATIONS if loc in results["folds"]]
    rows_all = np.flatnonzero(np.isin(location, held))
    boots = {loc: Resampler(location, cluster, np.flatnonzero(location == loc)) for loc in held}
    pooled = Resampler(location, cluster, rows_all)
    lines = ["# The residual driving model, leave one location out", "",
             _protocol(results), "", "## K = 1 (mode 0), FDE at 3 s in metres [95 % bootstrap over recordings]", "",
             "| method | pooled | " + " | ".join(held) + " |", "|---" * (len(held) + 2) + "|"]
    for key, label in K1:
        v = pt[f"{key}.fde"]
        cells = [_cell(v, rows_all, pooled if key in MINE else None)]
        cells += [_cell(v, np.flatnonzero(location == loc), boots[loc] if key in MINE else None) for loc in held]
        lines.append(f"| {label} | " + " | ".join(cells) + " |")
    lines += ["", "## K = 6 per agent, minFDE@6 in metres", "", "| method | pooled | turning (pooled) | "
              + " | ".join(held) + " |", "|---" * (len(held) + 3) + "|"]
    turn_rows = rows_all[turning[rows_all]]
    for key, label in K6:
        v = pt[f"{key}.min_fde"]
        mine = key in MINE
        cells = [_cell(v, rows_all, pooled if mine else None), _cell(v, turn_rows, None)]
        cells += [_cell(v, np.flatnonzero(location == loc), boots[loc] if mine else None) for loc in held]
        lines.append(f"| {label} | " + " | ".join(cells) + " |")
    lines += ["", "## The issue's criteria (the full model, pooled over the held-out locations)", ""]
    lines += _criteria(pt, location, held, rows_all, turning, pooled, turn_rows)
    lines += ["", "## Training cost", "", "| held-out location | variant | train targets | best epoch | core-hours |",
              "|---|---|---|---|---|"]
    total = 0.0
    for loc in held:
        for variant in ("full", "no_en"):
            cost = results["folds"][loc].get(variant)
            if cost:
                total += cost["core_hours"]
                lines.append(f"| {loc} | {variant} | {cost['train_targets']} | {cost['best_epoch']} | "
                             f"{cost['core_hours']:.2f} |")
    lines += ["", f"All runs: {total:.2f} core-hours.", "", "## Choices per fold (on the training locations)", "",
              "| held-out location | best kinematic baseline | least-squares CV | Kalman | adaptive prior | CV sampler "
              "(heading rad, speed) | fallback of the fold model (its training clusters) |",
              "|---|---|---|---|---|---|---|"]
    for loc in held:
        chosen = results["folds"][loc]["chosen_on_training_locations"]
        per = chosen["baselines"]
        sampler = chosen["cv_sampler"]
        lines.append(f"| {loc} | {_label(chosen['best_kinematic'])} | {_label(per['least_squares_cv'])} | "
                     f"{_label(per['kalman'])} | {_label(per['adaptive_prior'])} | {sampler['heading_std_rad']}, "
                     f"{sampler['speed_std_frac']}{' (grid edge)' if sampler['on_grid_edge'] else ''} | "
                     f"{_label(results['folds'][loc]['full']['fallback_k1'])} |")
    lines += ["", "A choice marked (grid edge) lies at its grid's largest value, where a better one may lie beyond."]
    return "\n".join(lines) + "\n"


def _label(choice: dict[str, Any]) -> str:
    return str(best_baseline.label(choice)) + (" (grid edge)" if choice.get("on_grid_edge") else "")


def _protocol(results: dict[str, Any]) -> str:
    return ("Produced by `python -m scripts.driving_lolo` then `python -m scripts.driving_report`. "
            f"{results['targets']:,} real targets: every vehicle observed over its whole window (AV1: every agent "
            "but the AV; AV1 labels no classes), 20 observed + 30 predicted steps at 10 Hz, in six locations: AV1 MIA, "
            "AV1 PIT (one window per sequence), AV2 (scenario + sensor logs, stride 10), NGSIM US-101, Lankershim, "
            "Peachtree (CommonRoad, stride 10). Each location is predicted by models trained on the other five only "
            "(their recordings' validation clusters choose the epoch); every kinematic choice is made on the "
            "training locations too (`model.kinematic.best_baseline`; the CV sampler keeps plain CV as its mode 0). "
            "The mean head is the network's own K = 1; `logpipe predict` by default (`--out-of-distribution auto`) "
            "gives a target on a road the checkpoint never trained on (every target here) the best kinematic "
            "baseline of the checkpoint's own training targets as mode 0, its mode heads around it "
            "(`model.residual.modes`). Intervals: 95 % bootstrap over recording clusters within each location "
            "(CommonRoad files that share tracks form one cluster). K = 1 is each method's single forecast (the "
            "residual model's mean head); K = 6 is per agent, the best of 6 modes at the final step. Turning: the "
            "future's last 0.5 s heads more than 20 degrees away from the last 0.4 s observed.")


def _criteria(pt: dict[str, np.ndarray], location: np.ndarray, held: list[str], rows: np.ndarray,
              turning: np.ndarray, pooled: Resampler, turn_rows: np.ndarray) -> list[str]:
    def mean(key: str, r: np.ndarray) -> float:
        return float(np.nanmean(pt[key][r]))

    best = mean("best_kinematic.fde", rows)
    out = [f"- K = 1 FDE pooled against the best kinematic baseline ({best:.3f}): the mean head "
           f"{mean('full.fde', rows):.3f} ({mean('full.fde', rows) / best:.3f}x), as predict runs it "
           f"{mean('full_auto.fde', rows):.3f} ({mean('full_auto.fde', rows) / best:.3f}x; target <= 1)."]
    per = [(loc, np.flatnonzero(location == loc)) for loc in held]
    out.append("- Per location, K = 1 FDE against the best kinematic baseline: mean head "
               + ", ".join(f"{loc} {mean('full.fde', r) / mean('best_kinematic.fde', r):.3f}" for loc, r in per)
               + "; as predict runs it "
               + ", ".join(f"{loc} {mean('full_auto.fde', r) / mean('best_kinematic.fde', r):.3f}" for loc, r in per)
               + " (the issue: never above 1).")
    out.append("- Per location, the mean head's K = 1 FDE against constant velocity: "
               + ", ".join(f"{loc} {mean('full.fde', r) / mean('cv.fde', r):.3f}" for loc, r in per) + ".")
    for key, label in (("full", "the full model"), ("full_auto", "as predict runs it")):
        out.append(f"- minFDE@6 pooled, {label}: {mean(f'{key}.min_fde', rows) / mean('cv_sampler.min_fde', rows):.3f}"
                   f" of the CV sampler's; turning targets ({len(turn_rows)}): "
                   f"{mean(f'{key}.min_fde', turn_rows) / mean('cv_sampler.min_fde', turn_rows):.3f}.")
    diff = pt["no_en.min_fde"] - pt["full.min_fde"]  # paired: the same targets, resampled by cluster with the rest
    lo, hi = pooled.interval(lambda r: float(np.nanmean(diff[r[turning[r]]])))
    out.append(f"- Full model against the same without EN, minFDE@6 of turning targets: the EN gains "
               f"{np.nanmean(diff[turn_rows]):.3f} m [{lo:.3f}, {hi:.3f}].")
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--results", type=Path, default=REPO / "docs" / "results" / "driving_lolo.json")
    args = ap.parse_args(argv)
    results = json.loads(args.results.read_text())
    args.results.with_suffix(".md").write_text(render(results))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
