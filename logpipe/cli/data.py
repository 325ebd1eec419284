"""``logpipe ingest``, ``index`` and ``rasterise``: the commands that build a dataset folder (tracks, sample
index, map rasters)."""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Annotated, Any

import typer

from logpipe.cli.app import (
    DatasetArg,
    JsonOpt,
    MinTargetsOpt,
    ObsOpt,
    PredOpt,
    ProtocolOpt,
    StrideOpt,
    TargetsOpt,
    TargetTypesOpt,
    WindowOpt,
    counting_warnings,
    emit,
    fail_after_summary,
    next_step,
    stage_progress,
    user_errors,
)

MAP_FORMATS = ("argoverse1", "argoverse2")
"""Formats whose shipped model reads map rasters: their next step after ingest is rasterise."""
OWN_MAP_FORMATS = ("commonroad",)
"""Formats whose inputs carry their own map: rasterise needs no ``--maps``."""


def ingest(  # noqa: PLR0913  typer command: one parameter per CLI option
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
        "--mapping", help="Bags/MCAP: TOML or YAML file naming the ego and agent topics (docs/guide.md, 'Bags and "
        "MCAP: the mapping'; logpipe inspect BAG --format toml writes one).")] = None,
    overrides: Annotated[list[str] | None, typer.Option(
        "--set", help="Bags/MCAP: mapping override KEY=VALUE, repeatable (ego=/odom, agent=/red_pose, map=lab).")
    ] = None,
    hz: Annotated[float | None, typer.Option(
        "--hz", help="Bags/MCAP: resample tracks to this rate (default 10; 0 keeps original times).")] = None,
    allow_empty: Annotated[bool, typer.Option(
        "--allow-empty", help="Bags/MCAP/AV2: a log without tracks is kept empty instead of being an error.")
    ] = False,
    retry_quarantined: Annotated[bool, typer.Option(
        "--retry-quarantined", help="Read again the inputs an earlier --on-error skip run quarantined, with this "
        "run's options (after fixing them or their --mapping); without it a rerun skips them.")] = False,
    max_quarantined: Annotated[int | None, typer.Option(
        "--max-quarantined", help="With --on-error skip: exit 2 (after committing what was read) when more inputs "
        "than this are quarantined. Quarantining every new input exits 2 whatever the limit.")] = None,
    as_json: JsonOpt = False,
) -> None:
    """Turn logs (Argoverse 1 CSV, ETH/UCY, ApolloScape, ...) into canonical Parquet shards, a sample index
    and one MCAP per log. Re-running skips inputs already ingested (by content hash).

    Limits per input (an input over one is refused, or quarantined with --on-error skip, with the limit named):
    CommonRoad files 16 MiB (after gzip); compressed chunks and ROS 2 zstd messages inflate at most
    LOGPIPE_MAX_INFLATION (1000) times their size, and at most LOGPIPE_MAX_CHUNK_BYTES (1 GiB); coordinates
    below 1e7 m (CommonRoad states 1e5); no track moving faster than 150 m/s between observations; ETH/UCY and
    ApolloScape ids whole numbers below 2^31; a text file's last line ends with a newline (else it was cut).

    Example: logpipe ingest tests/data/driving --out out/av1

    Example: logpipe ingest tests/data/rosbags/datmo --out out/ros --set ego=/ego_pose --set agent=/red_pose --hz 10
    """
    from logpipe import api
    from logpipe.errors import QuarantineLimitError

    failure = None
    with user_errors(as_json), counting_warnings() as logged:
        try:
            with stage_progress("ingest", "inputs") as advance:
                summary: dict[str, Any] = dict(api.ingest(
                    inputs, out=out, format=fmt, protocol=protocol, obs=obs, pred=pred, stride=stride,
                    min_targets=min_targets, targets=targets, target_types=target_types, window=window,
                    on_error=on_error, mcap=mcap, workers=workers, backend=backend, batch_files=batch_files,
                    mapping=mapping, overrides=overrides or (), hz=hz, allow_empty=allow_empty,
                    retry_quarantined=retry_quarantined, max_quarantined=max_quarantined, progress=advance,
                ))
        except QuarantineLimitError as exc:  # committed, yet the run fails: its summary first, then the error
            failure, summary = str(exc), {**exc.summary, "error": str(exc), "exit_code": 2}
    emit(summary, as_json, ingest_lines, logged)
    if failure is not None:
        fail_after_summary(failure)


