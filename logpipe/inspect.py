"""``logpipe inspect PATH...``: what is in a bag / MCAP / AV2 input, and which topics logpipe can turn into tracks.

Like ``ros2 bag info`` / ``mcap info``: topics (channels), types, message counts, time span and frequency, plus
whether the first message of each topic decodes, and the mapping logpipe would use without one (or why it
cannot choose). ``inspect_paths`` returns plain dicts (the ``--json`` output); ``render`` prints them as rich
tables; ``mapping_toml`` gives the detected mapping as the TOML file ``logpipe ingest --mapping`` takes
(``--format toml``).
"""

from __future__ import annotations

import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from rich.console import Console
from rich.table import Table

from logpipe.formats.av2 import Av2Adapter
from logpipe.formats.base import as_source_error, require_regular
from logpipe.formats.inflation import check_ros1_bags
from logpipe.formats.mcapfile import McapAdapter, McapFile
from logpipe.formats.ros.mapping import AmbiguousMappingError, TopicSummary, auto_mapping
from logpipe.formats.ros.message_types import topic_kind, unsupported_reason
from logpipe.formats.ros.tf import TfBuffer
from logpipe.formats.rosbag import RosbagAdapter, explain_open_error, storage_paths


def expand(paths: Sequence[Path]) -> list[tuple[str, Path]]:
    """(format, input) pairs for ``paths``: each is an input itself or a folder searched by every adapter."""
    bag, mcap, av2 = RosbagAdapter(), McapAdapter(), Av2Adapter()
    out: list[tuple[str, Path]] = []
    for p in paths:
        if p.is_file() and (found_here := bag.discover(p) or mcap.discover(p) or av2.discover(p)):
            fmt = "rosbag" if bag.sniff(p) else "mcap" if mcap.sniff(p) else "argoverse2"
            out += [(fmt, x) for x in found_here]
        elif p.is_file() and p.suffix in (".bag", ".db3", ".mcap"):  # damaged: let the reader say why
            out.append(("mcap" if p.suffix == ".mcap" else "rosbag", p))
        elif bag.sniff(p):
            out.append(("rosbag", p))
        elif av2.sniff(p):
            out.append(("argoverse2", p))
        elif p.is_dir():
            found = [("rosbag", x) for x in bag.discover(p)] + [("mcap", x) for x in mcap.discover(p)]
            found += [("argoverse2", x) for x in av2.discover(p)]
            out += sorted(found, key=lambda fx: str(fx[1])) or [("unknown", p)]
        else:
            out.append(("unknown", p))
    return out


def inspect_paths(paths: Sequence[Path]) -> list[dict[str, Any]]:
    """One report per input found under ``paths`` (see the module docstring); never raises for bad inputs."""
    reports = []
    for given in paths:
        try:
            require_regular(given, str(given), folder_ok=True)  # a FIFO would block, /dev/zero never end
            found = expand([given])
        except Exception as err:  # a damaged input is a report, never a traceback
            reports.append(_report(given, "unknown", error=as_source_error(err, str(given)).describe()))
            continue
        for fmt, path in found:
            try:
                reports.append(_inspect_one(fmt, path))
            except Exception as err:  # whatever a damaged file makes a reader raise
                reports.append(_report(path, fmt, error=as_source_error(err, str(path)).describe()))
    return reports


def _inspect_one(fmt: str, path: Path) -> dict[str, Any]:
    if fmt == "rosbag":
        check_ros1_bags(storage_paths(path))  # before rosbags decompresses any chunk, unbounded
        return inspect_rosbag(path)
    if fmt == "mcap":
        return inspect_mcap(path)
    if fmt == "argoverse2":
        return inspect_av2(path)
    what = "holds no" if path.is_dir() else "is not a"
    return _report(path, "unknown", error=f"{what} ROS bag, MCAP file or Argoverse 2 input")


def _report(path: Path, fmt: str, **kw: Any) -> dict[str, Any]:
    out: dict[str, Any] = {
        "path": str(path), "format": fmt, "ok": True, "error": None, "start_ns": None, "end_ns": None,
        "duration_s": None, "message_count": None, "topics": [], "mapping": None, "mapping_error": None,
    }  # fmt: skip
    out.update(kw)
    if out["error"]:
        out["ok"] = False
    return out


