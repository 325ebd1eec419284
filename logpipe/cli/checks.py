"""``logpipe score``, ``verify`` and ``inspect``: the commands that examine what exists (predictions against
the truth, folders against their manifests, recordings' topics) and exit non-zero when it falls short."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated, Any

import typer

from logpipe.cli.app import JsonOpt, counting_warnings, emit, next_step, say, stage_progress, user_errors


def score(  # noqa: PLR0913  typer command: one parameter per CLI option
    predictions: Annotated[list[Path], typer.Argument(help="Prediction run folders (logpipe predict --out) or "
                                                      "predictions files; one method each.",
                                                      show_default=False)],
    truth: Annotated[Path, typer.Option("--truth", help="Dataset folder the predictions were made on.")],
    out: Annotated[Path, typer.Option("--out", "-o", help="Report folder.")] = Path("out/score"),
    split: Annotated[str | None, typer.Option(
        "--split", help="Score exactly this split's samples (eth/test, hash/test); every counted agent must "
                        "be predicted. Default: the predicted samples.")] = None,
    agents: Annotated[str, typer.Option("--agents", help="all: every protocol target | focal: the focal track.")
                      ] = "all",
    min_agents: Annotated[int, typer.Option(
        "--min-agents", help="Only samples with at least this many targets (Social-GAN's loader: 2).")] = 1,
    k: Annotated[list[int] | None, typer.Option(
        "--k", help="K values to report, repeatable (default: 1 and each method's own K).")] = None,
    miss_threshold: Annotated[float, typer.Option("--miss-threshold", help="Argoverse miss threshold, metres.")
                              ] = 2.0,
    fail_above: Annotated[list[str] | None, typer.Option(
        "--fail-above", help="Gate kN.METRIC=VALUE, repeatable (k1.ade=0.6, k6.miss_rate=0.2): exit 1 when any "
                             "method's overall value is above.")] = None,
    label: Annotated[list[str] | None, typer.Option(
        "--label", help="Method names in input order, one per folder/file (default: the predictor; the folder "
                        "name where predictors collide).")] = None,
    allow_missing: Annotated[bool, typer.Option(
        "--allow-missing", help="Score what is there when counted agents lack a forecast.")] = False,
    plots: Annotated[bool, typer.Option("--plots/--no-plots", help="Write horizon.png and scenes_*.png.")] = True,
    plot_samples: Annotated[int, typer.Option("--plot-samples", help="Samples per scene grid.")] = 6,
    as_json: JsonOpt = False,
) -> None:
    """Score predictions against a dataset: report.json, report.md and PNG plots; exit 1 when a --fail-above
    threshold is crossed.

    Example: logpipe score out/pred/cv out/pred/eth --truth out/ethucy --split eth/test --min-agents 2
    """
    from logpipe import api

    # No units to count: the reporter's heartbeat says it is running (in CI logs, every interval).
    with user_errors(as_json), counting_warnings() as logged, stage_progress("score", "methods"):
        report = api.score(predictions, truth=truth, out=out, split=split, agents=agents, min_agents=min_agents,
                           k=k, miss_threshold=miss_threshold, fail_above=fail_above, label=label,
                           allow_missing=allow_missing, plots=plots, plot_samples=plot_samples)
    emit(dict(report), as_json, lambda r: score_lines(r, out), logged)
    if not as_json:
        say([f"FAILED: {v['method']} {v['metric']} = {v['value']:.4f} > {v['limit']}"  # errors: shown with -q too
             for v in report["gate"]["violations"]])
    if report["gate"]["failed"]:
        raise typer.Exit(code=1)


def score_lines(report: dict[str, Any], out: Path) -> list[str]:
    """The human summary of ``score``: ADE/FDE per method, where the report and plots are, what to open next."""
    from logpipe.scoring.reports import cv_modes, cv_note

    lines = []
    for name, e in report["methods"].items():
        o = e["overall"]
        cv = cv_modes(e) if cv_note(name, e) else 0
        cells = ", ".join(f"K={kk}{' (constant velocity)' if kk <= cv else ''} "
                          f"{o[f'k{kk}']['ade']:.3f}/{o[f'k{kk}']['fde']:.3f}" for kk in e["ks"] if o.get(f"k{kk}"))
        lines.append(f"score: {name}: {o['samples']} samples, {o['agents']} agents, ADE/FDE (m) {cells}")
        if note := cv_note(name, e):
            lines.append(f"  {note}")
    pngs = sorted(p.name for p in out.glob("*.png"))
    lines.append(f"  report: {out / 'report.md'} (report.json" + (f", {', '.join(pngs)})" if pngs else ")"))
    lines.append(next_step(f"open {out / 'report.md'}", "the table in the paper's layout and the plots"))
    return lines



def verify(
    folders: Annotated[list[Path], typer.Argument(
        help="Artifact folders: a dataset, a raster run (DATASET/rasters/<run>), a prediction run, a score report.",
        show_default=False)],
    repair: Annotated[bool, typer.Option(
        "--repair", help="Remove uncommitted leftovers (staging and temp files, files no manifest names).")] = False,
    shallow: Annotated[bool, typer.Option("--shallow", help="Check sizes only, not sha256 and row counts.")] = False,
    as_json: JsonOpt = False,
) -> None:
    """Check folders against their manifests: every committed file's size, sha256 and row count. Prints one line
    per problem and exits 1 when any is found. A dataset's raster runs are checked with it."""
    from logpipe import api

    with user_errors(as_json):
        report = api.verify(folders, repair=repair, shallow=shallow)
    if not as_json:  # the problems are shown with -q too, on stdout as before
        for line in report["problems"]:
            typer.echo(line)
        for line in report["leftovers"]:
            typer.echo(f"{line}: uncommitted leftover" + (" (removed)" if repair else " (--repair removes it)"))
    emit(dict(report), as_json, lambda r: verify_lines(r, repair))
    if report["problems"]:
        raise typer.Exit(code=1)


