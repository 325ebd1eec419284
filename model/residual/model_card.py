"""The ``MODEL_CARD.md`` of a run of ``logpipe train`` on driving data (``fleet.train_fleet``), and the lines of its
comparison the command prints: what was trained on what, how it was validated, how it started, and how it
compares with the kinematic baselines on the validation targets, saying plainly where it does not beat them."""

from __future__ import annotations

from typing import Any

LABELS = {"model": "trained model (mean head)", "shipped_model": "shipped driving model, as shipped",
          "cv": "constant velocity (last displacement)",
          "least_squares_cv": "least-squares CV (window chosen on training)",
          "kalman": "Kalman CV filter (noise chosen on training)",
          "adaptive_prior": "adaptive prior (its constants chosen on training)",
          "model_prior": "the model's own prior alone (constants fixed since issue 57)"}


def _settings(record: dict[str, Any]) -> str:
    shown = {k: v for k, v in record.items() if k not in ("method", "train_fde", "on_grid_edge")}
    return (", ".join(f"{k} {v}" for k, v in shown.items()) or "none") + (
        " (on its grid's edge)" if record.get("on_grid_edge") else "")


def _k1_line(s: dict[str, Any]) -> str:
    k1 = s["k1"]
    line = (f"K = 1 in `logpipe predict`: the trained model's mean head ({k1['reason']})" if k1["source"] == "model"
            else f"K = 1 in `logpipe predict`: the best kinematic baseline of its training, its modes after it "
            f"({k1['reason']})")
    roads = s.get("k1_by_location") or {}
    if k1["source"] == "model" and roads:
        line += "; per road, where validation showed it on at least 30 targets (elsewhere physics): " + ", ".join(
            f"{loc} {r['source']} ({r['model_fde']:.2f} m against {r['baseline_fde']:.2f}, {r['targets']} targets)"
            for loc, r in roads.items())
    return line


def comparison_lines(s: dict[str, Any]) -> list[str]:
    """The comparison as plain lines (the command's human summary)."""
    c = s["comparison"]
    if not c["targets"]:
        return [f"  validation: {s['validation']['description']}", f"  start: {s['start']['chosen']}",
                f"  verdict: {c['verdict']}", f"  {_k1_line(s)}"] + [f"  note: {n}" for n in s.get("notes", [])]
    k = c["k"]
    k1 = c["k1"]
    sampler = c["cv_sampler"]
    best_of = c[f"min_fde_{k}"]
    lines = [f"  validation: {s['validation']['description']}",
             f"  start: {s['start']['chosen']} (validation score "
             + ", ".join(f"{n} {v:.3f}" for n, v in s["start"]["validation_scores"].items()) + ")"
             + (f"; {s['start']['finetune_not_tried']}" if s["start"]["finetune_not_tried"] else ""),
             f"  on {c['targets']} validation targets, K = 1 FDE/ADE (m): "
             + "; ".join(f"{n} {v['fde']:.2f}/{v['ade']:.2f}" for n, v in k1.items()),
             f"  minFDE@{k} (m): model {best_of['model']:.2f}, CV sampler {best_of['cv_sampler']:.2f} (CV as one "
             f"mode, noise {sampler['heading_std_rad']} rad / {sampler['speed_std_frac']} chosen on training)"
             + (f", shipped model {best_of['shipped_model']:.2f}" if "shipped_model" in best_of else ""),
             f"  model / CV: K = 1 FDE {c['model_fde_to_cv']}x, minFDE@{k} {c[f'model_min_fde_{k}_to_cv_fde']}x CV's "
             f"K = 1 FDE; best kinematic baseline ({c['best_kinematic']}, chosen on training): "
             f"{c['model_fde_to_best_kinematic']}x",
             f"  verdict: {c['verdict']}", f"  {_k1_line(s)}"]
    if c.get("shipped_model_saw_validation_logs"):
        seen = c["shipped_model_saw_validation_logs"]
        lines.append(f"  note: the shipped model was trained or validated on {seen} of the validation recordings: "
                     "its figures here are not held out")
    return lines + [f"  note: {n}" for n in s.get("notes", [])]


