"""``logpipe score``: ADE/FDE reports for one or more prediction runs against a dataset's ground truth.

Reads top-down: open each input (a ``logpipe predict`` output folder, or a predictions file; one method each,
read through ``logpipe.predictions`` with its protocol, K and horizon from its metadata) → check the protocol
against the dataset's → decide which agents count (the protocol flags: ``agents``, ``min_agents``, ``split``) → look up
their true futures in the dataset's track table with one join → per-step L2 errors → metrics per method,
overall / per object type / per log, for every K asked → ``report.json``, ``report.md``, PNG plots,
committed as one artifact folder (``manifest.json``, ``logpipe.artifact``) → threshold gate for CI.

Conventions are those of ``logpipe.metrics`` (ADE = mean Euclidean distance in metres; per-agent and joint
best-of-K; the Argoverse min-FDE mode with its ADE and a 2.0 m miss rate). The protocol is written next to
every method's numbers so a number never travels without it.
"""

from __future__ import annotations

import io
import json
import math
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc

from logpipe import metrics
from logpipe.artifact import MANIFEST
from logpipe.dataset import Dataset
from logpipe.errors import LogpipeError
from logpipe.io import as_numpy, read_table, sha256_file
from logpipe.predictions import PredictionMeta, PredictionRun
from logpipe.reports import REPORT_JSON, REPORT_MD, REPORT_VERSION, write_report_folder
from logpipe.types import NDArrayFloat, NDArrayInt, SceneSample

"""Bumped when a key of ``report.json`` changes meaning or disappears."""

Agents = Literal["all", "focal"]

CONVENTIONS = {
    "ade": "mean Euclidean (L2) distance over the predicted steps, metres (the paper's 'mean square error' "
           "wording notwithstanding)",
    "fde": "Euclidean distance at the last predicted step, metres",
    "kN.ade/kN.fde": "per-agent best-of-N (Social-STGCNN and most ETH/UCY papers): min over the first N modes of "
                     "each agent's ADE and, independently, of its FDE; N=1 is the most likely mode",
    "kN.ade_joint/kN.fde_joint": "joint best-of-N (Social-GAN evaluate_model.py): one mode per sample, the one "
                                 "with the lowest error summed over the sample's agents",
    "kN.argo_ade/kN.argo_fde/kN.miss_rate": "Argoverse: per agent the mode with the lowest FDE, its ADE and FDE; "
                                            "miss when that FDE > miss_threshold_m",
    "kN.error_by_step": "mean L2 error per predicted step of each agent's min-ADE mode, metres (averages to kN.ade)",
    "averaging": "means over agents (each agent-window counts once); per-log and per-type groups likewise, the "
                 "joint choice then made among the group's agents of each sample",
}


class ScoreError(LogpipeError):
    """Predictions and truth cannot be scored together (bad table, missing agents, unknown metric)."""


@dataclass
class MethodForecasts:
    """One method's forecasts (one prediction run folder or predictions file), as dense arrays.

    Attributes:
        name: label in reports (the predictor unless relabelled or colliding).
        predictor: the metadata's predictor.
        checkpoint_ids: distinct ``checkpoint_id`` values.
        source: the folder or file.
        run_name: the folder's name or the file's stem (the label when predictor names collide).
        meta: what the forecasts were made with (protocol, K, horizon, seed, ...).
        sample_ids: (N,) sample of each agent row.
        track_ids: (N,) track of each agent row.
        object_types: (N,) normalised class of each agent row.
        pred: (N, K, T, 2) metres, world frame; mode 0 the most likely.
    """

    name: str
    predictor: str
    checkpoint_ids: list[str]
    source: str
    run_name: str
    meta: PredictionMeta
    sample_ids: Any
    track_ids: Any
    object_types: Any
    pred: NDArrayFloat

    @property
    def num_modes(self) -> int:
        """K."""
        return int(self.pred.shape[1])


