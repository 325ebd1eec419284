"""``logpipe score``: ADE/FDE reports for one or more prediction runs against a dataset's ground truth.

Reads top-down: open each input (a ``logpipe predict`` output folder, or a predictions file; one method each,
read by ``logpipe.scoring.method_forecasts`` with its protocol, K and horizon from its metadata), label it and check
its protocol against the dataset's → decide which agents count and look up their true futures
(``logpipe.scoring.agents``) → per-step L2 errors → metrics per method (``logpipe.scoring.metrics.group_metrics``),
overall / per object type / per log, for every K asked → threshold gate for CI → ``report.json``,
``report.md`` (``logpipe.scoring.reports``), PNG plots (``logpipe.scoring.plots``), committed as one artifact folder
(``manifest.json``, ``logpipe.storage.artifact``).

Conventions are those of ``logpipe.scoring.metrics`` (ADE = mean Euclidean distance in metres; per-agent and joint
best-of-K; the Argoverse min-FDE mode with its ADE and a 2.0 m miss rate). The protocol is written next to
every method's numbers so a number never travels without it.
"""

from __future__ import annotations

import json
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from logpipe.dataset.reader import Dataset
from logpipe.errors import ScoreError
from logpipe.scoring import metrics
from logpipe.scoring.agents import Agents, Selection, select_agents, step_seconds, truth_futures
from logpipe.scoring.method_forecasts import MethodForecasts, check_protocol, load_method, name_methods
from logpipe.scoring.plots import ScoredMethod, render_plots
from logpipe.scoring.reports import (
    CONVENTIONS,
    REPORT_JSON,
    REPORT_MD,
    REPORT_VERSION,
    Gate,
    GateViolation,
    MethodReport,
    ScoreProtocol,
    ScoreReport,
    ScoreResult,
    render_markdown,
    write_report_folder,
)
from logpipe.storage.artifact import MANIFEST
from logpipe.storage.io import sha256_file


def _check_thresholds(fail_above: dict[str, float]) -> None:
    allowed = {"ade", "fde", "ade_joint", "fde_joint", "argo_ade", "argo_fde", "miss_rate"}
    for key in fail_above:
        k, _, name = key.partition(".")
        if not (k.startswith("k") and k[1:].isdigit() and name in allowed):
            raise ScoreError(f"--fail-above {key!r}: expected kN.METRIC with METRIC one of {sorted(allowed)}, "
                             "e.g. k1.ade=0.6 or k6.miss_rate=0.2")


def score(  # noqa: PLR0913  stage entry: keyword options mirror `logpipe score` one to one
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
) -> ScoreResult:
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
    methods = _load_methods(predictions, labels, ds)
    truth_sha = sha256_file(ds.root / MANIFEST)
    sel = _select(ds, methods, split=split, agents=agents, min_agents=min_agents)
    protocol = _protocol_block(ds, truth, agents=agents, min_agents=min_agents, split=split,
                               miss_threshold_m=miss_threshold_m)
    entries: dict[str, MethodReport] = {}
    scored: dict[str, ScoredMethod] = {}
    for m in methods:
        entries[m.name], scored[m.name] = _score_method(
            m, ds, sel, ks=ks, miss_threshold_m=miss_threshold_m, allow_missing=allow_missing, protocol=protocol,
            truth_sha=truth_sha)
    # ``plots`` is filled by ``_render``, once the plots are drawn.
    report: ScoreReport = {
        "report_version": REPORT_VERSION, "protocol": protocol, "conventions": CONVENTIONS, "methods": entries,
        "gate": _gate(entries, fail_above), "plots": [],
    }
    outputs = _render(report, scored, ds, plot_samples if plots else None, title)
    write_report_folder(Path(out_dir), outputs, [m.source for m in methods], str(truth))
    return {**report, "seconds": round(time.perf_counter() - t0, 3)}


def _load_methods(predictions: Sequence[Path], labels: Sequence[str] | None, ds: Dataset) -> list[MethodForecasts]:
    """Every input read as one method, labelled (``name_methods``) and checked against ``ds``'s protocol."""
    methods = [load_method(Path(p)) for p in predictions]
    if not methods:
        raise ScoreError("no predictions given")
    name_methods(methods, labels)
    check_protocol(methods, ds)
    return methods


def _select(ds: Dataset, methods: Sequence[MethodForecasts], *, split: str | None, agents: Agents,
            min_agents: int) -> Selection:
    """The agents that count (``scoring.agents.select_agents``) among the samples any method predicted."""
    predicted = {s for m in methods for s in m.sample_ids.tolist()}
    sel = select_agents(ds, predicted, split=split, agents=agents, min_agents=min_agents)
    if not sel.expected:
        raise ScoreError(f"no agent counts under agents={agents!r}, min_agents={min_agents}, split={split!r} "
                         f"({sel.dropped}); e.g. agents='focal' needs a dataset with focal tracks")
    return sel