def model_card(s: dict[str, Any]) -> str:
    """The markdown card."""
    c = s["comparison"]
    k = c["k"]
    datasets = s["dataset"] if isinstance(s["dataset"], list) else [s["dataset"]]
    lines = ["# Model card", "",
             "The residual driving model (our extension of Zhu et al.: learned corrections to an adaptive "
             "constant-velocity prior), trained by `logpipe train` with the shipped driving default's recipe.", "",
             "## Data", "",
             f"- datasets: {', '.join(f'`{d}`' for d in datasets)}",
             f"- training: {s['train_samples']} windows, {s['train_targets']} targets; validation: "
             f"{s['val_samples']} windows, {s['val_targets']} targets",
             f"- how validation was chosen: {s['validation']['description']}",
             f"- environment net (map crops): {'on' if s['environment_net'] else 'off'}",
             *[f"- note: {n}" for n in s.get("notes", [])], "",
             "## Training", "",
             f"- start: **{s['start']['chosen']}** ("
             + (f"lowest {s['start']['score']}: " + ", ".join(
                 f"{n} {v:.3f}" for n, v in s["start"]["validation_scores"].items()) if s["start"]["validation_scores"]
                else "nothing to validate on: the only start tried") + ")"
             + (f"; {s['start']['finetune_not_tried']}" if s["start"]["finetune_not_tried"] else ""),
             f"- best epoch's step {s['best_step']} of {s['steps']}; {s['seconds']} s wall time on the CPU", "",
             f"## Against the kinematic baselines, on the {c['targets']} validation targets", "",
             f"**Verdict: {c['verdict']}.**", "", f"**{_k1_line(s)}.**", ""]
    if not c["targets"]:
        return "\n".join([*lines, f"Use it: `logpipe predict DATASET --checkpoint {s['best_checkpoint']} --out PRED`.",
                          ""])
    lines += ["| method | K = 1 FDE (m) | K = 1 ADE (m) |", "|---|---|---|"]
    lines += [f"| {LABELS.get(n, n)} | {v['fde']:.3f} | {v['ade']:.3f} |" for n, v in c["k1"].items()]
    sampler = c["cv_sampler"]
    lines += ["", f"| method | minFDE@{k} (m) |", "|---|---|"]
    lines += [f"| {LABELS.get(n, 'CV sampler (mode 0 is CV)')} | {v:.3f} |" for n, v in c[f"min_fde_{k}"].items()]
    lines += ["", f"- trained model / CV at K = 1: {c['model_fde_to_cv']}x; minFDE@{k} / CV's K = 1 FDE: "
              f"{c[f'model_min_fde_{k}_to_cv_fde']}x",
              f"- best kinematic baseline at K = 1, chosen on the training targets: {c['best_kinematic']} "
              f"(trained model / it on validation: {c['model_fde_to_best_kinematic']}x)",
              f"- CV sampler: heading noise {sampler['heading_std_rad']} rad, speed noise {sampler['speed_std_frac']}, "
              "chosen on the training targets by minFDE"
              + ("; the choice lies on the grid's edge, so a better one may lie beyond it" if sampler["on_grid_edge"]
                 else " (an interior point of the grid)"),
              "- settings chosen on the training targets: " + "; ".join(
                  f"{name} {_settings(record)}" for name, record in c["baselines"].items()),
              *([f"- the shipped model was trained or validated on {c['shipped_model_saw_validation_logs']} of the "
                 "validation recordings: its rows are not held-out figures"]
                if c.get("shipped_model_saw_validation_logs") else []),
              "", "Use it: `logpipe predict DATASET --checkpoint " + s["best_checkpoint"] + " --out PRED`.", ""]
    return "\n".join(lines)