def load_method(path: Path) -> MethodForecasts:
    """Read one method: a ``logpipe predict`` output folder (its committed predictions) or a predictions file.

    Raises:
        PredictionsError: missing, damaged, not a prediction run, or not one row per (agent, mode) with the
            metadata's K and lists of its T steps (version 1 tables: one row per (agent, mode, step)).
    """
    run = PredictionRun.open(Path(path))
    dense = run.dense()
    return MethodForecasts(
        name=run.meta.predictor, predictor=run.meta.predictor, checkpoint_ids=dense.checkpoint_ids,
        source=str(path), run_name=run.name, meta=run.meta, sample_ids=dense.sample_ids, track_ids=dense.track_ids,
        object_types=dense.object_types, pred=dense.pred,
    )


def _name_methods(methods: list[MethodForecasts], labels: Sequence[str] | None) -> None:
    """Labels given, else the predictor; methods whose predictors collide (two checkpoints of one method) are
    named by their folder or file, and ``#N`` is added where even those collide."""
    if labels:
        if len(labels) != len(methods):
            raise ScoreError(f"{len(labels)} labels for {len(methods)} methods (one per predictions folder or "
                             f"file: {', '.join(m.source for m in methods)})")
        for m, label in zip(methods, labels, strict=True):
            m.name = label
    else:
        counts: dict[str, int] = {}
        for m in methods:
            counts[m.name] = counts.get(m.name, 0) + 1
        for m in methods:
            if counts[m.name] > 1:
                m.name = m.run_name
    seen: dict[str, int] = {}
    for m in methods:
        if m.name in seen:
            seen[m.name] += 1
            m.name = f"{m.name}#{seen[m.name]}"
        else:
            seen[m.name] = 1


def _check_protocol(methods: Sequence[MethodForecasts], ds: Dataset) -> None:
    """Every method was predicted under the dataset's protocol (name, observed and predicted steps)."""
    p = ds.protocol
    for m in methods:
        meta = m.meta
        wrong = []
        if meta.protocol is not None and meta.protocol != p.name:
            wrong.append(f"protocol {meta.protocol!r}, the dataset's is {p.name!r}")
        if meta.obs_len and meta.obs_len != p.obs_len:
            wrong.append(f"{meta.obs_len} observed steps, the dataset's protocol {p.obs_len}")
        if meta.pred_len != p.pred_len:
            wrong.append(f"horizon {meta.pred_len} steps, the dataset's protocol {p.pred_len}")
        if wrong:
            raise ScoreError(f"{m.source}: predicted with " + "; ".join(wrong) + f" ({ds.root})")


# ---------------------------------------------------------------------------------------------- truth


@dataclass
class Selection:
    """The agents that count under the protocol flags, and the samples' facts the report needs."""

    samples: pa.Table  # the kept rows of the sample index
    expected: set[tuple[str, str]]  # (sample_id, track_id) that must be scored
    dropped: dict[str, int]


def select_agents(ds: Dataset, sample_ids: set[str], *, split: str | None, agents: Agents,
                  min_agents: int) -> Selection:
    """Samples (of ``split``, else those predicted) with >= ``min_agents`` targets, and the agents to score.

    ``agents="all"``: every target of the protocol (ETH/UCY: every agent present in all steps of the window);
    ``"focal"``: the sample's focal track only (Argoverse). ``min_agents`` counts the sample's targets
    (Social-GAN's loader keeps windows with >= 2 fully observed pedestrians).
    """
    table = ds.samples()
    if split is not None:
        logs = ds.logs_in_split(split)
        table = table.filter(pc.is_in(table.column("log_id"), value_set=pa.array(logs)))
    else:
        table = table.filter(pc.is_in(table.column("sample_id"), value_set=pa.array(sorted(sample_ids), pa.string())))
        unknown = sample_ids - set(table.column("sample_id").to_pylist())
        if unknown:
            raise ScoreError(f"{ds.root}: {len(unknown)} predicted samples are not in the dataset's sample index, "
                             f"e.g. {sorted(unknown)[0]!r} (predictions made on another dataset or protocol?)")
    n_targets = pc.list_value_length(table.column("target_track_ids"))
    few = pc.less(n_targets, min_agents)
    dropped = {"samples_below_min_agents": int(pc.sum(few).as_py() or 0)}
    table = table.filter(pc.invert(few))
    expected: set[tuple[str, str]] = set()
    no_focal = 0
    for sid, targets, focal in zip(table.column("sample_id").to_pylist(), table.column("target_track_ids").to_pylist(),
                                   table.column("focal_track_id").to_pylist(), strict=True):
        if agents == "focal":
            if focal is None:
                no_focal += 1
            else:
                expected.add((sid, focal))
        else:
            expected.update((sid, t) for t in targets)
    dropped["samples_without_focal"] = no_focal
    return Selection(samples=table, expected=expected, dropped=dropped)


