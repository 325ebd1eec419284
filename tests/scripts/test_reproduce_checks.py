"""The ETH/UCY reproduction's checks and the scripts' shared pieces (scripts.ethucy_checks, .validation, .seeds,
.forecasts, .ethucy_report), on a bundled real ETH/UCY file."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from logpipe.prediction.runs import PredictionRun
from scripts.ethucy_checks import FRAME_RATE_SHIFT, rate_shifted_text

REPO = Path(__file__).resolve().parents[2]

ZARA = REPO / "tests" / "data" / "ethucy" / "eth" / "train" / "crowds_zara01_train.txt"


def _rows(text: str) -> np.ndarray:
    return np.array([[float(v) for v in line.split("\t")] for line in text.splitlines()])


def test_rate_shift_by_one_keeps_every_row() -> None:
    src = np.loadtxt(ZARA, ndmin=2)
    out = _rows(rate_shifted_text(ZARA, factor=1.0))
    order = np.lexsort((src[:, 1], src[:, 0]))
    np.testing.assert_allclose(out, src[order], atol=5e-5)


def test_rate_shift_interpolates_each_track_on_the_longer_step() -> None:
    src = np.loadtxt(ZARA, ndmin=2)
    out = _rows(rate_shifted_text(ZARA))
    step_s = 0.4 * FRAME_RATE_SHIFT
    checked = 0
    for ped in np.unique(src[:, 1])[:20]:
        track = src[src[:, 1] == ped]
        mine = out[out[:, 1] == ped]
        if len(mine) == 0:  # shorter than one new step: nothing on the new grid
            assert (track[-1, 0] - track[0, 0]) * 0.04 < 2 * step_s
            continue
        # independent: the new step k sits at k x step_s on the recording's clock, 10 frames per new step
        t_new = mine[:, 0] / 10 * step_s
        t_src = track[:, 0] * 0.04
        assert t_new[0] >= t_src[0] - 1e-6 and t_new[-1] <= t_src[-1] + 1e-6
        np.testing.assert_allclose(mine[:, 2], np.interp(t_new, t_src, track[:, 2]), atol=2e-3)
        np.testing.assert_allclose(mine[:, 3], np.interp(t_new, t_src, track[:, 3]), atol=2e-3)
        assert np.all(np.diff(mine[:, 0]) == 10)
        checked += 1
    assert checked >= 10
    assert len(out) == pytest.approx(len(src) / FRAME_RATE_SHIFT, rel=0.1)


def test_seed_checkpoints_are_found_under_seed_folders(tmp_path: Path) -> None:
    from scripts.seeds import seed_template, training_seeds

    for name in ("seed2/ethucy", "seed10/ethucy", "seed10/apolloscape", "seed4/apolloscape", "seedx/ethucy",
                 "ethucy"):
        (tmp_path / name).mkdir(parents=True)
    (tmp_path / "seed3").write_text("a file, not a checkpoint folder")
    assert training_seeds("ethucy", tmp_path) == [2, 10]
    assert training_seeds("apolloscape", tmp_path) == [4, 10]  # seed 2 trained ETH/UCY only
    assert training_seeds("ethucy", tmp_path / "absent") == []  # no seed folder: only seed 0, no error
    # a shipped template maps into the seeds folder, outside the package
    assert (seed_template("model/checkpoints/ethucy/{scene}/lstm", 2, tmp_path)
            == f"{tmp_path.resolve().as_posix()}/seed2/ethucy/{{scene}}/lstm")
    assert seed_template("/elsewhere/run/best", 2, tmp_path) == "/elsewhere/run/best"  # an explicit folder stays


def test_results_files_say_when_there_are_no_seed_checkpoints(tmp_path: Path) -> None:
    from scripts.ethucy_report import across_seeds_section
    from scripts.reproduce_apolloscape import render_across_seeds

    results: dict[str, dict[str, object]] = {"seeds": {"eth": {}}, "stale_seeds": {}, "scenes": {}}
    eth = across_seeds_section(results, tmp_path / "none")
    assert eth[0] == "## Across training seeds" and f"{tmp_path.resolve() / 'none'}/seedN/ethucy/" in eth[2]
    apollo = render_across_seeds({}, {}, REPO / "out" / "checkpoints")
    assert "`out/checkpoints/seedN/apolloscape/`" in apollo[-1] and "only training seed 0" in apollo[-1]


def test_a_seed_trained_with_another_recipe_is_left_out(tmp_path: Path) -> None:
    """Seed N counts only while each of its checkpoints has the config of the shipped one beside it, seed and
    step budget aside: a seed trained before a config change is no repeat of the shipped runs."""
    from logpipe.model.checkpoint.format import stamped_meta
    from scripts.seeds import stale_seeds, training_seeds

    shipped = json.loads((REPO / "model/checkpoints/ethucy/eth/meta.json").read_text(encoding="utf-8"))

    def place(folder: str, **change: object) -> None:
        meta = json.loads(json.dumps(shipped))
        for key, value in change.items():
            block = meta["config"]["model"] if key == "mode_gate" else meta["config"]
            block[key] = value
        (tmp_path / folder).mkdir(parents=True)
        (tmp_path / folder / "meta.json").write_text(json.dumps(stamped_meta(meta)), encoding="utf-8")

    gate = bool(shipped["config"]["model"].get("mode_gate", False))
    place("ethucy/eth")
    place("seed1/ethucy/eth", seed=1, steps=1234)
    place("seed2/ethucy/eth", seed=2, mode_gate=not gate, lr=1e-3)
    place("seed2/ethucy/hotel", seed=2, lr=1e-3)  # nothing shipped beside it to compare with
    assert stale_seeds("ethucy", tmp_path, tmp_path) == {2: ["ethucy/eth: lr, model.mode_gate"]}
    assert training_seeds("ethucy", tmp_path, tmp_path) == [1]


def test_settings_a_network_cannot_feel_make_no_other_recipe(tmp_path: Path) -> None:
    """A Noise-LSTM trained before ``context_radius_m`` existed and one trained with it collate the same windows
    (no pools read other agents), so they are one recipe; for the paper's method the radius is another recipe."""
    from logpipe.model.checkpoint.format import stamped_meta
    from scripts.seeds import stale_seeds

    for method in ("noise_lstm", ""):
        meta = json.loads((REPO / f"model/checkpoints/ethucy/univ/{method}/meta.json").read_text(encoding="utf-8"))
        for folder, radius in ((f"ethucy/univ/{method}", None), (f"seed1/ethucy/univ/{method}", 3.0)):
            meta["config"]["model"]["context_radius_m"] = radius
            (tmp_path / folder).mkdir(parents=True, exist_ok=True)
            (tmp_path / folder / "meta.json").write_text(json.dumps(stamped_meta(meta)), encoding="utf-8")
    assert stale_seeds("ethucy", tmp_path, tmp_path) == {1: ["ethucy/univ: model.context_radius_m"]}


