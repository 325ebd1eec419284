"""The ``logpipe`` command: a thin Typer layer over the stage functions.

Every command prints a human summary, or with ``--json`` one JSON object on stdout (for CI). Errors that
concern the user's input print one line naming file, line/record and field, and exit with code 2.
"""

from __future__ import annotations

import json
import logging
import os
import sys
from collections.abc import Callable, Iterator
from contextlib import contextmanager, nullcontext
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any, TextIO

import typer
from rich.console import Console

from logpipe import __version__
from logpipe.errors import LogpipeError
from logpipe.progress import Mode, ProgressReporter
from logpipe.types import PROTOCOLS

app = typer.Typer(
    name="logpipe",
    help="Offline pipeline for multi-agent trajectory forecasting: ingest → rasterise → train → predict → score.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
    # Rich help panels only on a terminal: piped (CI logs, `| less`) rich cuts option names to fit 80
    # columns (`--constant-velo…`); click's plain help wraps the text and never cuts a name.
    rich_markup_mode="rich" if sys.stdout.isatty() else None,
)
err = Console(stderr=True)


@dataclass
class _Output:
    """What the global ``-q`` / ``-v`` options chose (set by the app callback before every command)."""

    quiet: bool = False
    verbose: int = 0


_output = _Output()


def _version(value: bool) -> None:
    if value:
        typer.echo(f"logpipe {__version__}")
        raise typer.Exit


@app.callback()
def main(
    version: Annotated[bool, typer.Option("--version", callback=_version, is_eager=True,
                                          help="Print the version and exit.")] = False,
    quiet: Annotated[bool, typer.Option(
        "--quiet", "-q", help="No progress and no human summary; errors and warnings are still shown.")] = False,
    verbose: Annotated[int, typer.Option(
        "--verbose", "-v", count=True, help="Also log details (per-batch timings); -vv for debug logging.")] = 0,
) -> None:
    """Offline pipeline for multi-agent trajectory forecasting.

    Progress goes to stderr: a bar on a terminal, elsewhere one line every 5 s (LOGPIPE_PROGRESS_INTERVAL
    seconds). stdout carries only --json output.
    """
    if quiet and verbose:
        raise typer.BadParameter("--quiet and --verbose exclude each other")
    _output.quiet, _output.verbose = quiet, verbose
    _configure_logging(logging.DEBUG if verbose > 1 else logging.INFO if verbose else logging.WARNING)


class _StderrHandler(logging.StreamHandler[TextIO]):
    """Writes to the current ``sys.stderr``: a progress bar redirects it to print above the bar."""

    def emit(self, record: logging.LogRecord) -> None:
        # Assigned, not ``setStream``: that flushes the previous stream, which may be closed by now (a test
        # runner's captured stderr from an earlier command in this process).
        self.stream = sys.stderr
        super().emit(record)


def _configure_logging(level: int) -> None:
    """logpipe's own loggers at ``level`` on stderr, one plain line per record (never wrapped)."""
    logger = logging.getLogger("logpipe")
    for handler in [h for h in logger.handlers if isinstance(h, _StderrHandler)]:
        logger.removeHandler(handler)  # one handler, however often the app runs in this process (tests)
    handler = _StderrHandler()
    handler.setFormatter(logging.Formatter("%(levelname)s %(name)s: %(message)s"))
    logger.addHandler(handler)
    logger.setLevel(level)


def _progress_mode() -> Mode:
    """``off`` with -q; a bar when stderr is a terminal that can redraw; else plain lines (CI, pipes)."""
    if _output.quiet:
        return "off"
    return "bar" if sys.stderr.isatty() and os.environ.get("TERM") != "dumb" else "lines"


@contextmanager
def _user_errors() -> Iterator[None]:
    """Turn logpipe's own errors into one clear line and exit code 2 (no traceback)."""
    try:
        yield
    except LogpipeError as exc:
        err.print(f"[bold red]error:[/] {exc}", highlight=False, soft_wrap=True)
        raise typer.Exit(code=2) from None
    except OSError as exc:
        # Disk full, read-only or forbidden outputs: the writers commit only by the manifest swap, so the
        # folder still holds its previous state; one line, not a traceback.
        from logpipe.artifact import os_error_message

        err.print(f"[bold red]error:[/] {os_error_message(exc)}", highlight=False, soft_wrap=True)
        raise typer.Exit(code=2) from None


