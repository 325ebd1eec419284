"""``logpipe score``, ``verify`` and ``inspect``: the commands that examine what exists (predictions against
the truth, folders against their manifests, recordings' topics) and exit non-zero when it falls short."""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Annotated

import typer

from logpipe.cli.app import JsonOpt, err, output, user_errors


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

    with user_errors():
        report = api.score(predictions, truth=truth, out=out, split=split, agents=agents, min_agents=min_agents,
                           k=k, miss_threshold=miss_threshold, fail_above=fail_above, label=label,
                           allow_missing=allow_missing, plots=plots, plot_samples=plot_samples)
    if as_json:
        typer.echo(json.dumps(report, indent=2, sort_keys=True))
    else:
        for name, e in report["methods"].items() if not output.quiet else ():
            o = e["overall"]
            cells = ", ".join(f"K={kk} {o[f'k{kk}']['ade']:.3f}/{o[f'k{kk}']['fde']:.3f}" for kk in e["ks"]
                              if o.get(f"k{kk}"))
            print(f"{name}: {o['samples']} samples, {o['agents']} agents, ADE/FDE {cells}", file=sys.stderr)
        if not output.quiet:
            print(f"report: {out / 'report.md'}", file=sys.stderr)
        for v in report["gate"]["violations"]:  # errors: shown with -q too
            print(f"FAILED: {v['method']} {v['metric']} = {v['value']:.4f} > {v['limit']}", file=sys.stderr)
    if report["gate"]["failed"]:
        raise typer.Exit(code=1)



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

    with user_errors():
        report = api.verify(folders, repair=repair, shallow=shallow)
    if as_json:
        typer.echo(json.dumps(report, indent=2, sort_keys=True))
    else:
        for line in report["problems"]:
            typer.echo(line)
        for line in report["leftovers"]:
            typer.echo(f"{line}: uncommitted leftover" + (" (removed)" if repair else " (--repair removes it)"))
        if not output.quiet:  # the problems above are shown with -q too
            err.print(f"{report['files_checked']} files checked in {len(report['folders'])} folders: "
                      f"{len(report['problems'])} problems, {len(report['leftovers'])} leftovers", highlight=False,
                      soft_wrap=True)
    if report["problems"]:
        raise typer.Exit(code=1)


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

    Example: logpipe inspect ../shared/data/rosbags/datmo/intersection.bag
    Example: logpipe inspect run.bag --format toml > map.toml && logpipe ingest run.bag --mapping map.toml -o out/run
    """
    from logpipe import api
    from logpipe.inspect import mapping_toml, render

    if output not in ("human", "toml", "json"):
        raise typer.BadParameter("--format must be human, toml or json")
    with user_errors():
        reports = api.inspect(paths)
        if output == "toml":
            typer.echo(mapping_toml(reports), nl=False)
            return
    if as_json or output == "json":
        typer.echo(json.dumps(reports, indent=2, sort_keys=True, default=str))
    else:
        render(reports)
    if not all(r.get("ok", False) for r in reports):
        raise typer.Exit(code=2)