def _render(report: ScoreReport, scored: dict[str, ScoredMethod], ds: Dataset, plot_samples: int | None,
            title: str | None) -> dict[str, bytes]:
    """The report folder's files: the plots (none when ``plot_samples`` is None; listed in ``report["plots"]``),
    ``report.json`` and ``report.md``."""
    report["plots"] = []
    outputs: dict[str, bytes] = {}
    if plot_samples is not None:
        outputs = render_plots(dict(report), scored, ds, plot_samples)
        report["plots"] = list(outputs)
    # Key-sorted, no timings: the same inputs give the same bytes.
    outputs[REPORT_JSON] = (json.dumps(report, indent=2, sort_keys=True) + "\n").encode()
    outputs[REPORT_MD] = render_markdown(report, title).encode()
    return outputs


def _protocol_block(ds: Dataset, truth: Path, *, agents: Agents, min_agents: int, split: str | None,
                    miss_threshold_m: float) -> ScoreProtocol:
    """``report.json`` ``protocol``: what every number of the report was computed under."""
    pred_len = ds.protocol.pred_len
    dt_s = step_seconds(ds)
    return {
        "dataset": str(truth), "dataset_format": ds.kind, "dataset_protocol": ds.protocol.to_dict(),
        "obs_len": ds.protocol.obs_len, "pred_len": pred_len, "step_s": dt_s,
        "horizon_s": [round(dt_s * (i + 1), 6) for i in range(pred_len)],
        "agents": agents, "min_agents": min_agents, "split": split, "miss_threshold_m": miss_threshold_m,
        "unit": "metres",
    }


def _score_method(m: MethodForecasts, ds: Dataset, sel: Selection, *, ks: Sequence[int] | None,
                  miss_threshold_m: float, allow_missing: bool, protocol: ScoreProtocol,
                  truth_sha: str) -> tuple[MethodReport, ScoredMethod]:
    """One method's ``report.json`` entry (metrics overall, per type, per log) and what its plots need."""
    keep, counts = _keep_rows(m, sel, allow_missing)
    sub_pred = m.pred[keep]
    truth_xy, log_ids = truth_futures(ds, sel.samples, m.sample_ids[keep], m.track_ids[keep], ds.protocol.pred_len)
    bad_truth = ~np.all(np.isfinite(truth_xy), axis=(1, 2))
    counts["agents_incomplete_truth"] = int(bad_truth.sum())
    ok = ~bad_truth
    err = metrics.displacement_errors(sub_pred[ok], truth_xy[ok])
    sids = m.sample_ids[keep][ok]
    _, sample_idx = np.unique(sids, return_inverse=True)
    method_ks = sorted({k for k in (ks or [1, m.num_modes]) if k <= m.num_modes})
    types = m.object_types[keep][ok]
    logs = log_ids[ok]
    entry: MethodReport = {
        "predictor": m.predictor, "checkpoint_ids": m.checkpoint_ids, "source": m.source,
        "metadata": dict(m.meta.to_dict()),
        "same_dataset": None if m.meta.dataset_manifest_sha256 is None
        else m.meta.dataset_manifest_sha256 == truth_sha,
        "num_modes": m.num_modes, "ks": method_ks, "protocol": protocol, "counts": counts,
        "overall": metrics.group_metrics(err, sample_idx, method_ks, miss_threshold_m),
        "by_type": {t: metrics.group_metrics(err[types == t], sample_idx[types == t], method_ks, miss_threshold_m)
                    for t in sorted(set(types.tolist()))},
        "by_log": {g: metrics.group_metrics(err[logs == g], sample_idx[logs == g], method_ks, miss_threshold_m)
                   for g in sorted(set(logs.tolist()))},
    }
    return entry, ScoredMethod(forecasts=m, truth=truth_xy[ok], sample_ids=sids)


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


def _gate(methods: dict[str, MethodReport], fail_above: dict[str, float]) -> Gate:
    """``report.json`` ``gate``: every method's overall value above its ``--fail-above`` limit."""
    violations: list[GateViolation] = []
    for name, entry in methods.items():
        for key, limit in sorted(fail_above.items()):
            k, _, metric = key.partition(".")
            block = entry["overall"].get(k)
            if block is None:
                continue  # this method has fewer modes than k; nothing to check
            value = block[metric]
            if value > limit:
                violations.append({"method": name, "metric": key, "value": value, "limit": limit})
    return {"thresholds": fail_above, "violations": violations, "failed": bool(violations)}
