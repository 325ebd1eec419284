"""The summaries the API returns and ``--json`` prints, as typed records: ``logpipe.api`` functions return
them; the keys are the JSON's."""

from __future__ import annotations

from typing import Any, NotRequired, TypedDict


class IngestSummary(TypedDict):
    """What ``ingest`` returns (``logpipe ingest --json``). Counts are of this run unless under ``totals``.

    ``inputs_found`` counts distinct inputs: ``duplicates`` more files were identical copies of one of them
    (listed in ``duplicate_inputs`` as ``{"path", "same_as"}``, relative paths) and were ingested once, as
    that input (their folders are added to its memberships). ``logs_without_samples`` counts the logs that
    give no prediction sample, by reason (e.g. ``"too short for 8+12 steps"``). ``inputs_retried`` counts the
    quarantined inputs read again (``retry_quarantined``). ``skipped_inputs`` names the files under the input
    folders that another format recognises (``{"path", "format", "why"}``): a dataset holds one format.
    """

    dataset: str
    format: str
    protocol: dict[str, Any]
    inputs_found: int
    inputs_skipped_already_ingested: int
    inputs_ingested: int
    duplicates: int
    duplicate_inputs: list[dict[str, str]]
    quarantined: list[dict[str, Any]]
    logs: int
    rows: int
    samples: int
    logs_without_samples: dict[str, int]
    shards_written: list[str]
    mcap_messages: NotRequired[int]
    inputs_retried: NotRequired[int]
    skipped_inputs: list[dict[str, str]]
    seconds: float
    totals: dict[str, int]


class IndexSummary(TypedDict):
    """What ``index`` returns (``logpipe index --json``); ``unchanged`` when the protocol was the dataset's
    already (then nothing was recounted, and ``logs_without_samples`` is absent)."""

    dataset: str
    protocol: dict[str, Any]
    samples: int
    logs_without_samples: NotRequired[dict[str, int]]
    unchanged: NotRequired[bool]


class VerifyReport(TypedDict):
    """What ``verify`` returns: the folders checked, how many files, one line per problem, leftover paths."""

    folders: list[str]
    files_checked: int
    problems: list[str]
    leftovers: list[str]


class RoadVehicles(TypedDict):
    """``RasteriseSummary.road_vehicles``: observed road-vehicle positions inside the rasters, on drivable pixels."""

    observed: int
    on_drivable: int
    share: float | None


class RasteriseSummary(TypedDict):
    """What ``rasterise_dataset`` returns (``logpipe rasterise --json``). Counts are of this invocation:
    ``skipped_existing`` samples were in shards an earlier run committed (their counts are in the run manifest's
    ``counts``, not here).

    ``spec`` is ``RasterSpec.to_dict()`` (open JSON: its keys follow the spec's version). ``heading_source`` and
    ``centre_role`` count rendered samples by rule (``column``/``motion``/``lane``/``none``;
    ``ego``/``focal``/``target``). ``road_vehicles`` counts the observed positions of road vehicles (vehicle,
    bus_truck, motorcyclist) inside the rasters rendered by this invocation and how many fall on drivable pixels
    (``share``: a low one means map and tracks do not share a frame). ``previews`` are PNG paths.
    ``blank_with_map`` counts rendered rasters that are blank although their log has a map (the centre off it);
    ``warnings`` says what makes rasters blank, one line each. The timings are set once the run is committed:
    ``seconds`` (wall), ``render_seconds`` (drawing only) and ``rasters_per_s`` (None when nothing was rendered).
    """

    run_dir: str
    run_id: str
    spec: dict[str, Any]
    fingerprint: str
    centre: str
    samples: int
    rendered: int
    skipped_existing: int
    empty: int
    no_centre: int
    blank_with_map: int
    warnings: list[str]
    logs_without_map: int
    logs_without_map_examples: list[str]
    heading_source: dict[str, int]
    centre_role: dict[str, int]
    road_vehicles: RoadVehicles
    previews: list[str]
    seconds: NotRequired[float]
    render_seconds: NotRequired[float]
    rasters_per_s: NotRequired[float | None]


