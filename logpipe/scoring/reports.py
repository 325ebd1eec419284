"""The score report folder ``logpipe score`` writes: ``report.json``, ``report.md`` and PNG plots, committed
as one artifact (``logpipe.storage.artifact``), and its reader; what the report's metric names mean (``CONVENTIONS``)
and its Markdown form (``render_markdown``). The plots are drawn by ``logpipe.scoring.plots``."""

from __future__ import annotations

import json
from collections.abc import Mapping
from pathlib import Path
from typing import Any, TypedDict

from logpipe import __version__
from logpipe.errors import DatasetError
from logpipe.storage.artifact import ArtifactWriter, FileEntry, Ownership, output_errors, read_manifest
from logpipe.storage.io import atomic_path, sha256_bytes

REPORT_VERSION = 1
REPORT_ARTIFACT = "score_report"
"""``manifest.json`` ``artifact`` value of a score report folder."""
REPORT_JSON = "report.json"
REPORT_MD = "report.md"

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
"""``report.json`` ``conventions``: what each metric key means (``logpipe.scoring.metrics`` computes them)."""


class ScoreProtocol(TypedDict):
    """``report.json`` ``protocol`` (also in every method's entry): what every number was computed under.
    ``dataset_protocol`` is the dataset's ``SampleProtocol.to_dict()`` (open JSON); ``step_s`` and ``horizon_s``
    (each predicted step's horizon) are seconds, ``miss_threshold_m`` metres; ``split`` None scores the predicted
    samples."""

    dataset: str
    dataset_format: str
    dataset_protocol: dict[str, Any]
    obs_len: int
    pred_len: int
    step_s: float
    horizon_s: list[float]
    agents: str
    min_agents: int
    split: str | None
    miss_threshold_m: float
    unit: str


class MethodReport(TypedDict):
    """One method's entry in ``report.json`` ``methods``.

    Open JSON inside: ``metadata`` (the predictions' ``PredictionMeta.to_dict()``); ``counts`` (agent
    bookkeeping by name, including the selection's drop reasons); ``overall`` and each value of ``by_type`` /
    ``by_log`` (by object type / log id) are ``logpipe.scoring.metrics.group_metrics`` blocks: ``samples``,
    ``agents`` and one ``kN`` block of metres (None for a group without agents) per K of ``ks``.
    ``same_dataset``: whether the predictions were made on this dataset's manifest (None: not recorded).
    """

    predictor: str
    checkpoint_ids: list[str]
    source: str
    metadata: dict[str, Any]
    same_dataset: bool | None
    num_modes: int
    ks: list[int]
    protocol: ScoreProtocol
    counts: dict[str, int]
    overall: dict[str, Any]
    by_type: dict[str, dict[str, Any]]
    by_log: dict[str, dict[str, Any]]


class GateViolation(TypedDict):
    """A method whose overall ``metric`` (``kN.METRIC``) is above its ``--fail-above`` limit (metres or a rate)."""

    method: str
    metric: str
    value: float
    limit: float


class Gate(TypedDict):
    """``report.json`` ``gate``: the thresholds asked, their violations, and whether the gate failed (exit 1)."""

    thresholds: dict[str, float]
    violations: list[GateViolation]
    failed: bool


class ScoreReport(TypedDict):
    """``report.json``: methods by label (in input order), the protocol, the metric ``conventions`` (name ->
    meaning), the gate and the plot file names (in the report folder)."""

    report_version: int
    protocol: ScoreProtocol
    conventions: dict[str, str]
    methods: dict[str, MethodReport]
    gate: Gate
    plots: list[str]


class ScoreResult(ScoreReport):
    """What ``score`` returns (``logpipe score --json``): the report plus this call's wall time, seconds."""

    seconds: float


REPORT_OWNED = Ownership([REPORT_JSON, REPORT_MD, "horizon.png", "scenes_*.png"])
"""A report folder's own files: the reports and the plots at its top (never a report nested in it)."""


def write_report_folder(out_dir: Path, outputs: dict[str, bytes], inputs: list[str], truth: str) -> None:
    """Commit ``outputs`` (file name -> bytes) as the report folder's state (``logpipe.storage.artifact``).

    Files whose bytes are already committed are left alone (a rerun over the same inputs writes nothing). A
    committed file about to get other bytes is first dropped from the manifest by a commit of its own, so the
    manifest never names a file whose bytes differ from what it records, whenever a crash comes.

    Raises:
        DatasetError: ``out_dir`` holds another artifact (a dataset, a prediction run).
        OutputError: the disk is full, read-only or not writable; the folder keeps its committed state.
    """
    _refuse_other_artifact(out_dir)
    new: dict[str, FileEntry] = {name: {"bytes": len(data), "sha256": sha256_bytes(data)}
                                 for name, data in outputs.items()}

    def manifest(files: dict[str, FileEntry]) -> dict[str, Any]:
        return {"artifact": REPORT_ARTIFACT, "report_version": REPORT_VERSION, "logpipe_version": __version__,
                "inputs": inputs, "truth": truth, "files": files}

    with output_errors(), ArtifactWriter(out_dir, REPORT_OWNED, REPORT_ARTIFACT) as writer:
        _refuse_other_artifact(out_dir)
        old: dict[str, FileEntry] = dict((writer.manifest or {}).get("files", {}))
        changed = [name for name in outputs if old.get(name) != new[name]]
        if writer.manifest is not None and any(name in old for name in changed):
            writer.commit(manifest({k: v for k, v in old.items() if k not in changed}))
        for name in changed:
            with atomic_path(out_dir / name) as tmp:
                tmp.write_bytes(outputs[name])
        if not writer.is_committed(manifest(new)):
            writer.commit(manifest(new))