def truth_futures(ds: Dataset, sample_table: pa.Table, sample_ids: Any, track_ids: Any,
                  pred_len: int) -> tuple[NDArrayFloat, Any]:
    """True positions (N, T, 2) metres of each (sample, track) at steps current+1 .. current+T, NaN where the
    track has no row, and each row's log id; one join against the track table of the logs involved."""
    n = len(sample_ids)
    agents = pa.table({"i": pa.array(np.arange(n)), "sample_id": pa.array(sample_ids, pa.string()),
                       "track_id": pa.array(track_ids, pa.string())})
    agents = agents.join(sample_table.select(["sample_id", "log_id", "current_step"]), "sample_id")
    agents = agents.sort_by("i")
    if agents.num_rows != n:
        raise ScoreError("internal: agents lost when joining the sample index")
    log_ids = as_numpy(agents.column("log_id")).astype(str)
    cur = as_numpy(agents.column("current_step")).astype(np.int64)
    keys = pa.table({
        "i": pa.array(np.repeat(np.arange(n), pred_len)),
        "t": pa.array(np.tile(np.arange(pred_len), n)),
        "log_id": pa.array(np.repeat(log_ids, pred_len), pa.string()),
        "track_id": pa.array(np.repeat(np.asarray(track_ids, dtype=str), pred_len), pa.string()),
        "step": pa.array((cur[:, None] + np.arange(1, pred_len + 1)).reshape(-1).astype(np.int32)),
    })
    needed = sorted(set(log_ids.tolist()))
    parts = [read_table(p, columns=["log_id", "track_id", "step", "x", "y"], filters=[("log_id", "in", needed)])
             for p in ds.shard_paths]
    tracks = pa.concat_tables(parts)
    joined = keys.join(tracks, ["log_id", "track_id", "step"], join_type="left outer")
    if joined.num_rows != len(keys):
        raise ScoreError(f"{ds.root}: the track table has duplicate (log, track, step) rows; re-ingest the dataset")
    joined = joined.sort_by([("i", "ascending"), ("t", "ascending")])
    truth = np.stack([as_numpy(joined.column("x").fill_null(math.nan)),
                      as_numpy(joined.column("y").fill_null(math.nan))], axis=-1).astype(np.float64)
    return truth.reshape(n, pred_len, 2), log_ids


# -------------------------------------------------------------------------------------------- metrics


def group_metrics(err: NDArrayFloat, sample_idx: NDArrayInt, ks: Sequence[int], miss_threshold_m: float
                  ) -> dict[str, Any]:
    """Counts and, for each k in ``ks``, every convention's means over the agents of ``err`` (N, K, T)."""
    out: dict[str, Any] = {"samples": len(np.unique(sample_idx)), "agents": int(err.shape[0])}
    for k in ks:
        e = metrics.top_k(err, k)
        if e.shape[0] == 0:
            out[f"k{k}"] = None
            continue
        per_agent = metrics.best_of_k_per_agent(e)
        joint = metrics.best_of_k_joint(e, sample_idx)
        argo = metrics.argoverse(e)
        out[f"k{k}"] = {
            "ade": float(per_agent.ade.mean()),
            "fde": float(per_agent.fde.mean()),
            "ade_joint": float(joint.ade.mean()),
            "fde_joint": float(joint.fde.mean()),
            "argo_ade": float(argo.ade.mean()),
            "argo_fde": float(argo.fde.mean()),
            "miss_rate": float(metrics.miss(argo.fde, miss_threshold_m).mean()),
            "error_by_step": [float(v) for v in metrics.error_by_step(e, per_agent.mode)],
        }
    return out