def _progress(label: str, unit: str) -> ProgressReporter:
    """The progress callback of one stage run (the stage reports the total once it knows it). On stderr, so
    it runs with --json too: a CI job that parses stdout still shows progress in its log. The bar is redrawn
    by the reporter, not by rich's refresh thread: with no thread running, the stage's worker pool can fork
    from this process (see ``logpipe.executor``), ~0.4 s of a core less per run."""
    return ProgressReporter(label, unit, _progress_mode(), console=err)


def _emit(summary: dict[str, Any], as_json: bool, human: Callable[[dict[str, Any]], None]) -> None:
    if as_json:
        typer.echo(json.dumps(summary, indent=2, sort_keys=True))
    elif not _output.quiet:
        human(summary)


ProtocolOpt = Annotated[str | None, typer.Option("--protocol", help=f"Sample preset: {', '.join(PROTOCOLS)} "
                                                 "(default: the format's own).")]
ObsOpt = Annotated[int | None, typer.Option("--obs", help="Observed steps per sample (overrides the preset).")]
PredOpt = Annotated[int | None, typer.Option("--pred", help="Predicted steps per sample.")]
StrideOpt = Annotated[int | None, typer.Option("--stride", help="Steps between sliding windows.")]
MinTargetsOpt = Annotated[int | None, typer.Option(
    "--min-targets", help="Keep windows with at least this many fully observed agents (Social-GAN: 2).")]
TargetsOpt = Annotated[str | None, typer.Option(
    "--targets", help="fully_observed | fully_observed_no_ego (the ego's future is an input) | focal")]
TargetTypesOpt = Annotated[str | None, typer.Option(
    "--target-types", help="Only agents of these types are targets, comma-separated (vehicle,bus_truck).")]
WindowOpt = Annotated[str | None, typer.Option(
    "--window", help="sliding (a window every --stride steps) | first (one window at step 0, Argoverse).")]
JsonOpt = Annotated[bool, typer.Option("--json", help="Print a JSON summary on stdout (for CI).")]
DatasetArg = Annotated[Path, typer.Argument(help="Dataset folder written by `logpipe ingest`.")]


def _print_summary(summary: dict[str, Any]) -> None:
    """The human form of a summary that has no shorter one: indented JSON on stderr, written as is (rich
    would wrap long lines at the console width, 80 columns off a terminal, and break the JSON)."""
    typer.echo(json.dumps(summary, indent=2, default=str), err=True)


@app.command()
def ingest(
    inputs: Annotated[list[Path], typer.Argument(help="Input files or folders.", show_default=False)],
    out: Annotated[Path, typer.Option("--out", "-o", help="Dataset folder to create or extend.")],
    fmt: Annotated[str | None, typer.Option("--format", "-f", help="Input format (default: detected).")] = None,
    protocol: ProtocolOpt = None,
    obs: ObsOpt = None,
    pred: PredOpt = None,
    stride: StrideOpt = None,
    min_targets: MinTargetsOpt = None,
    targets: TargetsOpt = None,
    target_types: TargetTypesOpt = None,
    window: WindowOpt = None,
    on_error: Annotated[str, typer.Option(
        "--on-error", help="fail: stop at the first bad input, write nothing. skip: quarantine bad inputs.")
    ] = "fail",
    mcap: Annotated[bool, typer.Option("--mcap/--no-mcap", help="Also write each log as an MCAP file.")] = True,
    workers: Annotated[int, typer.Option("--workers", "-j", help="Worker processes (0 = all cores).")] = 0,
    backend: Annotated[str, typer.Option("--backend", help="local | ray")] = "local",
    batch_files: Annotated[int | None, typer.Option("--batch-files", help="Inputs per shard.")] = None,
    mapping: Annotated[Path | None, typer.Option(
        "--mapping", help="Bags/MCAP: TOML or YAML file naming the ego and agent topics (see README).")] = None,
    overrides: Annotated[list[str] | None, typer.Option(
        "--set", help="Bags/MCAP: mapping override KEY=VALUE, repeatable (ego=/odom, agent=/red_pose, map=lab).")
    ] = None,
    hz: Annotated[float | None, typer.Option(
        "--hz", help="Bags/MCAP: resample tracks to this rate (default 10; 0 keeps original times).")] = None,
    allow_empty: Annotated[bool, typer.Option(
        "--allow-empty", help="Bags/MCAP/AV2: a log without tracks is kept empty instead of being an error.")
    ] = False,
    as_json: JsonOpt = False,
) -> None:
    """Turn logs (Argoverse 1 CSV, ETH/UCY, ApolloScape, ...) into canonical Parquet shards, a sample index
    and one MCAP per log. Re-running skips inputs already ingested (by content hash).

    Example: logpipe ingest ../shared/data/argoverse1/data --out out/av1
    Example: logpipe ingest run.bag --out out/run --set ego=/odom --set agent=/red_pose --hz 10
    """
    from logpipe import api

    with _user_errors(), _progress("ingest", "inputs") as advance:
        summary = api.ingest(
            inputs, out=out, format=fmt, protocol=protocol, obs=obs, pred=pred, stride=stride,
            min_targets=min_targets, targets=targets, target_types=target_types, window=window, on_error=on_error,
            mcap=mcap,
            workers=workers, backend=backend, batch_files=batch_files, mapping=mapping, overrides=overrides or (),
            hz=hz, allow_empty=allow_empty, progress=advance,
        )
    _emit(dict(summary), as_json, _print_ingest)


