"""The Python API: one function per ``logpipe`` command, taking the command's options as keyword arguments.

Each function does what its command does and returns the summary the command prints with ``--json`` (a dict);
it raises a ``logpipe.errors.LogpipeError`` subclass where the command prints one error line and exits with
code 2 (``SourceError`` for a bad input, naming file, line and field; ``DatasetError``, ``OutputError``, ...).
The CLI (``logpipe.cli``) is a thin layer over these functions, so both check and resolve options the same way.

Every path may be a ``str`` or a ``pathlib.Path``; options that repeat on the command line take a sequence.
Names follow the CLI's options (``--min-targets`` is ``min_targets``); ``--set`` is ``overrides``, ``--map``
is ``map_file``, ``--filter`` is ``filters``. ``ingest``, ``index``, ``rasterise``, ``train``, ``predict`` and
``score`` are also ``logpipe.<name>``; ``verify`` and ``inspect`` share their names with modules of the package,
so they are called as ``logpipe.api.verify`` and ``logpipe.api.inspect``.

Example::

    import logpipe

    summary = logpipe.ingest("tests/data/ethucy", out="out/ethucy", mcap=False)
    print(summary["inputs_ingested"], summary["duplicates"], summary["samples"])
    logpipe.predict("out/ethucy", out="out/pred/cv", predictor="cv", mcap=False)
    report = logpipe.score(["out/pred/cv"], truth="out/ethucy", out="out/score")
    print(report["methods"]["cv"]["overall"]["k1"]["ade"])  # metres

Importing this module is cheap: the stages (and torch, pyarrow) are imported by the function that needs them.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from typing import TYPE_CHECKING, Any, cast

from logpipe.errors import LogpipeError, QuarantineLimitError
from logpipe.options import (
    StrPath,
    adapter_options,
    as_path,
    as_paths,
    check_choice,
    gates,
    map_files,
    names,
    optional_path,
    sample_protocol,
)
from logpipe.summaries import (
    ExportSummary,
    IndexSummary,
    IngestSummary,
    RasteriseSummary,
    TrainSummary,
    VerifyReport,
    quarantine_failure,
)

if TYPE_CHECKING:  # its module loads the storage layer; the API imports it only in score (cheap `import logpipe`)
    from logpipe.scoring.reports import ScoreResult

Progress = Callable[[int], None]
"""Called with the number of items (inputs, samples) each finished batch covered."""


def ingest(  # noqa: PLR0913  public API: keyword options mirror `logpipe ingest` one to one
    inputs: StrPath | Sequence[StrPath],
    *,
    out: StrPath,
    format: str | None = None,
    protocol: str | None = None,
    obs: int | None = None,
    pred: int | None = None,
    stride: int | None = None,
    min_targets: int | None = None,
    targets: str | None = None,
    target_types: str | Sequence[str] | None = None,
    window: str | None = None,
    on_error: str = "fail",
    mcap: bool = True,
    workers: int = 0,
    backend: str = "local",
    batch_files: int | None = None,
    mapping: StrPath | None = None,
    overrides: Sequence[str] = (),
    hz: float | None = None,
    allow_empty: bool = False,
    retry_quarantined: bool = False,
    max_quarantined: int | None = None,
    progress: Progress | None = None,
) -> IngestSummary:
    """``logpipe ingest``: input logs → the dataset folder ``out`` (track shards, logs and samples tables,
    one MCAP per log unless ``mcap=False``). Rerunning skips inputs already ingested (by sha256).

    Args:
        inputs: input files or folders.
        out: dataset folder to create or extend.
        format: input format (default: detected from the first input).
        protocol: sample preset (``ethucy``, ``apolloscape``, ``argoverse``, ``argoverse2``; default: the
            format's own); ``obs``/``pred``/``stride``/``min_targets``/``targets``/``target_types``/``window``
            (``sliding``: a window every ``stride`` steps; ``first``: one at step 0) override it.
        on_error: ``fail`` (the first bad input stops the run, nothing is written) or ``skip`` (quarantine).
        retry_quarantined: read again the inputs an earlier run quarantined (after fixing them or the mapping),
            with this call's options; otherwise a rerun skips them like inputs already ingested.
        max_quarantined: with ``on_error="skip"``, fail (after the commit) when more inputs than this are
            quarantined; a run that quarantines every new input fails whatever it is.
        mcap: also write each log as an MCAP file.
        workers: processes (0 = all cores); ``backend``: ``local`` or ``ray``; ``batch_files``: inputs per shard.
        mapping: bags/MCAP: TOML or YAML mapping file (``logpipe inspect --format toml`` writes one);
            ``overrides``: ``KEY=VALUE`` strings merged over it (the CLI's ``--set``).
        hz: bags/MCAP: resample tracks to this rate (default 10; 0 keeps the original times).
        allow_empty: bags/MCAP/AV2: keep a log without tracks empty instead of failing.
        progress: called with the number of inputs each finished batch covered.

    Raises:
        SourceError: a bad input (with ``on_error="fail"``), naming file, line and field.
        QuarantineLimitError: ``on_error="skip"`` quarantined every new input, or more than ``max_quarantined``
            (what was ingested is committed; the error's ``summary`` is the run's).
        LogpipeError: a bad option, no inputs found; ``DatasetError`` when ``out`` holds another dataset.

    Example::

        s = logpipe.ingest("tests/data/ethucy", out="/tmp/ethucy", mcap=False)
        s["inputs_found"], s["duplicates"]          # (3, 1): hotel/train holds a copy of an eth/train file
        s["duplicate_inputs"][0]["same_as"]         # 'eth/train/crowds_zara01_train.txt'
    """
    from logpipe.stages.ingest import IngestOptions
    from logpipe.stages.ingest import ingest as run_ingest

    roots = as_paths(inputs)
    if not roots:
        raise LogpipeError("give at least one input file or folder")
    check_choice("--on-error", on_error, ("fail", "skip"))
    check_choice("--backend", backend, ("local", "ray"))
    own = None
    if protocol is None:  # overrides alone change the input format's own preset, not a generic 8 + 12 one
        from logpipe.formats import adapter_class, detect

        own = adapter_class(format or detect(roots[0])).default_protocol
    options = IngestOptions(
        out=as_path(out), format=format,
        protocol=sample_protocol(protocol, obs=obs, pred=pred, stride=stride, min_targets=min_targets,
                                 targets=targets, target_types=target_types, window=window, default=own),
        on_error="skip" if on_error == "skip" else "fail", write_mcap=mcap, workers=workers,
        backend="ray" if backend == "ray" else "local", batch_files=batch_files,
        adapter_options=adapter_options(mapping, overrides, hz, allow_empty), retry_quarantined=retry_quarantined,
    )
    if max_quarantined is not None and max_quarantined < 0:
        raise LogpipeError(f"--max-quarantined must be >= 0, got {max_quarantined}")
    summary = run_ingest(roots, options, progress=progress)
    failure = quarantine_failure(summary, max_quarantined)
    if failure is not None:
        raise QuarantineLimitError(failure, summary)
    return cast(IngestSummary, summary)


def index(  # noqa: PLR0913  public API: keyword options mirror `logpipe index` one to one
    dataset: StrPath,
    *,
    protocol: str | None = None,
    obs: int | None = None,
    pred: int | None = None,
    stride: int | None = None,
    min_targets: int | None = None,
    targets: str | None = None,
    target_types: str | Sequence[str] | None = None,
    window: str | None = None,
    progress: Progress | None = None,
) -> IndexSummary:
    """``logpipe index``: rebuild the sample index of ``dataset`` with another protocol (no re-ingest); the
    overrides change the dataset's current protocol unless ``protocol`` names a preset. ``progress`` is called
    with the number of logs each shard held.

    Raises:
        LogpipeError: no protocol option given, an unknown preset; ``DatasetError``: not a dataset.

    Example::

        s = logpipe.index("/tmp/ethucy", obs=400, pred=400)
        s["logs_without_samples"]   # {'no agent observed over the whole window': 2, 'too short for 400+400 steps': 1}
    """
    from logpipe.dataset.reader import Dataset
    from logpipe.stages.index import reindex

    folder = as_path(dataset)
    chosen = sample_protocol(protocol, obs=obs, pred=pred, stride=stride, min_targets=min_targets, targets=targets,
                             target_types=target_types, window=window, default=Dataset.open(folder).protocol)
    if chosen is None:
        raise LogpipeError("give --protocol or at least one of --obs/--pred/--stride/--min-targets/--targets"
                           "/--target-types/--window")
    return cast(IndexSummary, reindex(folder, chosen, progress=progress))


def rasterise(  # noqa: PLR0913  public API: keyword options mirror `logpipe rasterise` one to one
    dataset: StrPath,
    *,
    maps: StrPath | Sequence[StrPath] | None = None,
    map_file: Sequence[str] | Mapping[str, StrPath] | None = None,
    centre: str = "ego",
    rotate: bool = False,
    preview: int = 0,
    size: int = 224,
    extent: float = 100.0,
    channels: str | Sequence[str] | None = None,
    shard_size: int = 256,
    force: bool = False,
    workers: int | None = None,
    backend: str = "local",
    progress: Progress | None = None,
) -> RasteriseSummary:
    """``logpipe rasterise``: one ego-centred map raster per sample into ``DATASET/rasters/<run>/``.

    Args:
        maps: folder(s) holding map files; ``map_file``: ``MAP_ID=FILE`` strings or ``{map_id: file}``.
        centre: ``ego`` (focal when a log has no ego) or ``focal``; ``rotate``: to the centre's heading.
        size: raster side, pixels; ``extent``: raster side, metres; ``channels``: names (default: all).
        workers: shards rendered at once (0 = all cores; default 1 locally, all with ``backend="ray"``).

    Raises:
        LogpipeError: a bad option, missing maps; ``DatasetError``: not a dataset.

    Example::

        logpipe.rasterise("out/av1", maps="../shared/data/argoverse1/maps", rotate=True, preview=4)
    """
    from logpipe.maps import MapSource
    from logpipe.raster.rasteriser import DEFAULT_CHANNELS, RasterSpec
    from logpipe.stages.rasterise import rasterise_dataset

    check_choice("--backend", backend, ("local", "ray"))
    files = map_files(map_file)
    try:
        spec = RasterSpec(size_px=size, extent_m=extent, rotate=rotate, channels=names(channels) or DEFAULT_CHANNELS)
    except ValueError as err:
        raise LogpipeError(str(err)) from None
    summary: RasteriseSummary = rasterise_dataset(
        as_path(dataset), MapSource(roots=tuple(as_paths(maps)), files=files), centre=centre, rotate=rotate,
        preview=preview, spec=spec, shard_size=shard_size, force=force, progress=progress,
        workers=workers if workers is not None else (0 if backend == "ray" else 1),
        backend="ray" if backend == "ray" else "local",
    )
    return summary


def train(  # noqa: PLR0913  public API: keyword options mirror `logpipe train` one to one
    dataset: StrPath | Sequence[StrPath],
    *,
    out: StrPath,
    scene: str | None = None,
    train_split: str | None = None,
    val_split: str | None = None,
    config: StrPath | None = None,
    steps: int | None = None,
    seed: int | None = None,
    preset: str | None = None,
    resume: bool = False,
    raster_run: str | None = None,
    loader_workers: int = 0,
    init_from: StrPath | None = None,
    device: str = "auto",
    progress: bool | Progress = False,
) -> TrainSummary:
    """``logpipe train``: train the predictor on ``dataset`` into the run folder ``out``.

    Args:
        dataset: a dataset folder, or several trained on together (the splits apply in each; samples in the
            order given, each dataset with its own raster run; the checkpoints record every format).
        scene: ETH/UCY leave-one-scene-out: train on ``SCENE/train``, validate on ``SCENE/val``.
        train_split: training logs (default ``hash/train``); ``val_split``: validation logs (default: the
            matching ``/val`` split; ``"none"`` disables it).
        config: TOML/JSON hyper-parameters (none on driving data: the shipped driving model's recipe, validated
            on data it picks itself when no split is given, compared with the kinematic baselines; see
            ``model.residual.fleet``); ``steps`` and ``seed`` override ``[train]``; ``preset``: a row of
            the paper's tables (``full``, ``v1``..``v4``, ``baseline``, ``lstm``, ``no_position``).
        device: ``auto`` (CUDA when torch sees a GPU, else the CPU), ``cpu`` or ``cuda`` (autocast on CUDA).
        progress: True: the training loop's own bar (a terminal); a callback: called with the steps done.

    Raises:
        LogpipeError: a split expression without ``val_split``, an existing run without ``resume``, ...

    Example::

        s = logpipe.train("/tmp/ethucy", out="/tmp/run", scene="eth", config="configs/ethucy.toml", steps=100)
        s["best_checkpoint"]                        # the folder ``predict(checkpoint=...)`` takes
    """
    from logpipe.dataset.reader import is_split_expression
    from logpipe.stages.train import train as run_train

    folders = as_paths(dataset)
    if not folders:
        raise LogpipeError("give at least one dataset")
    # Driving data without a config picks its own validation data (stages.train): no split given, none chosen here.
    auto = config is None and preset is None and scene is None and train_split is None and val_split is None
    chosen_train = train_split or (f"{scene}/train" if scene else "hash/train")
    if val_split is None and is_split_expression(chosen_train):
        raise LogpipeError(f"--train-split {chosen_train!r} has no matching /val split: give --val-split "
                           "(e.g. the held-out logs) or 'none'")
    chosen_val = val_split or ("none" if chosen_train == "all" else chosen_train.rsplit("/", 1)[0] + "/val")
    social = preset is not None and preset.startswith("social_")
    if social and (init_from is not None or raster_run is not None or loader_workers):
        raise LogpipeError(f"--preset {preset} trains from the tracks alone: --init-from, --raster-run and "
                           "--loader-workers do not apply")
    overrides: dict[str, Any] = {}
    if steps is not None:
        overrides["steps"] = steps
    if seed is not None:
        overrides["seed"] = seed
    summary: TrainSummary = run_train(
        folders[0] if len(folders) == 1 else folders, as_path(out), train_split=None if auto else chosen_train,
        val_split=None if auto or chosen_val == "none" else chosen_val,
        config_path=optional_path(config), overrides=overrides, preset=preset,
        resume=resume, raster_run=raster_run, loader_workers=loader_workers,
        init_from=optional_path(init_from), progress=progress, device=device,
    )
    return summary


def predict(  # noqa: PLR0913  public API: keyword options mirror `logpipe predict` one to one
    dataset: StrPath,
    *,
    out: StrPath,
    checkpoint: StrPath | None = None,
    predictor: str | None = None,
    modes: int | None = None,
    seed: int = 0,
    noise_scale: float | None = None,
    constant_velocity_modes: int | None = None,
    context_max_neighbours: int | None = None,
    as_trained: bool = False,
    filters: Sequence[str] = (),
    inputs: StrPath | Sequence[StrPath] | None = None,
    raster_run: str | None = None,
    raster_images: bool = True,
    mcap: bool = True,
    batch_size: int = 64,
    threads: int = 0,
    device: str = "auto",
    progress: Progress | None = None,
    backend: str = "local",
    workers: int = 0,
    allow_blank_rasters: bool = False,
    out_of_distribution: str = "auto",
) -> dict[str, Any]:
    """``logpipe predict``: run a checkpoint (default: the shipped one for the dataset kind) or a baseline
    (``predictor="cv"|"linear"|"kalman"|"cv_sampler"|"adaptive_cv"``) on every selected sample into the run folder
    ``out``.

    Args:
        modes: K futures per agent (default 20 for pedestrians, 6 for vehicles).
        noise_scale, constant_velocity_modes, context_max_neighbours: the network's inference settings
            (default: the checkpoint's stored ones; ``as_trained`` ignores those).
        filters: ``log=ID[,ID]``, ``split=eth/test``, ``time=START_NS:END_NS``, ``type=pedestrian[,..]``.
        inputs: root(s) bags/MCAP files were ingested from (their channels are copied into the MCAPs).
        mcap: write one MCAP per log; ``raster_images``: add each sample's raster to it.
        device: where a checkpoint's network runs: ``auto`` (CUDA when torch sees a GPU, else the CPU), ``cpu`` or
            ``cuda`` (autocast on CUDA); baselines ignore it.
        backend: ``local`` or ``ray`` (forecasts on ``workers`` Ray actors, 0 = one per GPU, else per CPU; the
            dataset must be on a file system every node shares); the same output bytes at the same ``threads``.
        allow_blank_rasters: run a network's environment net even where selected samples' rasters are blank.
        out_of_distribution: ``auto`` (physics at K = 1 on roads a residual checkpoint never trained on),
            ``warn``, ``fallback`` or ``refuse`` (``model.residual.ood``).

    Raises:
        LogpipeError: a bad option or filter, a checkpoint that does not fit the dataset, missing or blank rasters.

    Example::

        logpipe.predict("/tmp/ethucy", out="/tmp/pred_cv", predictor="cv", filters=["split=eth/test"])
    """
    from logpipe.dataset.sample_filter import parse_filter
    from logpipe.prediction.options import PredictOptions
    from logpipe.stages.predict import predict_dataset

    options = PredictOptions(
        checkpoint=optional_path(checkpoint),
        predictor=predictor, modes=modes, seed=seed, noise_scale=noise_scale,
        constant_velocity_modes=constant_velocity_modes, context_max_neighbours=context_max_neighbours,
        as_trained=as_trained, sample_filter=parse_filter(list(filters)), inputs=as_paths(inputs),
        raster_run=raster_run, raster_images=raster_images, write_mcap=mcap, batch_size=batch_size, threads=threads,
        device=device, backend=backend, workers=workers, allow_blank_rasters=allow_blank_rasters,
        out_of_distribution=out_of_distribution,
    )
    summary: dict[str, Any] = predict_dataset(as_path(dataset), as_path(out), options, progress=progress)
    return summary


def score(  # noqa: PLR0913  public API: keyword options mirror `logpipe score` one to one
    predictions: StrPath | Sequence[StrPath],
    *,
    truth: StrPath,
    out: StrPath = "out/score",
    split: str | None = None,
    agents: str = "all",
    min_agents: int = 1,
    k: Sequence[int] | None = None,
    miss_threshold: float = 2.0,
    fail_above: Sequence[str] | Mapping[str, float] | None = None,
    label: Sequence[str] | None = None,
    allow_missing: bool = False,
    plots: bool = True,
    plot_samples: int = 6,
) -> ScoreResult:
    """``logpipe score``: ADE/FDE (metres) of prediction run folders (or files), one method each, against the
    dataset ``truth``; writes ``report.json``, ``report.md`` and plots into ``out`` and returns the report.

    Args:
        fail_above: gates, as ``kN.METRIC=VALUE`` strings or ``{"k1.ade": 0.6}``; the report's
            ``["gate"]["failed"]`` says whether one was crossed (the CLI then exits 1; this returns).
        label: method names in input order; ``k``: K values to report (default 1 and each method's own K).

    Raises:
        LogpipeError: a malformed gate; ``ScoreError``, ``PredictionsError``, ``DatasetError`` from the stage.

    Example::

        r = logpipe.score(["/tmp/pred_cv"], truth="/tmp/ethucy", out="/tmp/score", split="eth/test")
        r["methods"]["cv"]["overall"]["k1"]["ade"]  # 1.075 (metres)
    """
    from logpipe.stages.score import score as run_score

    check_choice("--agents", agents, ("all", "focal"))
    thresholds = gates(fail_above)
    report: ScoreResult = run_score(
        as_paths(predictions), as_path(truth), as_path(out), agents=cast(Any, agents), min_agents=min_agents,
        split=split, ks=list(k) if k else None, miss_threshold_m=miss_threshold, fail_above=thresholds,
        labels=list(label) if label else None, allow_missing=allow_missing, plots=plots, plot_samples=plot_samples,
    )
    return report


def verify(folders: StrPath | Sequence[StrPath], *, repair: bool = False, shallow: bool = False) -> VerifyReport:
    """``logpipe verify``: check artifact folders against their manifests (size, sha256, row count of every
    committed file; sizes only with ``shallow``); ``repair`` removes uncommitted leftovers. Problems are
    returned, not raised (the CLI exits 1 when there are any).

    Example::

        assert not logpipe.api.verify(["/tmp/ethucy", "/tmp/pred_cv"])["problems"]
    """
    from logpipe.verify import verify_tree

    return cast(VerifyReport, verify_tree(as_paths(folders), repair=repair, deep=not shallow))


def inspect(paths: StrPath | Sequence[StrPath]) -> list[dict[str, Any]]:
    """``logpipe inspect --json``: one report per bag / MCAP / AV2 input found under ``paths`` (topics, types,
    counts, span, rate, the detected mapping); unreadable inputs are reports with ``ok`` False, not errors.
    ``logpipe.inspect.mapping_toml(reports)`` gives the mapping file ``ingest(mapping=...)`` takes.

    Example::

        from logpipe import api
        from logpipe.inspect import mapping_toml

        (report,) = api.inspect("tests/data/rosbags/datmo/intersection.bag")
        report["mapping"]["ego"]["topic"]           # '/ego_pose'
        Path("map.toml").write_text(mapping_toml([report]))
    """
    from logpipe.inspect import inspect_paths

    return inspect_paths(as_paths(paths))


def export(paths: StrPath | Sequence[StrPath], *, out: StrPath, format: str = "rrd") -> ExportSummary:
    """``logpipe export``: the MCAPs of a dataset or prediction run (or MCAP files) for another viewer; ``rrd``
    writes one Rerun recording per log into ``out`` (agents, history, truth, forecasts, lanes, raster, legend).
    Needs ``rerun-sdk`` (``pip install 'logpipe[rerun]'``).

    Raises:
        LogpipeError: an unknown format, rerun-sdk missing; ``DatasetError``: no MCAP found, an unreadable one.

    Example::

        logpipe.api.export("out/pred", out="out/rrd")
    """
    check_choice("--format", format, ("rrd",))
    try:
        import rerun  # noqa: F401  only to say what is missing before any work
    except ImportError:
        raise LogpipeError("export --format rrd needs rerun-sdk: pip install 'logpipe[rerun]'") from None
    from logpipe.mcap.rerun_export import export_rrd

    return export_rrd(as_paths(paths), as_path(out))