def _check_thresholds(fail_above: dict[str, float]) -> None:
    allowed = {"ade", "fde", "ade_joint", "fde_joint", "argo_ade", "argo_fde", "miss_rate"}
    for key in fail_above:
        k, _, name = key.partition(".")
        if not (k.startswith("k") and k[1:].isdigit() and name in allowed):
            raise ScoreError(f"--fail-above {key!r}: expected kN.METRIC with METRIC one of {sorted(allowed)}, "
                             "e.g. k1.ade=0.6 or k6.miss_rate=0.2")


def score(
    predictions: Sequence[Path],
    truth: Path,
    out_dir: Path,
    *,
    agents: Agents = "all",
    min_agents: int = 1,
    split: str | None = None,
    ks: Sequence[int] | None = None,
    miss_threshold_m: float = metrics.MISS_THRESHOLD_M,
    fail_above: dict[str, float] | None = None,
    labels: Sequence[str] | None = None,
    allow_missing: bool = False,
    plots: bool = True,
    plot_samples: int = 6,
    title: str | None = None,
) -> dict[str, Any]:
    """Score prediction tables against a dataset and write ``report.json``, ``report.md`` and PNG plots.

    Args:
        predictions: prediction run folders (``logpipe predict --out``) or predictions files
            (``schemas/predictions.json``); each one is one method, shown side by side.
        truth: the dataset folder the predictions were made on (``logpipe ingest`` output).
        out_dir: the report folder (created; a committed artifact, rerunning replaces its report).
        agents: ``all`` (every protocol target, e.g. all fully observed pedestrians) or ``focal``.
        min_agents: score only samples with at least this many targets (Social-GAN: 2).
        split: score exactly the samples of this split (``eth/test``, ``hash/test``); every agent that counts
            must then be predicted. None: the samples present in the predictions.
        ks: the K values to report (first K modes by score); default 1 and each method's own K.
        miss_threshold_m: Argoverse miss threshold, metres.
        fail_above: ``{"k1.ade": 0.6, ...}``: the gate fails when any method's overall value is above.
        labels: names for the methods in input order (one per input), default the predictor names (the folder
            or file names where predictors collide).
        allow_missing: score what is there when agents that count have no (or a NaN) forecast, instead of
            failing.
        plots: write ``horizon.png`` and ``scenes_<method>.png``.
        plot_samples: samples in each scene grid.
        title: heading of ``report.md``.

    Returns:
        the report (as written to ``report.json``) plus ``seconds``; ``report["gate"]["failed"]`` tells the CLI
        its exit code.

    Raises:
        ScoreError: predictions of another protocol or horizon, missing agents (unless ``allow_missing``), bad
            threshold names.
        PredictionsError: an input missing, damaged or inconsistent with its metadata.
        DatasetError: the truth folder is not a dataset, or damaged.
        OutputError: the report folder cannot be written (disk full, read-only); it keeps its last report.
    """
    t0 = time.perf_counter()
    fail_above = dict(fail_above or {})
    _check_thresholds(fail_above)
    if agents not in ("all", "focal"):
        raise ScoreError(f"agents must be 'all' or 'focal', not {agents!r}")
    ds = Dataset.open(truth)
    methods = [load_method(Path(p)) for p in predictions]
    if not methods:
        raise ScoreError("no predictions given")
    _name_methods(methods, labels)
    _check_protocol(methods, ds)
    pred_len = ds.protocol.pred_len
    truth_sha = sha256_file(ds.root / MANIFEST)
    dt_s = _step_seconds(ds)
    predicted = {s for m in methods for s in m.sample_ids.tolist()}
    sel = select_agents(ds, predicted, split=split, agents=agents, min_agents=min_agents)
    if not sel.expected:
        raise ScoreError(f"no agent counts under agents={agents!r}, min_agents={min_agents}, split={split!r} "
                         f"({sel.dropped}); e.g. agents='focal' needs a dataset with focal tracks")
    protocol = {
        "dataset": str(truth), "dataset_format": ds.kind, "dataset_protocol": ds.protocol.to_dict(),
        "obs_len": ds.protocol.obs_len, "pred_len": pred_len, "step_s": dt_s,
        "horizon_s": [round(dt_s * (i + 1), 6) for i in range(pred_len)],
        "agents": agents, "min_agents": min_agents, "split": split, "miss_threshold_m": miss_threshold_m,
        "unit": "metres",
    }
    report: dict[str, Any] = {
        "report_version": REPORT_VERSION, "protocol": protocol, "conventions": CONVENTIONS, "methods": {},
    }
    scored: dict[str, tuple[MethodForecasts, NDArrayFloat, NDArrayFloat, Any]] = {}
    for m in methods:
        keep, counts = _keep_rows(m, sel, allow_missing)
        sub_pred = m.pred[keep]
        truth_xy, log_ids = truth_futures(ds, sel.samples, m.sample_ids[keep], m.track_ids[keep], pred_len)
        bad_truth = ~np.all(np.isfinite(truth_xy), axis=(1, 2))
        counts["agents_incomplete_truth"] = int(bad_truth.sum())
        ok = ~bad_truth
        err = metrics.displacement_errors(sub_pred[ok], truth_xy[ok])
        sids = m.sample_ids[keep][ok]
        _, sample_idx = np.unique(sids, return_inverse=True)
        method_ks = sorted({k for k in (ks or [1, m.num_modes]) if k <= m.num_modes})
        types = m.object_types[keep][ok]
        logs = log_ids[ok]
        entry: dict[str, Any] = {
            "predictor": m.predictor, "checkpoint_ids": m.checkpoint_ids, "source": m.source,
            "metadata": dict(m.meta.to_dict()),
            "same_dataset": None if m.meta.dataset_manifest_sha256 is None
            else m.meta.dataset_manifest_sha256 == truth_sha,
            "num_modes": m.num_modes, "ks": method_ks, "protocol": protocol, "counts": counts,
            "overall": group_metrics(err, sample_idx, method_ks, miss_threshold_m),
            "by_type": {t: group_metrics(err[types == t], sample_idx[types == t], method_ks, miss_threshold_m)
                        for t in sorted(set(types.tolist()))},
            "by_log": {g: group_metrics(err[logs == g], sample_idx[logs == g], method_ks, miss_threshold_m)
                       for g in sorted(set(logs.tolist()))},
        }
        report["methods"][m.name] = entry
        scored[m.name] = (m, err, truth_xy[ok], sids)
    report["gate"] = _gate(report, fail_above)
    report["plots"] = []
    outputs: dict[str, bytes] = {}
    if plots:
        outputs = render_plots(report, scored, ds, plot_samples)
        report["plots"] = list(outputs)
    # Key-sorted, no timings: the same inputs give the same bytes.
    outputs[REPORT_JSON] = (json.dumps(report, indent=2, sort_keys=True) + "\n").encode()
    outputs[REPORT_MD] = render_markdown(report, title).encode()
    write_report_folder(Path(out_dir), outputs, [m.source for m in methods], str(truth))
    return {**report, "seconds": round(time.perf_counter() - t0, 3)}