def test_stale_seed_lines_are_grouped_by_the_keys_that_differ() -> None:
    from scripts.seeds import stale_summary

    many = [f"ethucy/{scene}: model.mode_gate" for scene in ("eth", "hotel", "univ", "zara1")]
    assert stale_summary([*many, "ethucy/eth/lstm: lr, model.mode_gate"]) == (
        "`model.mode_gate` in 4 checkpoints; `lr, model.mode_gate` in 1 checkpoint (ethucy/eth/lstm)")


def test_across_seeds_table_means_ranges_and_standing() -> None:
    from scripts.seeds import across_seeds_table

    cells = {
        "eth": {"cv_sampler": [(0.50, 0.90), (0.52, 0.86)], "zhu2020": [(0.53, 0.91), (0.49, 0.87)]},
        "hotel": {"cv_sampler": [(0.20, 0.30), (0.20, 0.30)], "zhu2020": [(0.18, 0.31), (0.18, 0.31)]},
    }
    lines = across_seeds_table(["eth", "hotel"], cells, with_avg=True)
    sampler = next(line for line in lines if line.startswith("| CV sampler, best-of-20 (seeds: 2)"))
    assert "0.510/0.880 (0.500-0.520 / 0.860-0.900)" in sampler and sampler.endswith("| 0.355/0.590 |")
    ours = next(line for line in lines if line.startswith("| Our method"))
    assert "0.510/0.890" in ours and ours.endswith("| 0.345/0.600 |")
    verdict = next(line for line in lines[lines.index(ours) + 1:] if line.startswith("| CV sampler"))
    # eth: equal ADE, higher FDE -> not beaten; hotel: lower ADE, higher FDE -> split; AVG: lower ADE, higher FDE
    assert verdict == "| CV sampler, best-of-20 | **not beaten** | split | split |"
    assert not any(line.startswith("| LSTM") for line in lines)  # no seeds of a method: no row