def _topic_row(topic: str, msgtype: str, count: int | None, first: int | None, last: int | None) -> dict[str, Any]:
    freq = None
    if count and count > 1 and first is not None and last is not None and last > first:
        freq = (count - 1) / ((last - first) / 1e9)
    kind = topic_kind(msgtype)
    return {
        "topic": topic, "type": msgtype, "count": count, "first_ns": first, "last_ns": last,
        "frequency_hz": freq, "kind": kind, "decodes": None, "decode_error": None, "role": None,
        "note": None if kind else unsupported_reason(msgtype),
    }  # fmt: skip


def _finish(report: dict[str, Any], summaries: list[TopicSummary], tf: TfBuffer | None) -> None:
    """Fill the proposed mapping and the per-topic role (ego / agent / tf) into ``report``."""
    times = [(r["first_ns"], r["last_ns"]) for r in report["topics"] if r["first_ns"] is not None]
    if times:
        report["start_ns"] = min(a for a, _ in times)
        report["end_ns"] = max(b for _, b in times)
        report["duration_s"] = (report["end_ns"] - report["start_ns"]) / 1e9
    report["message_count"] = sum(r["count"] or 0 for r in report["topics"])
    usable = [
        s for s in summaries if not any(r["topic"] == s.topic and r["decodes"] is False for r in report["topics"])
    ]
    try:
        mapping = auto_mapping(usable, tf.dynamic_edges() if tf else ())
    except AmbiguousMappingError as err:
        report["mapping_error"] = str(err)
        return
    report["mapping"] = mapping.to_dict()
    roles = {a.topic: "agent" for a in mapping.agents}
    if mapping.ego and mapping.ego.topic:
        roles[mapping.ego.topic] = "ego"
    for r in report["topics"]:
        r["role"] = roles.get(r["topic"])
        if r["kind"] == "tf" and mapping.ego and mapping.ego.tf:
            r["role"] = "ego (tf {}->{})".format(*mapping.ego.tf)


def inspect_rosbag(path: Path) -> dict[str, Any]:
    """Report for a ROS1 bag or ROS2 bag folder/storage file, read with rosbags."""
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    paths = storage_paths(path)
    try:
        reader = AnyReader(paths, default_typestore=get_typestore(Stores.ROS2_HUMBLE))
        reader.open()
    except Exception as err:  # every failure is reported, not raised
        reason, topic = explain_open_error(path, err)
        mcaps = sorted(path.glob("*.mcap")) if path.is_dir() else [path] if path.suffix == ".mcap" else []
        if str(err).startswith("Could not parse") and len(mcaps) == 1:
            # as the adapter does: rosbags refuses the whole bag for one .srv schema, the mcap reader does not
            report = inspect_mcap(mcaps[0])
            report.update(path=str(path), format="rosbag2 (mcap reader)", rosbags_refused=reason)
            return report
        return _report(path, "rosbag", error=reason + (f" (topic {topic})" if topic else ""))
    try:
        fmt = "rosbag2" if reader.is2 else "rosbag1"
        first: dict[str, int] = {}
        last: dict[str, int] = {}
        seen: dict[str, int] = {}
        decode: dict[str, str | None] = {}
        tf = TfBuffer()
        tf_topics = {c.topic for c in reader.connections if topic_kind(c.msgtype) == "tf"}
        by_topic: dict[str, list[Any]] = {}
        for c in reader.connections:
            by_topic.setdefault(c.topic, []).append(c)
        # topic by topic: rosbags merges interleaved connections slowly (see formats/rosbag.py)
        stream = (m for conns in by_topic.values() for m in reader.messages(connections=conns))
        for conn, t, raw in stream:
            topic = conn.topic
            seen[topic] = seen.get(topic, 0) + 1
            first.setdefault(topic, t)
            last[topic] = t
            if topic not in decode or (topic in tf_topics and decode[topic] is None):
                try:
                    msg = reader.deserialize(raw, conn.msgtype)
                    decode[topic] = None
                    if topic in tf_topics:
                        tf.add_message(msg, static="static" in topic)
                except Exception as err:  # shown in the report
                    decode[topic] = f"{type(err).__name__}: {str(err).strip()[:200]}"
        report = _report(path, fmt, storage_files=[p.name for p in paths])
        summaries = []
        for name, info in sorted(reader.topics.items()):
            msgtype = info.msgtype or "?"
            row = _topic_row(name, msgtype, info.msgcount, first.get(name), last.get(name))
            row["read"] = seen.get(name, 0)
            if name in decode:
                row["decodes"] = decode[name] is None
                row["decode_error"] = decode[name]
            if info.msgcount and not seen.get(name):
                row["note"] = (f"declared {info.msgcount} messages but none can be read "
                               "(metadata.yaml does not match the storage)")  # fmt: skip
            report["topics"].append(row)
            summaries.append(TopicSummary(name, msgtype, seen.get(name, 0)))
        _finish(report, summaries, tf)
        if not seen:
            report["ok"] = False
            report["error"] = "no message can be read" if reader.message_count else "the bag holds no messages"
        return report
    finally:
        reader.close()