def ingest_lines(s: dict[str, Any]) -> list[str]:
    """The human summary of ``ingest``: counts, where the outputs are, quarantined inputs, the next command."""
    ds, totals = s["dataset"], s["totals"]
    lines = [
        f"ingest: {s['inputs_ingested']} inputs ingested, {s['inputs_skipped_already_ingested']} already there, "
        f"{len(s['quarantined'])} quarantined: {s['logs']} logs, {s['rows']:,} rows, {s['samples']:,} samples "
        f"in {s['seconds']} s ({s['format']})",
        f"  dataset: {ds} (now {totals['logs']} logs, {totals['rows']:,} rows, {totals['samples']:,} samples: "
        f"tracks/, logs/, samples/, manifest.json)",
    ]
    if s.get("mcap_messages"):
        lines.append(f"  MCAPs: {ds}/mcap/part-*/<log>.mcap (open one in Foxglove, or `logpipe export {ds} "
                     "--format rrd --out DIR` for Rerun)")
    for q in s["quarantined"]:
        e = q["error"]
        where = e["file"] + (f":{e['line']}" if e["line"] else "") + (f" field '{e['field']}'" if e["field"] else "")
        lines.append(f"  quarantined {where}: {e['reason']}")
    lines += [f"  warning: {w}" for w in s.get("warnings", [])]
    lines += [f"  {line}" for line in summary_notes(s) + location_lines(s)]
    earlier = totals.get("quarantined", 0) - len(s["quarantined"])
    if earlier > 0 and not s.get("inputs_retried"):
        lines.append(f"  {earlier} inputs quarantined by an earlier run are skipped (--retry-quarantined reads them "
                     "again)")
    if s["quarantined"] or earlier > 0:
        lines.append(next_step(f"logpipe ingest INPUTS --out {ds} --retry-quarantined",
                               "after fixing the inputs or the options, e.g. --mapping"))
    elif not s["logs"] and any((Path(ds) / "rasters").glob("*/manifest.json")):
        # nothing new since the rasters were drawn: they cover every log, so rasterise has nothing to do
        lines.append(next_step(f"logpipe predict {ds} --out {ds}-pred", "no new log; its rasters are current"))
    elif s["format"] in OWN_MAP_FORMATS:
        lines.append(next_step(f"logpipe rasterise {ds} --rotate", "each log's own map; then logpipe predict"))
    elif s["format"] in MAP_FORMATS:
        lines.append(next_step(f"logpipe rasterise {ds} --maps MAPS_FOLDER --rotate",
                               "map rasters for the driving model; then logpipe predict"))
    else:
        lines.append(next_step(f"logpipe predict {ds} --out {ds}-pred"))
    return lines


def summary_notes(summary: Mapping[str, Any]) -> list[str]:
    """Lines that explain an ingest or index summary's counts, for the human output: the inputs that were
    copies of others, and one line per reason logs gave no sample."""
    lines = []
    if summary.get("duplicates"):
        copies = summary.get("duplicate_inputs") or []
        example = f", e.g. {copies[0]['path']} = {copies[0]['same_as']}" if copies else ""
        lines.append(f"{summary['duplicates']} inputs were identical copies of another and were ingested once "
                     f"with it{example} (--json lists them)")
    for reason, count in (summary.get("logs_without_samples") or {}).items():
        lines.append(f"{count} log{'s' if count != 1 else ''} gave no sample: {reason}")
    return lines