def _print_ingest(s: dict[str, Any]) -> None:
    err.print(
        f"[bold]{s['dataset']}[/] ({s['format']}): {s['inputs_ingested']} inputs ingested, "
        f"{s['inputs_skipped_already_ingested']} already there, {len(s['quarantined'])} quarantined; "
        f"{s['logs']} logs, {s['rows']} rows, {s['samples']} samples in {s['seconds']} s. "
        f"Dataset totals: {s['totals']['logs']} logs, {s['totals']['rows']} rows, {s['totals']['samples']} samples.",
        highlight=False, soft_wrap=True,  # one line in a CI log, not cut at 80 columns
    )
    for q in s["quarantined"]:
        e = q["error"]
        where = e["file"] + (f":{e['line']}" if e["line"] else "") + (f" field '{e['field']}'" if e["field"] else "")
        err.print(f"  quarantined {where}: {e['reason']}", highlight=False, soft_wrap=True)
    _print_notes(s)


def _print_notes(s: dict[str, Any]) -> None:
    """The lines that explain the counts: inputs that were copies, and why logs gave no sample."""
    from logpipe.api import summary_notes

    for line in summary_notes(s):
        err.print(f"  {line}", highlight=False, soft_wrap=True)


def _print_index(s: dict[str, Any]) -> None:
    err.print(f"{s['dataset']}: {s['samples']} samples ({s['protocol']})", highlight=False, soft_wrap=True)
    _print_notes(s)


@app.command()
def index(
    dataset: DatasetArg,
    protocol: ProtocolOpt = None,
    obs: ObsOpt = None,
    pred: PredOpt = None,
    stride: StrideOpt = None,
    min_targets: MinTargetsOpt = None,
    targets: TargetsOpt = None,
    target_types: TargetTypesOpt = None,
    window: WindowOpt = None,
    as_json: JsonOpt = False,
) -> None:
    """Rebuild the sample index of a dataset with another protocol (no re-ingest).

    Example: logpipe index out/ethucy --min-targets 2
    """
    from logpipe import api

    with _user_errors(), _progress("index", "logs") as advance:
        summary = api.index(dataset, protocol=protocol, obs=obs, pred=pred, stride=stride, min_targets=min_targets,
                            targets=targets, target_types=target_types, window=window, progress=advance)
    _emit(dict(summary), as_json, _print_index)