def _step_seconds(ds: Dataset) -> float:
    """Nominal seconds per step from the logs' frame rates (10 Hz → 0.1, ETH/UCY 2.5 Hz → 0.4); the measured
    median step when no rate is known. Nominal because AV1 clocks jitter around 0.1 s."""
    logs = ds.logs()
    rates = as_numpy(logs.column("frame_rate_hz")).astype(np.float64)
    rates = rates[np.isfinite(rates) & (rates > 0)]
    if len(rates):
        return round(1.0 / float(np.median(rates)), 6)
    dts = as_numpy(logs.column("median_dt_ns")).astype(np.float64)
    dts = dts[dts > 0]
    return round(float(np.median(dts)) / 1e9, 6) if len(dts) else math.nan


def _keep_rows(m: MethodForecasts, sel: Selection, allow_missing: bool) -> tuple[Any, dict[str, int]]:
    """Rows of ``m`` that count, and the bookkeeping counts; fails on missing forecasts unless allowed."""
    pairs = list(zip(m.sample_ids.tolist(), m.track_ids.tolist(), strict=True))
    counts_keep = np.array([p in sel.expected for p in pairs], dtype=bool)
    finite = np.all(np.isfinite(m.pred), axis=(1, 2, 3))
    have = {p for p, f, k in zip(pairs, finite, counts_keep, strict=True) if f and k}
    missing = sel.expected - have
    nan_rows = int((counts_keep & ~finite).sum())
    if missing and not allow_missing:
        example = sorted(missing)[0]
        raise ScoreError(f"{m.source}: predictor {m.predictor!r} has no finite forecast for {len(missing)} of the "
                         f"{len(sel.expected)} agents that count (e.g. sample {example[0]!r} track {example[1]!r}); "
                         "predict them or pass --allow-missing")
    counts = {
        "agents_expected": len(sel.expected),
        "agents_missing": len(missing),
        "agents_nan_forecast": nan_rows,
        "agents_not_counted": int((~counts_keep).sum()),
        **sel.dropped,
    }
    return counts_keep & finite, counts