class TrainDatasetCount(TypedDict):
    """One dataset of a run trained on several (``TrainSummary.per_dataset``): its samples (``train_samples``
    is ``"streamed"`` for a dataset streamed through a DataLoader)."""

    dataset: str
    format: str
    train_samples: int | str
    val_samples: int | str


class TrainPerDataset(TypedDict, total=False):
    """``TrainSummary``'s ``per_dataset`` key, present only with several datasets (kept in its own record so the
    summary's keys keep their order)."""

    per_dataset: list[TrainDatasetCount]


class TrainResumed(TypedDict, total=False):
    """``TrainSummary``'s keys of a resumed run: the step this part started from and the training wall time of
    all parts in seconds (None when an earlier part predates the training state's clock)."""

    resumed_at_step: int
    seconds_total: float | None


class TrainSummary(TypedDict):
    """What ``train`` returns (``logpipe train --json``).

    With several datasets ``dataset`` and ``raster_run`` are lists (one per dataset, in the order given) and
    ``per_dataset`` says what each gave. ``train_samples`` is ``"streamed"`` with ``--loader-workers``.
    ``best_val_ade``/``best_val_fde`` are metres (NaN without validation), ``train_samples_per_s`` scenes per
    second of optimiser steps, ``seconds`` this call's wall time. The residual driving model (``model.residual.run``)
    reports its K = 1 errors there (and its best-of-K FDE as an extra key, ``best_val_min_fde``).
    """

    dataset: str | list[str]
    per_dataset: NotRequired[list[TrainDatasetCount]]
    run: str
    train_split: str
    val_split: str | None
    train_samples: int | str
    val_samples: int
    steps: int
    best_step: int
    best_val_ade: float
    best_val_fde: float
    stopped_early: bool
    best_checkpoint: str | None
    last_checkpoint: str
    train_samples_per_s: float
    raster_run: str | list[str | None] | None
    init_from: str | None
    environment_net: bool
    device: str
    seconds: float
    resumed_at_step: NotRequired[int]
    seconds_total: NotRequired[float | None]


class DrivingTrainSummary(TrainSummary):
    """``train`` on driving data without a config (the driving recipe, ``model.residual.fleet``): also the
    residual model's best-of-K FDE, the recipe, how validation was chosen (``validation``), the start (fine-tuned or
    from scratch, ``start``), the comparison with the kinematic baselines on the validation targets
    (``comparison``), the report lines the command prints and the model card's path."""

    best_val_min_fde: float
    recipe: str
    validation: dict[str, Any]
    start: dict[str, Any]
    comparison: dict[str, Any]
    notes: list[str]
    train_targets: int
    val_targets: int
    report: list[str]
    model_card: str


class ExportedFile(TypedDict):
    """One file ``export`` wrote: the MCAP it read, the recording it wrote and what that draws, by kind
    (``boxes``, ``history``, ``truth``, ``modes``, ``current``, ``lines``, ``lane_strips``, ``images``)."""

    mcap: str
    rrd: str
    drawn: dict[str, int]


class ExportSummary(TypedDict):
    """What ``export`` returns (``logpipe export --json``): the format, the output folder and each file."""

    format: str
    out: str
    files: list[ExportedFile]
    seconds: float


def quarantine_failure(summary: dict[str, Any], max_quarantined: int | None) -> str | None:
    """Why a committed ``--on-error skip`` run must still fail, or None: it quarantined every new input (nothing
    ingested), the dataset still holds no log but quarantined inputs, or this run quarantined more inputs than
    ``max_quarantined``."""
    quarantined, totals = len(summary["quarantined"]), summary["totals"]
    if quarantined and not summary["inputs_ingested"]:
        return (f"nothing ingested: all {quarantined} new inputs were quarantined "
                f"(e.g. {summary['quarantined'][0]['path']}); the dataset {summary['dataset']} gained no log")
    if not totals.get("logs") and totals.get("quarantined"):  # a rerun over the same bad inputs
        return (f"the dataset {summary['dataset']} holds no log: its {totals['quarantined']} inputs are "
                "quarantined (--retry-quarantined reads them again)")
    if max_quarantined is not None and quarantined > max_quarantined:
        return (f"{quarantined} inputs quarantined, more than --max-quarantined {max_quarantined} "
                f"({summary['inputs_ingested']} ingested and committed)")
    return None