@app.command()
def rasterise(
    dataset: DatasetArg,
    maps: Annotated[list[Path] | None, typer.Option(
        "--maps", help="Folder(s) holding map files (AV1 *_lane_centerlines.npz, AV2 log_map_archive_*.json, "
        "Lanelet2 .osm, AV1 vector-map .xml); repeatable.")] = None,
    map_file: Annotated[list[str] | None, typer.Option(
        "--map", help="MAP_ID=FILE: the map file of logs with that map id (e.g. lab=lab.osm); repeatable.")
    ] = None,
    centre: Annotated[str, typer.Option("--centre", help="ego (focal when a log has no ego) | focal")] = "ego",
    rotate: Annotated[bool, typer.Option("--rotate/--no-rotate", help="Rotate to the centre's heading.")] = False,
    preview: Annotated[int, typer.Option("--preview", help="Write PNG previews of the first N samples.")] = 0,
    size: Annotated[int, typer.Option("--size", help="Raster side, pixels.")] = 224,
    extent: Annotated[float, typer.Option("--extent", help="Raster side, metres.")] = 100.0,
    channels: Annotated[str | None, typer.Option(
        "--channels", help="Comma-separated channel names (default: all drawn layers).")] = None,
    shard_size: Annotated[int, typer.Option("--shard-size", help="Samples per .npy shard.")] = 256,
    force: Annotated[bool, typer.Option("--force", help="Replace a run made from other data or maps.")] = False,
    workers: Annotated[int | None, typer.Option(
        "--workers", "-j", help="Shards rendered at once (0 = all cores; default 1 locally, all with ray); "
        "each worker loads the maps it needs.")] = None,
    backend: Annotated[str, typer.Option(
        "--backend", help="local | ray (ray: DATASET must be on a file system every node shares)")] = "local",
    as_json: JsonOpt = False,
) -> None:
    """Draw one ego-centred map raster per prediction sample (224x224 over 100 m by default) into
    DATASET/rasters/<run>/, with the settings in the run manifest. Re-running skips finished shards.

    Example: logpipe rasterise out/av1 --maps ../shared/data/argoverse1/maps --rotate --preview 4
    """
    from logpipe import api

    with _user_errors(), _progress("rasterise", "samples") as advance:
        summary = api.rasterise(dataset, maps=maps, map_file=map_file, centre=centre, rotate=rotate, preview=preview,
                                size=size, extent=extent, channels=channels, shard_size=shard_size, force=force,
                                workers=workers, backend=backend, progress=advance)
    _emit(summary, as_json, _print_summary)


DeviceOpt = Annotated[str, typer.Option(
    "--device", help="Where the network runs: auto (CUDA when torch sees a GPU, else the CPU) | cpu | cuda "
    "(autocast in bf16, or fp16 where the GPU lacks bf16).")]