def location_lines(summary: Mapping[str, Any]) -> list[str]:
    """One line per location (logs, tracks, windows, targets) and the tracks logs of one location share."""
    lines = [f"{loc}: {c['logs']} logs, {c['tracks']:,} tracks, {c['windows']:,} windows, {c['targets']:,} targets"
             for loc, c in (summary.get("by_location") or {}).items()]
    if shared := summary.get("shared_tracks"):
        lines.append(f"{shared['tracks']} tracks recur in another log of their location ({shared['pairs']} log "
                     f"pairs): flagged in the logs' attributes (shared_tracks); keep such logs in one split")
    return lines


def protocol_text(protocol: dict[str, Any]) -> str:
    """``argoverse: 20 + 30 steps, targets focal, window first`` (a sample protocol in one phrase)."""
    extra = [f"{k.replace('_', ' ')} {protocol[k]}" for k in ("targets", "window", "stride", "min_targets")
             if protocol.get(k) not in (None, "", [])]
    steps = f"{protocol.get('obs_len')} + {protocol.get('pred_len')} steps"
    return f"{protocol.get('name', '?')}: " + ", ".join([steps, *extra])


def index_lines(s: dict[str, Any]) -> list[str]:
    """The human summary of ``index``."""
    what = "unchanged" if s.get("unchanged") else "rebuilt"
    lines = [f"index: {s['dataset']}: sample index {what}, {s['samples']:,} samples",
             f"  protocol {protocol_text(s['protocol'])}"]
    lines += [f"  {line}" for line in summary_notes(s)]
    lines.append(next_step(f"logpipe predict {s['dataset']} --out {s['dataset']}-pred"))
    return lines


def index(  # noqa: PLR0913  typer command: one parameter per CLI option
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

    with user_errors(as_json), counting_warnings() as logged, stage_progress("index", "logs") as advance:
        summary = api.index(dataset, protocol=protocol, obs=obs, pred=pred, stride=stride, min_targets=min_targets,
                            targets=targets, target_types=target_types, window=window, progress=advance)
    emit(dict(summary), as_json, index_lines, logged)


def rasterise(  # noqa: PLR0913  typer command: one parameter per CLI option
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

    Example: logpipe rasterise out/av1 --maps tests/data/driving --rotate --preview 4
    """
    from logpipe import api

    with user_errors(as_json), counting_warnings() as logged, stage_progress("rasterise", "samples") as advance:
        summary = api.rasterise(dataset, maps=maps, map_file=map_file, centre=centre, rotate=rotate, preview=preview,
                                size=size, extent=extent, channels=channels, shard_size=shard_size, force=force,
                                workers=workers, backend=backend, progress=advance)
    emit(dict(summary), as_json, rasterise_lines, logged)


def rasterise_lines(s: dict[str, Any]) -> list[str]:
    """The human summary of ``rasterise``: counts (blank ones too), the run folder, previews, the next command."""
    dataset = str(Path(s["run_dir"]).parent.parent)
    lines = [f"rasterise: {s['samples']:,} samples: {s['rendered']:,} rendered, {s['skipped_existing']:,} already "
             f"there; {s['empty']:,} blank ({s['logs_without_map']} logs without a map, {s['blank_with_map']} off "
             f"their map) in {s.get('seconds', 0)} s",
             f"  rasters: {s['run_dir']} (shards, index, manifest.json)"]
    road = s.get("road_vehicles") or {}
    if road.get("observed"):
        lines.append(f"  {road['share']:.2%} of {road['observed']:,} observed road-vehicle positions lie on drivable "
                     "pixels (a check that each log met its own map)")
    if s["previews"]:
        lines.append(f"  previews: {Path(s['previews'][0]).parent}/ ({len(s['previews'])} PNG, e.g. "
                     f"{Path(s['previews'][0]).name})")
    lines.append(next_step(f"logpipe predict {dataset} --out {dataset}-pred"))
    return lines