def _refuse_other_artifact(out_dir: Path) -> None:
    existing = read_manifest(out_dir, required=False) if out_dir.is_dir() else None
    if existing is not None and existing.get("artifact") != REPORT_ARTIFACT:
        raise DatasetError(f"{out_dir}: holds another logpipe artifact (a {existing.get('artifact') or 'dataset'}), "
                         "not a score report; choose another --out")




def read_report(out_dir: Path) -> ScoreReport:
    """``report.json`` of a committed report folder (checked against its manifest's size).

    Raises:
        DatasetError: not a committed score report, or its ``report.json`` was changed.
    """
    manifest = read_manifest(Path(out_dir))
    assert manifest is not None
    if manifest.get("artifact") != REPORT_ARTIFACT:
        raise DatasetError(f"{out_dir}: not a score report (a {manifest.get('artifact') or 'dataset'})")
    entry = manifest["files"].get(REPORT_JSON)
    data = (Path(out_dir) / REPORT_JSON).read_bytes()
    if entry is None or sha256_bytes(data) != entry["sha256"]:
        raise DatasetError(f"{Path(out_dir) / REPORT_JSON}: differs from its manifest; `logpipe verify` says more")
    report: ScoreReport = json.loads(data)
    return report


def cv_modes(entry: Mapping[str, Any]) -> int:
    """How many leading modes of a method are the constant-velocity forecast (a checkpoint run with
    ``constant_velocity_modes`` C: its K <= C rows are constant velocity's, not the network's); 0 otherwise."""
    return int((entry.get("metadata") or {}).get("constant_velocity_modes") or 0)


def cv_note(name: str, entry: Mapping[str, Any]) -> str | None:
    """One sentence saying that ``name``'s first modes are constant velocity, or None when they are not."""
    c = cv_modes(entry)
    if not c or entry.get("predictor") == "cv":
        return None
    first = "mode 0 is" if c == 1 else f"modes 0-{c - 1} are"
    return (f"{name}: {first} the constant-velocity forecast (constant_velocity_modes: {c}), so its K<={c} "
            f"row{'s are' if c > 1 else ' is'} constant velocity, not the network")


def _pair(block: dict[str, Any] | None, a: str = "ade", f: str = "fde") -> str:
    if not block:
        return "—"
    return f"{block[a]:.2f}/{block[f]:.2f}"


def _overall_table(methods: dict[str, Any]) -> list[str]:
    """``report.md``'s overall table, rows of a method's constant-velocity modes marked, with a note saying so."""
    lines = ["## Overall", "", "| method | K | samples | agents | ADE/FDE (per-agent best-of-K) | joint best-of-K "
             "| Argoverse minADE/minFDE | miss rate |", "|---|---|---|---|---|---|---|---|"]
    for name, e in methods.items():
        o = e["overall"]
        for k in e["ks"]:
            b = o.get(f"k{k}")
            mr = f"{b['miss_rate']:.3f}" if b else "—"
            cv = " (constant velocity)" if cv_note(name, e) and k <= cv_modes(e) else ""
            lines.append(f"| {name} | {k}{cv} | {o['samples']} | {o['agents']} | {_pair(b)} | "
                         f"{_pair(b, 'ade_joint', 'fde_joint')} | {_pair(b, 'argo_ade', 'argo_fde')} | {mr} |")
    notes = [note for name, e in methods.items() if (note := cv_note(name, e))]
    if notes:
        lines += [""] + [f"Note: {note}." for note in notes]
    return lines


def render_markdown(report: ScoreReport, title: str | None = None) -> str:
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
    lines += _overall_table(methods)
    # Each grouping's blocks by method, so the loop below reads them without naming the key.
    groupings = (("Per object type", {name: e["by_type"] for name, e in methods.items()}),
                 ("Per log", {name: e["by_log"] for name, e in methods.items()}))
    for heading, by_method in groupings:
        cols = sorted({g for groups in by_method.values() for g in groups})
        if not cols or len(cols) > 40:
            continue
        lines += ["", f"## {heading} (ADE/FDE, per-agent best-of-K, largest K of each method)", "",
                  "| method | K | " + " | ".join(cols) + " | all |", "|---|---|" + "---|" * (len(cols) + 1)]
        for name, e in methods.items():
            top = f"k{e['ks'][-1]}"
            groups = by_method[name]
            cells = [_pair(groups[c].get(top)) if c in groups else "—" for c in cols]
            lines.append(f"| {name} | {e['ks'][-1]} | " + " | ".join(cells) + f" | {_pair(e['overall'].get(top))} |")
        lines += ["", "agents: " + "; ".join(
            f"{c} {max(groups[c]['agents'] for groups in by_method.values() if c in groups)}" for c in cols)]
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