@pytest.mark.slow
def test_seed_run_scores_the_sampler_like_a_direct_computation(bundled: Path, tmp_path: Path) -> None:
    from logpipe.model.kinematic.constant_velocity import ConstantVelocitySampler
    from logpipe.stages.train import scene_samples
    from scripts.locations import ensure_dataset
    from scripts.seeds import seed_run
    from scripts.validation import best_of_k, truth_of, tune_sampler

    ds = ensure_dataset(bundled / "ethucy", tmp_path / "ds", "ethucy")
    val, test = scene_samples(ds, "eth/train")[:40], scene_samples(ds, "eth/test")
    ours = {"zhu2020": str(REPO / "model" / "checkpoints" / "ethucy" / "eth"), "lstm": str(tmp_path / "none")}
    learned = {"zhu2020": ("", 20), "lstm": ("", 1)}
    runs = {seed: seed_run(seed, ours, learned, "eth", ds, val, test, "eth/test", 1, tmp_path / f"s{seed}")
            for seed in (1, 2)}
    for seed, run in runs.items():
        assert set(run) == {"cv_sampler", "zhu2020"}  # the missing lstm checkpoint is left out, not an error
        assert run["zhu2020"][0] == 20 and np.isfinite(run["zhu2020"][1:]).all()
        choice, _ = tune_sampler(val, 12, 20, seed)
        direct = best_of_k(np.concatenate(ConstantVelocitySampler(pred_len=12, **choice).predict(test, 20, seed)),
                           truth_of(test, 12))
        np.testing.assert_allclose(run["cv_sampler"][1:], direct, rtol=1e-9)
    assert runs[1]["zhu2020"][1:] != runs[2]["zhu2020"][1:]  # each seed samples its own noise


def test_motion_breakdown_splits_the_scored_agents(bundled: Path, tmp_path: Path) -> None:
    from logpipe.model.kinematic.constant_velocity import ConstantVelocitySampler
    from logpipe.stages.score import score
    from logpipe.stages.train import scene_samples
    from scripts.ethucy_checks import STAY_RADIUS_M, STILL_STEP_M, motion_breakdown
    from scripts.forecasts import read_forecasts, write_classical
    from scripts.locations import ensure_dataset

    ds = ensure_dataset(bundled / "ethucy", tmp_path / "ds", "ethucy")
    test = scene_samples(ds, "eth/test")
    sampler = {"heading_std_rad": 0.2, "speed_std_frac": 0.3}
    files = write_classical(test, 12, 0, sampler, 20, "cv_sampler", tmp_path / "pred")
    report = score(files, ds.root, tmp_path / "report", split="eth/test", min_agents=2, plots=False)
    forecasts = read_forecasts(files, test, ("cv_sampler", "cv"))
    # Read back from the file, the sampler's forecasts are the ones it makes (float32 storage aside).
    direct = np.concatenate(ConstantVelocitySampler(pred_len=12, **sampler).predict(test, 20, 0))
    np.testing.assert_allclose(forecasts["cv_sampler"], direct, atol=1e-4)
    parts = motion_breakdown(test, forecasts, 12, 2)
    n = parts["agents"]
    assert n["all"] == report["methods"]["cv"]["overall"]["agents"]  # the agents `logpipe score` counted
    assert n["stays"] + n["starts"] == n["standing"] and n["standing"] + n["moving"] == n["all"]
    assert min(n["stays"], n["starts"], n["moving"]) > 0
    for method, k in (("cv_sampler", 20), ("cv", 1)):
        whole = report["methods"][method]["overall"][f"k{k}"]
        got = parts["methods"][method]
        np.testing.assert_allclose(got["all"], (whole["ade"], whole["fde"]), rtol=1e-9)
        np.testing.assert_allclose(n["stays"] * got["stays"][0] + n["starts"] * got["starts"][0]
                                   + n["moving"] * got["moving"][0], n["all"] * got["all"][0], rtol=1e-9)
    # Constant velocity keeps a standing pedestrian within 12 steps of under 3 cm of where it stood: its FDE on
    # those that stayed is under the stay radius plus that drift, on those that started over the radius minus it.
    drift = 12 * STILL_STEP_M
    assert parts["methods"]["cv"]["stays"][1] < STAY_RADIUS_M + drift
    assert parts["methods"]["cv"]["starts"][1] > STAY_RADIUS_M - drift