def verify_lines(report: dict[str, Any], repair: bool) -> list[str]:
    """The human summary of ``verify``: what was checked, what was found, what to do about it."""
    lines = [f"verify: {report['files_checked']} files checked in {len(report['folders'])} folders: "
             f"{len(report['problems'])} problems, {len(report['leftovers'])} leftovers"]
    folders = " ".join(report["folders"])
    if report["problems"]:
        lines.append(next_step("re-run the command that wrote the folder (it rewrites what does not match), or "
                               "delete the folder and run it again"))
    elif report["leftovers"] and not repair:
        lines.append(next_step(f"logpipe verify {folders} --repair", "removes the uncommitted leftovers"))
    else:
        lines.append("  every committed file matches its manifest; nothing to do")
    return lines


def inspect(
    paths: Annotated[list[Path], typer.Argument(help="Bags (ROS1 .bag, ROS2 folders), MCAP files, AV2 logs.")],
    output: Annotated[str, typer.Option(
        "--format", help="human: tables | toml: the detected mapping as the file `logpipe ingest --mapping` takes "
        "(on stdout) | json: as --json.")] = "human",
    as_json: JsonOpt = False,
) -> None:
    """List topics/channels with types, counts, time span and rate, and which of them logpipe can turn
    into tracks with which mapping (like `ros2 bag info` / `mcap info`). Exit code 2 if any input is unreadable
    (with --format toml: if no mapping is detected).

    Example: logpipe inspect tests/data/rosbags/datmo/intersection.bag

    Example: logpipe inspect run.bag --format toml > map.toml && logpipe ingest run.bag --mapping map.toml -o out/run
    """
    from logpipe import api
    from logpipe.inspect import mapping_toml, render

    if output not in ("human", "toml", "json"):
        raise typer.BadParameter("--format must be human, toml or json")
    with user_errors(as_json or output == "json"):
        reports = api.inspect(paths)
        if output == "toml":
            typer.echo(mapping_toml(reports), nl=False)
            return
    if as_json or output == "json":
        typer.echo(json.dumps(reports, indent=2, sort_keys=True, default=str))
    else:
        render(reports)
        if not _quiet():
            say(inspect_lines(reports))
    if not all(r.get("ok", False) for r in reports):
        raise typer.Exit(code=2)


def _quiet() -> bool:
    from logpipe.cli.app import output as global_output

    return global_output.quiet


def inspect_lines(reports: list[dict[str, Any]]) -> list[str]:
    """The next command after ``inspect``: ingest with the detected mapping, or write one to edit."""
    paths = " ".join(str(r["path"]) for r in reports)
    if not all(r.get("ok") for r in reports):
        return ["  fix or leave out the unreadable inputs above"]
    if all(r.get("mapping") is not None or r.get("format") == "argoverse2" for r in reports):
        return [next_step(f"logpipe ingest {paths} --out out/NAME", "uses the detected mapping")]
    return [next_step(f"logpipe inspect {paths} --format toml > map.toml",
                      "edit the topics, then logpipe ingest ... --mapping map.toml")]


def export(
    paths: Annotated[list[Path], typer.Argument(
        help="A dataset or prediction run folder (its mcap/ files), or MCAP files.", show_default=False)],
    out: Annotated[Path, typer.Option("--out", "-o", help="Folder for the exported files (one per log).")],
    fmt: Annotated[str, typer.Option("--format", "-f", help="rrd: a Rerun recording per log.")] = "rrd",
    as_json: JsonOpt = False,
) -> None:
    """Export the MCAPs of a dataset or prediction run for another viewer: --format rrd writes one Rerun recording
    per log (agents as boxes, history, truth, forecasts, lanes, the raster image and a legend), which `rerun FILE`
    opens. Needs rerun-sdk (pip install 'logpipe[rerun]').

    Example: logpipe export out/pred --format rrd --out out/rrd && rerun out/rrd/20.rrd
    """
    from logpipe import api

    with user_errors(as_json), stage_progress("export", "files"):
        summary = api.export(paths, out=out, format=fmt)
    emit(dict(summary), as_json, export_lines)


def export_lines(s: dict[str, Any]) -> list[str]:
    """The human summary of ``export``: files written, what they draw, how to open one."""
    totals: dict[str, int] = {}
    for f in s["files"]:
        for kind, n in f["drawn"].items():
            totals[kind] = totals.get(kind, 0) + n
    drawn = ", ".join(f"{n:,} {kind.replace('_', ' ')}" for kind, n in sorted(totals.items()))
    first = s["files"][0]["rrd"] if s["files"] else f"{s['out']}/LOG.rrd"
    return [f"export: {len(s['files'])} Rerun recordings in {s['out']} in {s['seconds']} s "
            f"({drawn or 'nothing drawn'})",
            next_step(f"rerun {first}", "the viewer rerun-sdk installs")]