@app.command()
def train(
    dataset: Annotated[list[Path], typer.Argument(
        help="Dataset folder(s) written by `logpipe ingest`; several train one model on all of them (splits "
             "apply in each, samples in this order).", show_default=False)],
    out: Annotated[Path, typer.Option("--out", "-o", help="Run folder (checkpoints best/ and last/, log).")],
    scene: Annotated[str | None, typer.Option(
        "--scene", help="ETH/UCY leave-one-scene-out: train on SCENE/train, validate on SCENE/val.")] = None,
    train_split: Annotated[str | None, typer.Option(
        "--train-split", help="Training logs: a folder split (eth/train), hash/train (default), all, a log id, "
                              "or terms joined by + and - (eth/train-biwi_hotel_train holds out HOTEL).")] = None,
    val_split: Annotated[str | None, typer.Option(
        "--val-split", help="Validation logs, same syntax (default: the matching /val split; needed when "
                            "--train-split has + or -); 'none' disables.")] = None,
    config: Annotated[Path | None, typer.Option(
        "--config", help="TOML/JSON with every hyper-parameter (tables model and train); defaults: the paper's.")
    ] = None,
    steps: Annotated[int | None, typer.Option("--steps", help="Override train.steps.")] = None,
    seed: Annotated[int | None, typer.Option("--seed", help="Override train.seed.")] = None,
    preset: Annotated[str | None, typer.Option(
        "--preset", help="Train a row of the paper's tables instead: full, v1..v4, baseline (Noise-LSTM) or lstm; "
        "or no_position (the full model without PF, eqs. 1-2).")
    ] = None,
    resume: Annotated[bool, typer.Option("--resume", help="Continue from OUT/last.")] = False,
    raster_run: Annotated[str | None, typer.Option(
        "--raster-run", help="Raster run under DATASET/rasters/ for the environment net (default: the only one; "
                             "with several datasets, in each).")
    ] = None,
    loader_workers: Annotated[int, typer.Option(
        "--loader-workers", help="Stream training samples from the shards with a DataLoader of N workers "
        "(0: cut them all into memory first, exact resume).")] = 0,
    init_from: Annotated[Path | None, typer.Option(
        "--init-from", help="Start from this checkpoint folder: the parameters it has are copied (a Noise-LSTM "
        "checkpoint warm-starts the full model, whose feature inputs start at zero); the rest keep their "
        "initialisation. Ignored with --resume.")] = None,
    device: DeviceOpt = "auto",
    as_json: JsonOpt = False,
) -> None:
    """Train the Zhu et al. predictor (or a Table 4 ablation / LSTM baseline via the config) on a dataset.

    Example: logpipe train out/ethucy --scene eth --out runs/eth --config configs/ethucy.toml
    Example: logpipe train out/av1 out/av2 --out runs/av --config configs/argoverse.toml
    """
    from logpipe import api

    # On a terminal the training loop draws its own bar (with loss and val ADE/FDE), on stdout: not under --json.
    # Elsewhere it reports steps to the plain progress lines.
    terminal = _progress_mode() == "bar"
    with _user_errors(), (nullcontext(None) if terminal else _progress("train", "steps")) as advance:
        summary = api.train(dataset, out=out, scene=scene, train_split=train_split, val_split=val_split,
                            config=config, steps=steps, seed=seed, preset=preset, resume=resume,
                            raster_run=raster_run, loader_workers=loader_workers, init_from=init_from,
                            device=device, progress=(not as_json) if advance is None else advance)
    _emit(summary, as_json, _print_summary)


@app.command()
def predict(
    dataset: DatasetArg,
    out: Annotated[Path, typer.Option("--out", "-o", help="Output folder; rerunning resumes.")],
    checkpoint: Annotated[Path | None, typer.Option(
        "--checkpoint", help="Checkpoint folder (default: the shipped one for the dataset kind).")] = None,
    predictor: Annotated[str | None, typer.Option(
        "--predictor", help="Baseline instead of a checkpoint: cv | linear | kalman | cv_sampler.")] = None,
    modes: Annotated[int | None, typer.Option(
        "--modes", "-k", help="K futures per agent (default 20 for pedestrians, 6 for vehicles).")] = None,
    seed: Annotated[int, typer.Option("--seed", help="Seed of the sampled futures.")] = 0,
    noise_scale: Annotated[float | None, typer.Option(
        "--noise-scale", help="Std of the network's noise z (1 = as trained); the spread of the K futures. Default: "
        "the checkpoint's inference settings (chosen on validation by make reproduce-*), else 1.")] = None,
    constant_velocity_modes: Annotated[int | None, typer.Option(
        "--constant-velocity-modes", help="How many of the K futures are the constant-velocity forecast (the "
        "network's corrections held at zero). Default: the checkpoint's inference settings, else its training "
        "config (0 unless trained with it).")] = None,
    context_max_neighbours: Annotated[int | None, typer.Option(
        "--context-max-neighbours", help="At most this many of the agents within the checkpoint's context radius "
        "(the nearest) in each target's context. Default: the checkpoint's inference settings, else all.")] = None,
    as_trained: Annotated[bool, typer.Option(
        "--as-trained", help="Ignore the checkpoint's stored inference settings: noise scale 1 and its training "
        "config (the results files' 'as trained' rows).")] = False,
    filters: Annotated[list[str] | None, typer.Option(
        "--filter", help="log=ID[,ID] | split=eth/test | time=START_NS:END_NS | type=pedestrian[,..]; repeatable.")
    ] = None,
    inputs: Annotated[list[Path] | None, typer.Option(
        "--inputs", help="Root(s) the bags/MCAP files were ingested from (their channels are copied through).")
    ] = None,
    raster_run: Annotated[str | None, typer.Option("--raster-run", help="Folder under DATASET/rasters/.")] = None,
    raster_images: Annotated[bool, typer.Option(
        "--raster-images/--no-raster-images", help="Add each sample's raster to the MCAP as an image.")] = True,
    mcap: Annotated[bool, typer.Option("--mcap/--no-mcap", help="Write one MCAP per log.")] = True,
    batch_size: Annotated[int, typer.Option("--batch-size", help="Samples per forward pass.")] = 64,
    threads: Annotated[int, typer.Option(
        "--threads", help="torch threads (0 = all cores; with ray, per actor and default 1).")] = 0,
    device: DeviceOpt = "auto",
    backend: Annotated[str, typer.Option(
        "--backend", help="local | ray: forecast on Ray actors (DATASET on a file system every node shares); "
        "outputs are written here, the same bytes as a local run with the same --threads.")] = "local",
    workers: Annotated[int, typer.Option(
        "--workers", "-j", help="Ray actors (0 = one per GPU of the cluster, else one per CPU); ray only.")] = 0,
    as_json: JsonOpt = False,
) -> None:
    """Run a checkpoint (or a baseline) on every sample and write predictions as Parquet and, per log, an MCAP
    with all original channels plus prediction channels (logpipe.Predictions and foxglove.SceneUpdate).

    Example: logpipe predict out/ethucy --filter split=eth/test --out out/pred/eth
    """
    from logpipe import api

    with _user_errors(), _progress("predict", "samples") as advance:
        summary = api.predict(
            dataset, out=out, checkpoint=checkpoint, predictor=predictor, modes=modes, seed=seed,
            noise_scale=noise_scale, constant_velocity_modes=constant_velocity_modes,
            context_max_neighbours=context_max_neighbours, as_trained=as_trained, filters=filters or (),
            inputs=inputs, raster_run=raster_run, raster_images=raster_images, mcap=mcap, batch_size=batch_size,
            threads=threads, device=device, progress=advance, backend=backend, workers=workers,
        )
    for warning in summary["warnings"]:  # shown with --json and -q too: a leak must not pass unnoticed
        typer.echo(f"warning: {warning}", err=True)
    _emit(summary, as_json, _print_summary)


