"""``logpipe train`` on driving data without ``--config``: the shipped driving default's recipe trained on a fleet's
own logs, validated on data it picks itself, and compared with the kinematic baselines.

Reads top-down: the recipe (the shipped residual checkpoint's config, lengths from the dataset's protocol) → the
validation data (``logpipe.dataset.holdout``: whole recordings where there are enough, else the later part of each
recording; or the ``--train-split``/``--val-split`` given) → two candidates trained alike, from scratch and
fine-tuned from the shipped model (when its architecture fits), the one with the lower validation score kept
(K = 1 FDE + minFDE@K, ``fit``'s own criterion) → the comparison with CV, Kalman, the adaptive prior and the CV
sampler on the validation targets (``compare``) → ``best/``, ``last/``, ``train_log.jsonl``, ``MODEL_CARD.md``
and ``candidates/`` (each candidate's own run) in the run folder.
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable, Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any, cast

import pyarrow as pa
import pyarrow.compute as pc

from logpipe.dataset.holdout import Holdout, choose_holdout
from logpipe.dataset.locations import window_locations
from logpipe.dataset.reader import Dataset
from logpipe.errors import LogpipeError
from logpipe.raster.runs import RasterShards, find_raster_run
from logpipe.storage.io import atomic_open, sha256_file
from logpipe.summaries import DrivingTrainSummary, TrainSummary
from logpipe.types import SceneSample

from ..checkpoint.format import TrainingData, combined_kind, combined_manifest_hash
from ..training.run_folder import run_folder
from .checkpoint import load_residual, save_residual
from .compare import compare, k1_source, not_compared
from .config import ResidualConfig
from .fit import LOG, collect, fit_residual, target_locations
from .meta import read_residual_meta
from .model_card import comparison_lines, model_card
from .ood import tune_baselines


def _runs(datasets: Sequence[Dataset], raster_run: str | None, config: ResidualConfig
          ) -> tuple[list[RasterShards | None], ResidualConfig, list[str]]:
    """Each dataset's raster run, the config (environment net off unless every dataset has a run) and notes."""
    runs = [find_raster_run(ds.root, raster_run, None) for ds in datasets] if config.environment else []
    missing = [str(ds.root) for ds, run in zip(datasets, runs, strict=False) if run is None]
    if config.environment and missing:
        note = (f"no raster run in {', '.join(missing)}: trained without the map (environment net off); "
                "`logpipe rasterise DATASET --rotate` first to use it")
        return [None] * len(datasets), replace(config, environment=False), [note]
    return runs or [None] * len(datasets), config, []


def _samples(datasets: Sequence[Dataset], runs: Sequence[RasterShards | None], ids: Sequence[Sequence[str]]
             ) -> list[SceneSample]:
    """The ``SceneSample``s of the sample ids ``ids`` of each dataset, with their rasters."""
    out: list[SceneSample] = []
    for ds, run, wanted in zip(datasets, runs, ids, strict=True):
        if not wanted:
            continue
        if run is not None:
            have = set(run.index.column("sample_id").to_pylist())
            missing = [s for s in wanted if s not in have]
            if missing:
                raise LogpipeError(f"{run.run_dir}: raster run lacks {len(missing)} of the dataset's samples (e.g. "
                                   f"{missing[0]}; re-indexed since?); re-run `logpipe rasterise {ds.root} --rotate "
                                   "--force`")
        for sample in ds.iter_scene_samples(pc.is_in(pc.field("sample_id"), value_set=pa.array(list(wanted)))):
            if run is not None:
                sample.raster, sample.world_to_raster = run.get(sample.sample_id)
            out.append(sample)
    return out


def _given_splits(datasets: Sequence[Dataset], train_split: str, val_split: str) -> Holdout:
    """The holdout of splits given on the command line (whole logs)."""
    train_ids: list[list[str]] = []
    val_ids: list[list[str]] = []
    val_logs: list[list[str]] = []
    for ds in datasets:
        samples = ds.samples()
        for split, into in ((train_split, train_ids), (val_split, val_ids)):
            logs = ds.logs_in_split(split)
            into.append(samples.filter(pc.is_in(samples.column("log_id"), pa.array(logs))).column("sample_id")
                        .to_pylist())
            if into is val_ids:
                val_logs.append(logs)
    return Holdout("given", train_ids, val_ids, val_logs, 0)


