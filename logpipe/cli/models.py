"""``logpipe train`` and ``predict``: the commands that fit the forecasting network and run it (or a baseline)."""

from __future__ import annotations

from contextlib import nullcontext
from pathlib import Path
from typing import Annotated, Any

import typer

from logpipe.cli.app import (
    DatasetArg,
    JsonOpt,
    counting_warnings,
    emit,
    next_step,
    progress_mode,
    stage_progress,
    user_errors,
)

DeviceOpt = Annotated[str, typer.Option(
    "--device", help="Where the network runs: auto (CUDA when torch sees a GPU, else the CPU) | cpu | cuda "
    "(autocast in bf16, or fp16 where the GPU lacks bf16).")]


def train(  # noqa: PLR0913  typer command: one parameter per CLI option
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
        "--config", help="TOML/JSON with every hyper-parameter (tables model and train, or residual). Default on "
        "driving data (Argoverse 1/2, CommonRoad, ROS/MCAP vehicles): the shipped driving model's recipe, validated "
        "on data it picks itself (no split given) and compared with CV, Kalman and the adaptive prior; elsewhere the "
        "paper's.")
    ] = None,
    steps: Annotated[int | None, typer.Option("--steps", help="Override train.steps.")] = None,
    seed: Annotated[int | None, typer.Option("--seed", help="Override train.seed.")] = None,
    preset: Annotated[str | None, typer.Option(
        "--preset", help="Train a row of the paper's tables instead: full, v1..v4, baseline (Noise-LSTM) or lstm; "
        "or no_position (the full model without PF, eqs. 1-2); or a social baseline: social_lstm, social_gan_20v, "
        "social_gan_20vp (its settings from the [social_lstm] / [social_gan] table of --config).")
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
        "initialisation. Ignored with --resume. On driving data without --config: the residual checkpoint to "
        "fine-tune from instead of the shipped model (e.g. a fleet's earlier run).")] = None,
    device: DeviceOpt = "auto",
    as_json: JsonOpt = False,
) -> None:
    """Train a predictor: on driving data the shipped driving model's recipe, else the paper's network (Zhu et al.,
    IJCAI 2020), a Table 4 ablation or an LSTM baseline.

    Driving data without --config: the residual driving model, trained from scratch and fine-tuned from the shipped
    one, the better on validation kept; the summary, --json and RUN/MODEL_CARD.md compare it with CV, Kalman, the
    adaptive prior and a CV sampler on the validation data. A config (or --preset) trains the paper's network (or a
    Table 4 ablation / LSTM baseline).

    Example: logpipe train out/fleet --out runs/fleet

    Example: logpipe train out/ethucy --scene eth --out runs/eth --config configs/ethucy.toml

    Example: logpipe train out/av1 out/av2 --out runs/av --config configs/argoverse.toml
    """
    from logpipe import api

    # On a terminal the training loop draws its own bar (with loss and val ADE/FDE), on stdout: not under --json.
    # Elsewhere it reports steps to the plain progress lines.
    terminal = progress_mode() == "bar"
    with (user_errors(as_json), counting_warnings() as logged,
          (nullcontext(None) if terminal else stage_progress("train", "steps")) as advance):
        summary = api.train(dataset, out=out, scene=scene, train_split=train_split, val_split=val_split,
                            config=config, steps=steps, seed=seed, preset=preset, resume=resume,
                            raster_run=raster_run, loader_workers=loader_workers, init_from=init_from,
                            device=device, progress=(not as_json) if advance is None else advance)
    emit(dict(summary), as_json, train_lines, logged)


def train_lines(s: dict[str, Any]) -> list[str]:
    """The human summary of ``train``: steps, the best validation errors, the checkpoints, the next command."""
    datasets = s["dataset"] if isinstance(s["dataset"], list) else [s["dataset"]]
    best = s["best_checkpoint"] or s["last_checkpoint"]
    lines = [f"train: {s['steps']:,} steps on {s['train_samples']} samples in {s['seconds']} s ({s['device']}); "
             f"best validation ADE/FDE {s['best_val_ade']:.3f}/{s['best_val_fde']:.3f} m at step {s['best_step']}"
             + (" (stopped early)" if s["stopped_early"] else ""),
             f"  run: {s['run']} (checkpoints best/ and last/, train_log.jsonl)",
             *s.get("report", []),
             next_step(f"logpipe predict {datasets[0]} --checkpoint {best} --out {s['run']}-pred")]
    return lines