def _gate(report: dict[str, Any], fail_above: dict[str, float]) -> dict[str, Any]:
    violations = []
    for name, entry in report["methods"].items():
        for key, limit in sorted(fail_above.items()):
            k, _, metric = key.partition(".")
            block = entry["overall"].get(k)
            if block is None:
                continue  # this method has fewer modes than k; nothing to check
            value = block[metric]
            if value > limit:
                violations.append({"method": name, "metric": key, "value": value, "limit": limit})
    return {"thresholds": fail_above, "violations": violations, "failed": bool(violations)}


# ------------------------------------------------------------------------------------------- markdown


def _pair(block: dict[str, Any] | None, a: str = "ade", f: str = "fde") -> str:
    if not block:
        return "—"
    return f"{block[a]:.2f}/{block[f]:.2f}"


def render_markdown(report: dict[str, Any], title: str | None = None) -> str:
    """``report.md``: protocol, then tables in the paper's layout (methods x groups, cells "ADE/FDE")."""
    p = report["protocol"]
    lines = [f"# {title or 'logpipe score report'}", ""]
    lines += [
        f"Dataset `{p['dataset']}` ({p['dataset_format']}), split `{p['split'] or 'predicted samples'}`; "
        f"{p['obs_len']} observed + {p['pred_len']} predicted steps of {p['step_s']} s; agents `{p['agents']}`, "
        f"samples with >= {p['min_agents']} targets; miss threshold {p['miss_threshold_m']} m. "
        "ADE/FDE in metres; ADE is the mean Euclidean distance (not a squared error).", "",
    ]
    methods = report["methods"]
    lines += ["## Overall", "", "| method | K | samples | agents | ADE/FDE (per-agent best-of-K) | joint best-of-K "
              "| Argoverse minADE/minFDE | miss rate |", "|---|---|---|---|---|---|---|---|"]
    for name, e in methods.items():
        o = e["overall"]
        for k in e["ks"]:
            b = o.get(f"k{k}")
            mr = f"{b['miss_rate']:.3f}" if b else "—"
            lines.append(f"| {name} | {k} | {o['samples']} | {o['agents']} | {_pair(b)} | "
                         f"{_pair(b, 'ade_joint', 'fde_joint')} | {_pair(b, 'argo_ade', 'argo_fde')} | {mr} |")
    for group, heading in (("by_type", "Per object type"), ("by_log", "Per log")):
        cols = sorted({g for e in methods.values() for g in e[group]})
        if not cols or len(cols) > 40:
            continue
        lines += ["", f"## {heading} (ADE/FDE, per-agent best-of-K, largest K of each method)", "",
                  "| method | K | " + " | ".join(cols) + " | all |", "|---|---|" + "---|" * (len(cols) + 1)]
        for name, e in methods.items():
            k = f"k{e['ks'][-1]}"
            cells = [_pair(e[group][c].get(k)) if c in e[group] else "—" for c in cols]
            lines.append(f"| {name} | {e['ks'][-1]} | " + " | ".join(cells) + f" | {_pair(e['overall'].get(k))} |")
        lines += ["", "agents: " + "; ".join(
            f"{c} {max(e[group][c]['agents'] for e in methods.values() if c in e[group])}" for c in cols)]
    steps = _horizon_steps(p["horizon_s"])
    lines += ["", "## Error by horizon (metres, mode with the lowest ADE of the first K)", "",
              "| method | K | " + " | ".join(f"{p['horizon_s'][i]:g} s" for i in steps) + " |",
              "|---|---|" + "---|" * len(steps)]
    for name, e in methods.items():
        for k in e["ks"]:
            b = e["overall"].get(f"k{k}")
            if b:
                lines.append(f"| {name} | {k} | " + " | ".join(f"{b['error_by_step'][i]:.2f}" for i in steps) + " |")
    gate = report["gate"]
    if gate["thresholds"]:
        lines += ["", "## Gate", ""]
        lines += [f"FAILED: {v['method']} {v['metric']} = {v['value']:.3f} > {v['limit']}" for v in gate["violations"]]
        if not gate["failed"]:
            lines.append("passed: " + ", ".join(f"{k} <= {v}" for k, v in gate["thresholds"].items()))
    if report.get("plots"):
        lines += ["", "## Plots", ""] + [f"![{Path(f).stem}]({Path(f).name})" for f in report["plots"]]
    lines += ["", "## Counts", "", "| method | " + " | ".join(next(iter(methods.values()))["counts"]) + " |"
              if methods else "", "|---|" + "---|" * len(next(iter(methods.values()))["counts"]) if methods else ""]
    for name, e in methods.items():
        lines.append(f"| {name} | " + " | ".join(str(v) for v in e["counts"].values()) + " |")
    return "\n".join(lines) + "\n"