def _candidates(config: ResidualConfig, start: Path | None) -> tuple[dict[str, Path | None], str]:
    """The starts to try (``scratch``, and ``finetune`` from ``start``, the shipped model or ``--init-from``, when
    its architecture fits) and, when fine-tuning is not tried, why."""
    if start is None:
        return {"scratch": None}, "no shipped driving model to fine-tune"
    theirs = read_residual_meta(start).config
    if replace(theirs, **_training_keys(config)) != config:
        return {"scratch": None}, (f"the start's inputs differ ({theirs.obs_len}+{theirs.pred_len} steps, "
                                   f"environment net {theirs.environment}; here {config.obs_len}+{config.pred_len}, "
                                   f"{config.environment}): trained from scratch only")
    return {"scratch": None, "finetune": start}, ""


def _training_keys(config: ResidualConfig) -> dict[str, Any]:
    """The config keys a fine-tuning may change without changing the architecture or inputs."""
    return {k: getattr(config, k) for k in ("epochs", "batch_size", "lr", "weight_decay", "seed", "score_weight",
                                             "max_targets_per_window", "val_every", "patience", "num_threads")}


def train_fleet(  # noqa: PLR0913  the command's options one to one
    datasets: Sequence[Dataset], out_dir: Path, *, shipped: Path | None, train_split: str | None,
    val_split: str | None, raster_run: str | None = None, seed: int | None = None, paper_only: Sequence[str] = (),
    init_from: Path | None = None, progress: Callable[[int], None] | None = None,
) -> DrivingTrainSummary:
    """Train the driving recipe on ``datasets`` into ``out_dir`` (see the module docstring); ``shipped``: the
    shipped residual checkpoint (its config is the recipe, its weights the fine-tuning start); ``init_from``:
    another residual checkpoint to fine-tune from instead (a fleet's earlier run, or a model that never saw these
    roads); ``seed``: the recipe's seed replaced; ``paper_only``: options given that only the paper's network takes
    (an error).

    Raises:
        LogpipeError: such options, a training split without a validation split.
    """
    started = time.perf_counter()
    if paper_only:
        raise LogpipeError(f"{', '.join(paper_only)}: only for the paper's network (--config or --preset); the "
                           "driving recipe trains minutes-long runs from the start")
    if train_split is not None and val_split is None:
        raise LogpipeError("the driving recipe validates (it picks its start on validation): give --val-split too, "
                           "or neither split to let it choose")
    recipe = read_residual_meta(shipped).config if shipped is not None else ResidualConfig()
    recipe = recipe if seed is None else replace(recipe, seed=seed)
    protocol = datasets[0].protocol
    runs, config, notes = _runs(datasets, raster_run,
                                replace(recipe, obs_len=protocol.obs_len, pred_len=protocol.pred_len))
    if train_split is None:
        holdout = choose_holdout([ds.logs() for ds in datasets], [ds.samples() for ds in datasets])
    else:
        holdout = _given_splits(datasets, train_split, str(val_split))
    train, windows = collect(_samples(datasets, runs, holdout.train_ids), config)
    val_samples = _samples(datasets, runs, holdout.val_ids) if holdout.how != "none" else []
    val, val_windows = collect(val_samples, config) if val_samples else (None, None)
    val_locations = target_locations([d.logs() for d in datasets], val_samples, val_windows)
    starts, why_not = _candidates(config, init_from or shipped)
    if val is None:  # nothing to choose on: the start trained on more data, when there is one
        starts = {"finetune": starts["finetune"]} if "finetune" in starts else starts
    train_logs = [sorted({s.rsplit(":", 1)[0] for s in ids}) for ids in holdout.train_ids]
    training_data = TrainingData.of_logs(list(zip(datasets, train_logs, holdout.val_logs, strict=True)),
                                         train_split or f"auto ({holdout.how})", val_split or f"auto ({holdout.how})")
    manifests = combined_manifest_hash([sha256_file(d.root / "manifest.json") for d in datasets])
    kind = combined_kind([d.kind for d in datasets])
    locations = window_locations([d.logs() for d in datasets],
                                 [s.rsplit(":", 1)[0] for ids in holdout.train_ids for s in ids])
    baselines = tune_baselines(train, seed=config.seed)  # the same training targets for every candidate
    with run_folder(out_dir):
        fits = {name: fit_residual(train, windows, val, config, out_dir / "candidates" / name, dataset_kind=kind,
                                   manifest_hash=manifests, training_data=training_data, init_from=start,
                                   locations=locations, baselines=baselines, progress=progress,
                                   val_locations=val_locations)
                for name, start in starts.items()}
        scores = {name: r.best_metrics["fde"] + r.best_metrics[f"min_fde_{config.modes + 1}"]
                  for name, r in fits.items() if val is not None}
        chosen = min(scores, key=lambda name: scores[name]) if scores else next(iter(fits))
        net, meta = load_residual(fits[chosen].best_checkpoint)
        shipped_net = load_residual(shipped)[0] if "finetune" in starts and shipped is not None else None
        comparison = (compare(net, val, train, meta.ood["baselines"], shipped=shipped_net, seed=config.seed)
                      if val is not None else not_compared(holdout.describe()))
        k1 = k1_source(comparison)
        meta.ood |= {"k1_source": k1["source"], "k1_reason": k1["reason"]}
        if shipped_net is not None and shipped is not None:
            comparison["shipped_model_saw_validation_logs"] = _seen_by(shipped, datasets, holdout.val_logs)
        save_residual(out_dir / "best", net, meta)
        save_residual(out_dir / "last", *load_residual(fits[chosen].last_checkpoint))
        with atomic_open(out_dir / LOG, "w") as log:
            log.write((out_dir / "candidates" / chosen / LOG).read_text())
        start_record = {"chosen": chosen, "validation_scores": {k: round(v, 4) for k, v in scores.items()},
                        "score": f"K = 1 FDE + minFDE@{config.modes + 1} on the validation targets (m)",
                        "finetune_not_tried": why_not or None,
                        "finetune_from": str(init_from or shipped) if "finetune" in starts else None}
        summary: dict[str, Any] = dict(_summary(datasets, out_dir, holdout, fits[chosen], config, started,
                                                train_split, val_split))
        summary |= {"recipe": "residual driving model (the shipped default's config)", "validation": holdout.record(),
                    "start": start_record, "comparison": comparison, "notes": notes,
                    "train_targets": len(train), "val_targets": len(val) if val is not None else 0, "k1": k1,
                    "k1_by_location": meta.ood.get("k1_by_location", {}),
                    "model_card": str(out_dir / "MODEL_CARD.md"), "seconds": round(time.perf_counter() - started, 1)}
        summary["report"] = [*comparison_lines(summary), f"  model card: {out_dir / 'MODEL_CARD.md'}"]
        with atomic_open(out_dir / "MODEL_CARD.md", "w") as card:
            card.write(model_card(summary))
        with atomic_open(out_dir / "train_summary.json", "w") as record:
            record.write(json.dumps(summary, indent=2, sort_keys=True) + "\n")
    return cast(DrivingTrainSummary, summary)