def predict(  # noqa: PLR0913  typer command: one parameter per CLI option
    dataset: DatasetArg,
    out: Annotated[Path, typer.Option("--out", "-o", help="Output folder; rerunning resumes.")],
    checkpoint: Annotated[Path | None, typer.Option(
        "--checkpoint", help="Checkpoint folder (default: the shipped one for the dataset kind, else the Kalman "
        "baseline; the summary says which and why).")] = None,
    predictor: Annotated[str | None, typer.Option(
        "--predictor",
        help="Baseline instead of a checkpoint: cv | linear | kalman | cv_sampler | adaptive_cv.")] = None,
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
        "--workers", "-j", help="Ray actors (0 = one per GPU of the cluster, else one per CPU). Locally: parallel "
        "shard jobs of constant velocity with --no-mcap (0 = one per core); a network on the CPU forecasts in N "
        "processes of --threads threads (default 1) each, the same bytes (0 = one per core when --threads is 0 and "
        "the run is large enough to repay their ~1.5 s start-up: 250 samples per core with the environment net, "
        "1,500 without).")] = 0,
    allow_blank_rasters: Annotated[bool, typer.Option(
        "--allow-blank-rasters", help="Run a checkpoint's environment net even on samples whose raster is blank "
        "(no map for their log, or the centre off it); refused by default.")] = False,
    out_of_distribution: Annotated[str, typer.Option(
        "--out-of-distribution", help="For a checkpoint that records its training data (the residual driving "
        "model): on roads it never trained on, mode 0 (the K = 1 forecast) is the best kinematic baseline of its "
        "training and the model's own modes follow (auto, the default: its corrections did harm on unseen roads); "
        "targets outside its training data are only flagged (warn: no fallback at all), all get that fallback "
        "(fallback), or stop the run (refuse). Column fallback marks each replaced target.")
    ] = "auto",
    as_json: JsonOpt = False,
) -> None:
    """Run a checkpoint (or a baseline) on every sample and write predictions as Parquet and, per log, an MCAP
    with all original channels plus prediction channels (logpipe.Predictions and foxglove.SceneUpdate).

    Example: logpipe predict out/ethucy --filter split=eth/test --out out/pred/eth
    """
    from logpipe import api

    with user_errors(as_json), counting_warnings() as logged, stage_progress("predict", "samples") as advance:
        summary = api.predict(
            dataset, out=out, checkpoint=checkpoint, predictor=predictor, modes=modes, seed=seed,
            noise_scale=noise_scale, constant_velocity_modes=constant_velocity_modes,
            context_max_neighbours=context_max_neighbours, as_trained=as_trained, filters=filters or (),
            inputs=inputs, raster_run=raster_run, raster_images=raster_images, mcap=mcap, batch_size=batch_size,
            threads=threads, device=device, progress=advance, backend=backend, workers=workers,
            allow_blank_rasters=allow_blank_rasters, out_of_distribution=out_of_distribution,
        )
    for warning in summary["warnings"]:  # shown with --json and -q too: a leak must not pass unnoticed
        typer.echo(f"warning: {warning}", err=True)
    emit(summary, as_json, predict_lines, logged)


def predict_lines(s: dict[str, Any]) -> list[str]:
    """The human summary of ``predict``: what was forecast by what, where the table and MCAPs are, what next."""
    out, ds = s["out"], s["dataset"]
    by = s["checkpoint"] or s["predictor"]
    if s.get("already_done"):  # a rerun of a finished run: its totals, not this invocation's zeros
        head = (f"predict: already done: {s['samples_total']:,} samples, {s['targets_total']:,} agents x "
                f"{s['num_modes']} modes by {by} (all {s['shards']} shards committed earlier; checked in "
                f"{s['seconds']} s)")
    else:
        head = (f"predict: {s['samples']:,} samples, {s['targets']:,} agents x {s['num_modes']} modes by {by} in "
                f"{s['seconds']} s" + (f" ({s['shards_skipped_done']} shards already done)"
                                      if s["shards_skipped_done"] else ""))
    lines = [head]
    if s.get("predictor_reason") and not s["predictor_reason"].startswith("--"):  # a default: say why
        lines.append(f"  predictor {s['predictor']}: {s['predictor_reason']}")
    lines.append(f"  predictions: {out}/predictions/*.parquet ({s['rows_total']:,} rows; manifest.json)")
    if s["mcap_files"]:
        lines.append(f"  MCAPs: {out}/mcap/part-*/<log>.mcap ({s['mcap_files']} files; Foxglove: File > Open, "
                     f"3D panel; Rerun: logpipe export {out} --format rrd --out {out}-rrd)")
    lines.append(next_step(f"logpipe score {out} --truth {ds} --out {out}-score"))
    return lines