def inspect_mcap(path: Path) -> dict[str, Any]:
    """Report for a standalone MCAP file, read with the mcap package."""
    try:
        f = McapFile.open(path)
    except Exception as err:  # shown in the report
        return _report(path, "mcap", error=f"not a readable MCAP file: {type(err).__name__}: {err}")
    try:
        report = _report(path, "mcap", profile=f.profile, library=f.library, indexed=f.indexed)
        first: dict[str, int] = {}
        last: dict[str, int] = {}
        seen: dict[str, int] = {}
        decode: dict[str, str | None] = {}
        tf = TfBuffer()
        summaries = f.topic_summaries()
        tf_topics = {s.topic for s in summaries if topic_kind(s.msgtype) == "tf"}
        for channel, t, data in f.raw_messages(None):
            topic = channel.topic
            seen[topic] = seen.get(topic, 0) + 1
            first.setdefault(topic, t)
            last[topic] = t
            if topic not in decode or (topic in tf_topics and decode[topic] is None):
                try:
                    msg = f.decoder(channel.id)(data)
                    decode[topic] = None
                    if topic in tf_topics:
                        tf.add_message(msg, static="static" in topic)
                except Exception as err:  # shown in the report
                    decode[topic] = f"{type(err).__name__}: {str(err).strip()[:200]}"
        encodings = {}
        for info in f.channels.values():
            encodings[info.topic] = (info.message_encoding, info.schema_encoding)
        for s in sorted(summaries, key=lambda s: s.topic):
            row = _topic_row(s.topic, s.msgtype, s.count, first.get(s.topic), last.get(s.topic))
            row["message_encoding"], row["schema_encoding"] = encodings.get(s.topic, ("", ""))
            if s.topic in decode:
                row["decodes"] = decode[s.topic] is None
                row["decode_error"] = decode[s.topic]
            report["topics"].append(row)
        _finish(report, [TopicSummary(s.topic, s.msgtype, seen.get(s.topic, 0)) for s in summaries], tf)
        if f.damage:
            report["ok"] = False
            report["error"] = f.damage
        return report
    finally:
        f.close()


def inspect_av2(path: Path) -> dict[str, Any]:
    """Report for an AV2 scenario parquet or sensor-log folder (read through the adapter)."""
    from logpipe.errors import SourceError
    from logpipe.types import SourceFile

    try:
        parsed = Av2Adapter().read([SourceFile(str(path), path.name, "", 0)], keep_going=False)
    except SourceError as err:
        return _report(path, "argoverse2", error=err.describe())
    t = parsed.tracks
    meta = parsed.logs[0]
    ts = t.column("timestamp_ns").to_numpy()
    roles = t.column("role").to_pylist()
    tracks = t.column("track_id").to_pylist()
    report = _report(
        path, "argoverse2", start_ns=int(ts.min()), end_ns=int(ts.max()),
        duration_s=float(ts.max() - ts.min()) / 1e9, message_count=t.num_rows,
        log_id=meta.log_id, map_id=meta.map_id, attributes=meta.attributes,
        tracks=len(set(tracks)), timestamps=len(set(ts.tolist())),
        focal=sorted({tr for tr, r in zip(tracks, roles, strict=True) if r == "focal"}),
        ego=sorted({tr for tr, r in zip(tracks, roles, strict=True) if r == "ego"}),
    )  # fmt: skip
    return report