def _seen_by(shipped: Path, datasets: Sequence[Dataset], val_logs: Sequence[Sequence[str]]) -> int:
    """How many validation logs come from recordings the shipped model was trained or validated on (by sha256)."""
    data = read_residual_meta(shipped).training_data
    if data is None:
        return 0
    known = set(data.train_sources) | set(data.val_sources)
    seen = 0
    for ds, logs in zip(datasets, val_logs, strict=True):
        table = ds.logs()
        source = dict(zip(table.column("log_id").to_pylist(), table.column("source_sha256").to_pylist(), strict=True))
        seen += sum(str(source.get(log)) in known for log in logs)
    return seen


def _summary(datasets: Sequence[Dataset], out_dir: Path, holdout: Holdout, result: Any, config: ResidualConfig,
             started: float, train_split: str | None, val_split: str | None) -> TrainSummary:
    """The keys every ``logpipe train`` summary has."""
    several = len(datasets) > 1
    k = config.modes + 1
    return cast(TrainSummary, {
        "dataset": [str(d.root) for d in datasets] if several else str(datasets[0].root), "run": str(out_dir),
        "train_split": train_split or f"auto ({holdout.how})", "val_split": val_split or f"auto ({holdout.how})",
        "train_samples": sum(map(len, holdout.train_ids)), "val_samples": sum(map(len, holdout.val_ids)),
        "steps": result.steps, "best_step": result.best_step,
        "best_val_ade": result.best_metrics.get("ade", float("nan")),
        "best_val_fde": result.best_metrics.get("fde", float("nan")), "stopped_early": result.stopped_early,
        "best_checkpoint": str(out_dir / "best"), "last_checkpoint": str(out_dir / "last"),
        "train_samples_per_s": round(result.targets_per_s, 1), "raster_run": None, "init_from": None,
        "environment_net": config.environment, "device": "cpu", "seconds": round(time.perf_counter() - started, 1),
        "best_val_min_fde": result.best_metrics.get(f"min_fde_{k}", float("nan")),
    })