def _horizon_steps(horizon_s: list[float]) -> list[int]:
    """Step indices at whole seconds (plus the last step): 1 s / 2 s / 3 s for 10 Hz and 2 Hz data."""
    idx = [i for i, t in enumerate(horizon_s) if abs(t - round(t)) < 1e-6]
    last = len(horizon_s) - 1
    if last not in idx:
        idx.append(last)
    return idx


# ---------------------------------------------------------------------------------------------- plots


def _png(fig: Any, dpi: int) -> bytes:
    """The figure as PNG bytes (the report folder commits files it has whole, see ``write_report_folder``)."""
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", dpi=dpi)
    return buffer.getvalue()


def render_plots(report: dict[str, Any], scored: dict[str, tuple[MethodForecasts, NDArrayFloat, NDArrayFloat, Any]],
                 ds: Dataset, plot_samples: int) -> dict[str, bytes]:
    """``horizon.png`` (error vs horizon per method) and ``scenes_<method>.png`` (a grid of samples: history,
    truth and the K forecasts, over the map raster when the dataset has a raster run): file name -> PNG bytes."""
    import matplotlib

    matplotlib.use("Agg")  # files only, no display
    import matplotlib.pyplot as plt

    files: dict[str, bytes] = {}
    horizon = report["protocol"]["horizon_s"]
    fig, ax = plt.subplots(figsize=(7, 4.5))
    colours = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    for i, (name, e) in enumerate(report["methods"].items()):
        for k, style in zip(sorted({e["ks"][0], e["ks"][-1]}), ("-", "--"), strict=False):
            b = e["overall"].get(f"k{k}")
            if b:
                ax.plot(horizon, b["error_by_step"], style, marker=".", color=colours[i % len(colours)],
                        label=f"{name} K={k}")
    ax.set_xlabel("horizon (s)")
    ax.set_ylabel("mean L2 error (m)")
    ax.set_title("Error by horizon (mode with the lowest ADE of the first K)")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7, ncol=2)
    fig.tight_layout()
    files["horizon.png"] = _png(fig, 110)
    plt.close(fig)
    if plot_samples <= 0 or not scored:
        return files
    # The same samples for every method: evenly spread over the sample ids all methods scored.
    common = sorted(set.intersection(*(set(v[3].tolist()) for v in scored.values())))
    if not common:
        return files
    # Prefer samples where someone moves (standing pedestrians make empty-looking panels): the half with the
    # longest true displacement, then evenly spread in id order.
    _m, _e, truth_xy, sids = next(iter(scored.values()))
    travel = np.linalg.norm(truth_xy[:, -1] - truth_xy[:, 0], axis=-1)
    best: dict[str, float] = {}
    for sid, d in zip(sids.tolist(), travel.tolist(), strict=True):
        best[sid] = max(best.get(sid, 0.0), d)
    moving = [s for s in common if best.get(s, 0.0) >= float(np.median([best.get(c, 0.0) for c in common]))]
    pool = moving or common
    pick = sorted({pool[int(i)] for i in np.linspace(0, len(pool) - 1, min(plot_samples, len(pool)))})
    scenes = _scene_samples(ds, pick)
    rasters = _open_rasters(ds)
    for name, (m, _err, _truth, _sids) in scored.items():
        fname, data = _scene_grid(plt, name, m, pick, scenes, rasters)
        files[fname] = data
    return files