def test_inference_settings_are_the_val_argmin_over_the_joint_grid(bundled: Path, tmp_path: Path) -> None:
    """tune_inference tries every (constant-velocity modes, noise scale) pair, picks the lowest val best-of-20
    ADE, and ``tuned`` reproduces the chosen row; holding a mode at constant velocity changes the forecasts."""
    from logpipe.model.zhu2020.predictor import NetPredictor
    from logpipe.stages.train import scene_samples
    from scripts.locations import ensure_dataset
    from scripts.validation import (
        CV_MODES_GRID,
        NOISE_SCALE_GRID,
        best_of_k,
        grid_row,
        truth_of,
        tune_inference,
        tuned,
    )

    ds = ensure_dataset(bundled / "ethucy", tmp_path / "ds", "ethucy")
    val = scene_samples(ds, "eth/train")[:30]
    net = NetPredictor.from_checkpoint(REPO / "model" / "checkpoints" / "ethucy" / "eth", expect_kind=ds.kind)
    choice, grid = tune_inference(net, val, 12, 20, 0)
    assert {(g[0], g[1]) for g in grid} == {(c, s) for c in CV_MODES_GRID for s in NOISE_SCALE_GRID}
    row = grid_row(grid, choice["constant_velocity_modes"], choice["noise_scale"])
    assert row[2] == min(g[2] for g in grid)
    again = best_of_k(np.concatenate(tuned(net, choice).predict(val, 20, 0)), truth_of(val, 12))
    np.testing.assert_allclose(again, row[2:], rtol=1e-12)
    assert grid_row(grid, 0, 1.0)[2:] != grid_row(grid, 1, 1.0)[2:]