def mapping_toml(reports: Sequence[dict[str, Any]]) -> str:
    """The mapping detected in ``reports`` as a TOML mapping file for ``logpipe ingest --mapping FILE``.

    One ``--mapping`` applies to every input of an ingest, so inputs that detect different mappings give none.

    Raises:
        LogpipeError: no report, an input without a detected mapping (unreadable, ambiguous, no usable topic,
            or an Argoverse 2 input, which needs none), or inputs whose detected mappings differ.
    """
    from logpipe.errors import LogpipeError
    from logpipe.formats.ros.mapping import mapping_from_dict

    if not reports:
        raise LogpipeError("no input found to take a mapping from")
    for rep in reports:
        if rep["format"] == "argoverse2":
            raise LogpipeError(f"{rep['path']}: Argoverse 2 inputs need no mapping")
        if rep["mapping"] is None:
            why = rep["mapping_error"] or rep["error"] or "no topic logpipe can turn into tracks"
            raise LogpipeError(f"{rep['path']}: no mapping detected: {why}")
    first = reports[0]["mapping"]
    other = next((rep["path"] for rep in reports if rep["mapping"] != first), None)
    if other is not None:
        raise LogpipeError(f"{reports[0]['path']} and {other} detect different mappings; inspect them one at a time")
    # The file starts with comments naming its source; a path is one line of the comment whatever it holds.
    sources = "".join(f"#   {' '.join(str(rep['path']).splitlines())}\n" for rep in reports)
    return ("# logpipe mapping detected by `logpipe inspect` in:\n" + sources
            + "# use: logpipe ingest INPUT --mapping THIS_FILE\n" + mapping_from_dict(first).to_toml())


def _fmt_time(ns: int | None) -> str:
    if ns is None:
        return "-"
    import datetime as dt

    return dt.datetime.fromtimestamp(ns / 1e9, tz=dt.UTC).strftime("%Y-%m-%d %H:%M:%S.%f")[:-3] + "Z"


def _table_width(reports: Sequence[dict[str, Any]]) -> int:
    """Columns a topics table needs without cutting a cell (at least 100)."""
    widest = [0] * 6
    for rep in reports:
        for r in rep.get("topics") or []:
            cells = (r["topic"], r["type"], str(r["count"]), "12345.6", f"no: {r.get('decode_error')}",
                     f"usable ({r.get('kind')})")
            widest = [max(w, len(str(c))) for w, c in zip(widest, cells, strict=True)]
    return max(100, sum(widest) + 3 * len(widest) + 4)


def render(reports: Sequence[dict[str, Any]], console: Console | None = None) -> None:
    """Print ``reports`` as rich tables, one per input. Off a terminal (piped, a CI log) the console is as wide as
    the widest row, so no topic or type name is cut to fit 80 columns."""
    piped = not sys.stdout.isatty()
    console = console or Console(width=_table_width(reports) if piped else None, soft_wrap=piped)
    for rep in reports:
        status = "[green]ok[/green]" if rep["ok"] else "[red]error[/red]"
        console.rule(f"[bold]{rep['path']}[/bold]  ({rep['format']}, {status})")
        if rep.get("error"):
            console.print(f"[red]{rep['error']}[/red]")
        if rep["start_ns"] is not None:
            console.print(
                f"start {_fmt_time(rep['start_ns'])}  end {_fmt_time(rep['end_ns'])}  "
                f"duration {rep['duration_s']:.3f} s  messages {rep['message_count']}"
            )
        if rep["format"] == "argoverse2" and rep["ok"]:
            console.print(f"log {rep['log_id']}  map {rep['map_id']}  tracks {rep['tracks']}  "
                          f"timestamps {rep['timestamps']}  focal {rep['focal']}  ego {rep['ego']}")  # fmt: skip
            continue
        if rep["topics"]:
            table = Table(show_header=True, header_style="bold")
            for col in ("topic", "type", "count", "Hz", "decodes", "logpipe"):
                table.add_column(col, justify="right" if col in ("count", "Hz") else "left")
            for r in rep["topics"]:
                dec = "-" if r["decodes"] is None else ("yes" if r["decodes"] else f"no: {r['decode_error']}")
                # the role in the detected mapping; else whether a mapping could use the topic
                use = r["role"] or ("tf" if r["kind"] == "tf" else f"usable ({r['kind']})" if r["kind"] else "")
                table.add_row(
                    r["topic"], r["type"], str(r["count"] if r["count"] is not None else "?"),
                    f"{r['frequency_hz']:.1f}" if r["frequency_hz"] else "-", dec, use,
                )  # fmt: skip
            console.print(table)
        if rep["mapping"] is not None:
            console.print(f"mapping (detected): {rep['mapping']}")
        elif rep["mapping_error"]:
            console.print(f"[yellow]no automatic mapping: {rep['mapping_error']}[/yellow]")