@app.command()
def score(
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

    with _user_errors():
        report = api.score(predictions, truth=truth, out=out, split=split, agents=agents, min_agents=min_agents,
                           k=k, miss_threshold=miss_threshold, fail_above=fail_above, label=label,
                           allow_missing=allow_missing, plots=plots, plot_samples=plot_samples)
    if as_json:
        typer.echo(json.dumps(report, indent=2, sort_keys=True))
    else:
        for name, e in report["methods"].items() if not _output.quiet else ():
            o = e["overall"]
            cells = ", ".join(f"K={kk} {o[f'k{kk}']['ade']:.3f}/{o[f'k{kk}']['fde']:.3f}" for kk in e["ks"]
                              if o.get(f"k{kk}"))
            print(f"{name}: {o['samples']} samples, {o['agents']} agents, ADE/FDE {cells}", file=sys.stderr)
        if not _output.quiet:
            print(f"report: {out / 'report.md'}", file=sys.stderr)
        for v in report["gate"]["violations"]:  # errors: shown with -q too
            print(f"FAILED: {v['method']} {v['metric']} = {v['value']:.4f} > {v['limit']}", file=sys.stderr)
    if report["gate"]["failed"]:
        raise typer.Exit(code=1)



@app.command()
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

    with _user_errors():
        report = api.verify(folders, repair=repair, shallow=shallow)
    if as_json:
        typer.echo(json.dumps(report, indent=2, sort_keys=True))
    else:
        for line in report["problems"]:
            typer.echo(line)
        for line in report["leftovers"]:
            typer.echo(f"{line}: uncommitted leftover" + (" (removed)" if repair else " (--repair removes it)"))
        if not _output.quiet:  # the problems above are shown with -q too
            err.print(f"{report['files_checked']} files checked in {len(report['folders'])} folders: "
                      f"{len(report['problems'])} problems, {len(report['leftovers'])} leftovers", highlight=False,
                      soft_wrap=True)
    if report["problems"]:
        raise typer.Exit(code=1)


@app.command()
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
    with _user_errors():
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


if __name__ == "__main__":  # pragma: no cover
    app()