def _scene_samples(ds: Dataset, ids: list[str]) -> dict[str, SceneSample]:
    keep = pc.is_in(pc.field("sample_id"), value_set=pa.array(ids, pa.string()))
    return {s.sample_id: s for s in ds.iter_scene_samples(keep)}


def _open_rasters(ds: Dataset) -> Any:
    """The dataset's only finished raster run (``find_raster_run``), or None when there is none, several or an
    unreadable one (plots then show tracks only)."""
    from logpipe.rasters import find_raster_run

    try:
        return find_raster_run(ds.root, None, None)
    except (LogpipeError, KeyError, TypeError, ValueError):
        return None


def _scene_grid(plt: Any, name: str, m: MethodForecasts, pick: list[str], scenes: dict[str, SceneSample],
                rasters: Any) -> tuple[str, bytes]:
    cols = min(3, len(pick))
    rows = math.ceil(len(pick) / cols)
    fig, axes = plt.subplots(rows, cols, figsize=(4.2 * cols, 4.2 * rows), squeeze=False)
    row_of = {(s, t): i for i, (s, t) in enumerate(zip(m.sample_ids.tolist(), m.track_ids.tolist(), strict=True))}
    for ax, sid in zip(axes.ravel(), pick, strict=False):
        s = scenes.get(sid)
        if s is None:
            ax.set_visible(False)
            continue
        affine = None
        if rasters is not None:
            try:
                img, affine = rasters.get(sid)
                ax.imshow(np.asarray(img).max(axis=0), cmap="Greys", vmin=0, vmax=400, origin="upper")
            except KeyError:
                affine = None

        def to_px(xy: NDArrayFloat, a: Any = affine) -> NDArrayFloat:
            if a is None:
                return xy
            out: NDArrayFloat = xy @ a[:, :2].T + a[:, 2]
            return out

        for a in np.flatnonzero(s.target_mask):
            hist = to_px(s.positions[a, : s.obs_len])
            fut = to_px(s.positions[a, s.obs_len - 1 :])
            ax.plot(hist[:, 0], hist[:, 1], "-", color="tab:blue", lw=1.5)
            ax.plot(fut[:, 0], fut[:, 1], "-", color="tab:green", lw=1.5)
            r = row_of.get((sid, s.track_ids[a]))
            if r is not None:
                cur = s.positions[a, s.obs_len - 1]
                for k in range(m.num_modes):
                    path = to_px(np.vstack([cur, m.pred[r, k]]))
                    ax.plot(path[:, 0], path[:, 1], "--", color="tab:red", lw=0.8, alpha=0.6)
        ax.set_title(sid, fontsize=8)
        ax.set_aspect("equal", adjustable="datalim")
        if affine is None:
            ax.grid(alpha=0.3)
        ax.tick_params(labelsize=6)
    for ax in axes.ravel()[len(pick):]:
        ax.set_visible(False)
    fig.suptitle(f"{name} (K={m.num_modes}): history blue, truth green, forecasts red dashed", fontsize=9)
    fig.tight_layout()
    safe = "".join(c if c.isalnum() or c in "-_" else "_" for c in name)
    fname = f"scenes_{safe}.png"
    data = _png(fig, 75)
    plt.close(fig)
    return fname, data