def test_paired_differences_agree_with_the_report(bundled: Path, tmp_path: Path) -> None:
    from logpipe.stages.score import score
    from logpipe.stages.train import scene_samples
    from scripts.ethucy_checks import paired_differences, window_blocks
    from scripts.forecasts import read_forecasts, write_classical
    from scripts.locations import ensure_dataset

    ds = ensure_dataset(bundled / "ethucy", tmp_path / "ds", "ethucy")
    test = scene_samples(ds, "eth/test")
    files = write_classical(test, 12, 0, {"heading_std_rad": 0.2, "speed_std_frac": 0.3}, 20, "cv_sampler",
                            tmp_path / "pred")
    report = score(files, ds.root, tmp_path / "report", split="eth/test", min_agents=2, plots=False)
    read = read_forecasts(files, test, ("cv_sampler", "cv"))
    # The sampler stands in for the paper's method: paired with itself the difference is exactly 0; paired with
    # constant velocity (K=1) it is the difference of the report's rows, and clearly below 0.
    paired = paired_differences(test, {"zhu2020": read["cv_sampler"], "cv_sampler": read["cv_sampler"],
                                       "noise_lstm": read["cv"]}, 12, 2)
    assert paired["cv_sampler"]["ade"]["low"] == paired["cv_sampler"]["ade"]["high"] == 0.0
    rows = report["methods"]
    for key in ("ade", "fde"):
        got = paired["noise_lstm"][key]
        want = rows["cv_sampler"]["overall"]["k20"][key] - rows["cv"]["overall"]["k1"][key]
        assert got["mean"] == pytest.approx(want, rel=1e-9)
        assert got["low"] <= got["mean"] <= got["high"] < 0
        assert got["agents"] == rows["cv"]["overall"]["agents"]
    # Blocks: one label per target row; windows of one log starting within one 20-step block share it.
    blocks = window_blocks(test)
    starts = [(s.sample_id.rsplit(":", 1)[0], int(s.sample_id.rsplit(":", 1)[1]) // 20) for s in test
              for _ in range(int(s.target_mask.sum()))]
    assert len(blocks) == len(starts) and len(set(blocks.tolist())) == len(set(starts)) > 1
    assert all((blocks[i] == blocks[j]) == (starts[i] == starts[j]) for i in range(0, len(starts), 7)
               for j in range(0, len(starts), 11))


def test_the_neighbour_cap_is_the_training_percentile_and_only_for_pooling_nets(bundled: Path, tmp_path: Path) -> None:
    from logpipe.model.zhu2020.batching import neighbour_counts
    from logpipe.model.zhu2020.predictor import NetPredictor
    from logpipe.stages.train import scene_samples
    from scripts.forecasts import write_learned
    from scripts.locations import ensure_dataset
    from scripts.validation import NEIGHBOUR_CAP_PERCENTILE, best_of_k, grid_row, neighbour_cap, truth_of, tuned

    ds = ensure_dataset(bundled / "ethucy", tmp_path / "ds", "ethucy")
    train = scene_samples(ds, "eth/train")
    counts = np.concatenate([neighbour_counts(s, 2.0) for s in train])
    cap = neighbour_cap(train, 2.0)
    assert cap in counts and np.mean(counts <= cap) >= NEIGHBOUR_CAP_PERCENTILE / 100 > np.mean(counts < cap)
    # val: windows where the cap binds, so a grid run without it would score differently
    val = [s for s in train if neighbour_counts(s, 2.0).max(initial=0) > cap][:20]
    assert val
    test = scene_samples(ds, "eth/test")[:10]
    folder = REPO / "model" / "checkpoints" / "ethucy" / "eth"
    _, ours = write_learned(folder, ds.kind, val, test, 20, 0, 12, tmp_path / "p", "zhu2020", "as_trained",
                            train=train)
    _, theirs = write_learned(folder / "noise_lstm", ds.kind, val, test, 20, 0, 12, tmp_path / "p", "noise_lstm",
                              train=train)
    assert ours is not None and theirs is not None
    assert ours["context_max_neighbours"] == cap and "context_max_neighbours" not in theirs
    # The (c, s) grid ran with the cap: its chosen row is what the capped network scores on val.
    net = NetPredictor.from_checkpoint(folder, expect_kind=ds.kind)
    row = grid_row(ours["grid"], ours["constant_velocity_modes"], ours["noise_scale"])
    capped = tuned(net, {k: ours[k] for k in ("noise_scale", "constant_velocity_modes", "context_max_neighbours")})
    assert capped.context_max_neighbours == cap
    np.testing.assert_allclose(best_of_k(np.concatenate(capped.predict(val, 20, 0)), truth_of(val, 12)), row[2:],
                               rtol=1e-12)
    ids = {m: {PredictionRun.open(tmp_path / "p" / f"{m}.parquet").meta.checkpoint_id}  # the file's metadata
           for m in ("zhu2020", "as_trained")}
    assert all(f"context_max_neighbours={cap}" in i for i in ids["zhu2020"])
    assert not any("context_max_neighbours" in i for i in ids["as_trained"])


def test_the_ablation_is_never_a_baseline_and_gets_its_own_standing() -> None:
    from scripts.ethucy_report import ABLATION, SCENES, standing

    def cell(ade: float, fde: float) -> dict[str, dict[str, dict[str, float]]]:
        return {"overall": {"k20": {"ade": ade, "fde": fde, "ade_joint": ade * 2, "fde_joint": fde * 2},
                            "k1": {"ade": 9.0, "fde": 9.0}}}

    methods = {"noise_lstm": cell(0.30, 0.60), "zhu2020": cell(0.35, 0.70), ABLATION: cell(0.20, 0.40)}
    results = {"scenes": {s: {"min2": {"methods": methods}} for s in SCENES}}
    def row(lines: list[str], label: str) -> list[str]:
        return next(line for line in lines if line.startswith(f"| {label}")).strip("| ").split(" | ")[1:]

    ours = standing(results, "min2")
    assert not any(line.startswith("| Ablation") for line in ours)  # not a row the method must beat
    assert row(ours, "Noise-LSTM") == ["**not beaten**"] * (len(SCENES) + 1)
    ablation = standing(results, "min2", ABLATION)
    assert row(ablation, "Noise-LSTM") == ["beaten"] * (len(SCENES) + 1)
    # like with like: the joint rule of the paper's comparison rows decides, never the flattering per-agent one
    assert "Joint best-of-20 average 0.40/0.80 (the rule the paper's comparison rows use) against the paper's " \
        "0.36/0.75: **not reached**. (Per agent 0.20/0.40" in "\n".join(ablation)


def test_rows_chosen_on_val_name_their_constant_velocity_modes() -> None:
    from scripts.ethucy_report import SCENES, cv_mode_label

    label = "Ours (zhu2020), best-of-20 per agent (inference settings chosen on val)"
    val = {s: {"zhu2020": {"constant_velocity_modes": 1}, "noise_lstm": {"constant_velocity_modes": 0}}
           for s in SCENES}
    assert cv_mode_label(label, "zhu2020", {"val": val}).endswith(
        "(inference settings chosen on val, c = 1 on every scene: 1 of the 20 modes plain constant velocity)")
    assert cv_mode_label(label, "noise_lstm", {"val": val}).endswith("(inference settings chosen on val, c = 0 on "
                                                                      "every scene)")
    val["eth"]["zhu2020"]["constant_velocity_modes"] = 0
    assert "c = 0 (eth), 1 (hotel)" in cv_mode_label(label, "zhu2020", {"val": val})
    assert cv_mode_label("Constant velocity (K=1)", "cv", {"val": val}) == "Constant velocity (K=1)"
