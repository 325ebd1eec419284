"""One log's messages → canonical track rows: the reader-independent part of the rosbag and MCAP adapters.

A reader supplies the topic list and a function that yields decoded messages of chosen topics; this module
chooses the mapping (given, or detected), runs the extractors, places everything in the world frame,
resamples and reports per-topic problems as ``SourceError``s.
"""

from __future__ import annotations

from collections.abc import Callable, Collection, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pyarrow as pa

from logpipe.errors import SourceError
from logpipe.formats.mapping import EgoSpec, Mapping, resolve_mapping
from logpipe.formats.ros_messages import (
    OBJECT_KINDS,
    AmbiguousMappingError,
    FrameError,
    TfBuffer,
    TopicExtractor,
    TopicSummary,
    auto_mapping,
    ego_from_tf,
    empty_tracks,
    normalize_type,
    to_world,
    topic_kind,
    unsupported_reason,
    world_frame_for,
    world_to_table,
)
from logpipe.resample import ResampleSpec
from logpipe.types import PROTOCOLS

ROSBAG_PROTOCOL = PROTOCOLS["rosbag"]
"""Default protocol of the ROS bag and MCAP adapters: 2 s observed + 3 s predicted at the default 10 Hz, a window
every second, every fully observed agent a target."""


class ReadStopped(Exception):  # noqa: N818 - a marker yielded in place of a message, not raised
    """Yielded by a ``MessageSource`` when the storage cannot be read further on a topic (damaged chunk)."""


MessageSource = Callable[[Collection[str]], Iterator[tuple[str, int, Any]]]
"""``read(topics)`` yields ``(topic, log_time_ns, decoded)`` in log-time order; ``decoded`` is the exception
instance for a message that could not be decoded."""


@dataclass
class ExtractOptions:
    """Adapter options that shape extraction.

    Attributes:
        mapping: explicit mapping, or None to detect one from the topic types.
        hz: output rate (Hz); None keeps the source timestamps.
        gap_periods: gaps longer than this many output periods are not interpolated across.
        allow_empty: a log with no track rows is returned empty instead of being an error.
    """

    mapping: Mapping | None = None
    hz: float | None = 10.0
    gap_periods: float = 2.0
    allow_empty: bool = False

    @classmethod
    def from_settings(
        cls,
        mapping: Mapping | str | Path | None,
        overrides: Sequence[str],
        hz: float | None,
        gap_periods: float,
        allow_empty: bool,
    ) -> ExtractOptions:
        """The options of a log adapter's constructor: the mapping (object, file or None) with its CLI
        ``key=value`` overrides resolved, and ``hz`` 0 meaning "keep the source timestamps"."""
        return cls(resolve_mapping(mapping, overrides), hz or None, gap_periods, allow_empty)


@dataclass
class Extracted:
    """Result of one log: rows, ``LogMeta.attributes`` and per-topic problems kept (keep_going)."""

    tracks: pa.Table
    attributes: dict[str, Any]
    failures: list[SourceError] = field(default_factory=list)
    map_id: str | None = None


def _describe_topics(topics: Collection[TopicSummary]) -> str:
    parts = []
    for s in sorted(topics, key=lambda s: s.topic):
        why = "no messages" if s.count == 0 else unsupported_reason(s.msgtype)
        parts.append(f"{s.topic} ({s.msgtype}): {why}")
    return "; ".join(parts) if parts else "the log has no topics"


def _odd_topic(topics: Collection[TopicSummary]) -> str | None:
    """The topic to name in a no-tracks error: the only one, or the first with an odd type name."""
    if len(topics) == 1:
        return next(iter(topics)).topic
    for s in sorted(topics, key=lambda s: s.topic):
        if "/srv/" in s.msgtype or len(s.msgtype.split("/")) == 2:
            return s.topic
    return None


def extract_log(
    rel: str,
    topics: list[TopicSummary],
    read: MessageSource,
    opts: ExtractOptions,
    log_id: str,
    *,
    keep_going: bool,
) -> Extracted:
    """Turn one log into track rows.

    Raises:
        SourceError: a bad topic (unless ``keep_going``, then it is in ``failures``), or no tracks at all
            (unless ``allow_empty``), naming the file and topic.
    """
    failures: list[SourceError] = []

    def fail(err: SourceError) -> None:
        if not keep_going:
            raise err
        failures.append(err)

    by_name = {s.topic: s for s in topics}
    tf_topics = [s.topic for s in topics if topic_kind(s.msgtype) == "tf" and s.count != 0]
    tf = TfBuffer()
    tf_loaded = False
    counts: dict[str, int] = {}

    def load_tf() -> None:
        nonlocal tf_loaded
        if tf_loaded or not tf_topics:
            return
        tf_loaded = True
        for topic, _t, msg in read(tf_topics):
            counts[topic] = counts.get(topic, 0) + 1
            if isinstance(msg, BaseException):
                fail(SourceError(rel, f"cannot decode tf message: {_why(msg)}", line=counts[topic], field=topic))
                continue
            tf.add_message(msg, static="static" in topic)

    mapping = opts.mapping
    detected = mapping is None
    if mapping is None:
        has_candidates = any(topic_kind(s.msgtype) not in (None, "tf") and s.count != 0 for s in topics)
        if not has_candidates:
            load_tf()
        try:
            mapping = auto_mapping(topics, tf.dynamic_edges())
        except AmbiguousMappingError as err:
            if "no topic" not in str(err):
                raise SourceError(rel, str(err)) from None
            reason = f"no topic logpipe can turn into tracks: {_describe_topics(topics)}"
            if opts.allow_empty:
                return Extracted(empty_tracks(), {"empty_reason": reason, "message_counts": _counts(topics)})
            raise SourceError(rel, reason, field=_odd_topic(topics)) from None

    extractors: list[TopicExtractor] = []
    use_header = mapping.time == "header"
    sources: list[tuple[str, EgoSpec | Any, str]] = []
    if mapping.ego is not None and mapping.ego.topic:
        sources.append((mapping.ego.topic, mapping.ego, "ego"))
    sources += [(a.topic, a, "other") for a in mapping.agents]
    for topic, spec, role in sources:
        info = by_name.get(topic)
        if info is None:
            fail(SourceError(rel, f"topic is not in the log (topics: {', '.join(sorted(by_name))})", field=topic))
            continue
        try:
            extractors.append(TopicExtractor(topic, info.msgtype, role, spec, use_header))
        except ValueError as err:
            fail(SourceError(rel, str(err), field=topic))
    if (mapping.ego is not None and mapping.ego.tf) or any(ex.kind in OBJECT_KINDS.values() for ex in extractors):
        load_tf()

    by_topic = {ex.topic: ex for ex in extractors}
    dead: set[str] = set()
    if by_topic:
        for topic, t, msg in read(list(by_topic)):
            if topic in dead:
                continue
            counts[topic] = counts.get(topic, 0) + 1
            if isinstance(msg, BaseException):
                dead.add(topic)
                what = "reading stopped" if isinstance(msg, ReadStopped) else "cannot decode message"
                fail(SourceError(rel, f"{what}: {_why(msg)}", line=counts[topic], field=topic))
                continue
            try:
                by_topic[topic].add(msg, t)
            except (AttributeError, TypeError, ValueError, IndexError, KeyError) as err:
                dead.add(topic)
                fail(SourceError(rel, f"unexpected message content: {_why(err)}", line=counts[topic], field=topic))
    extractors = [ex for ex in extractors if ex.topic not in dead]
    for ex in extractors:
        declared = by_name[ex.topic].count
        if not ex.messages and declared:
            fail(
                SourceError(
                    rel,
                    f"the log declares {declared} messages on this topic but the reader yields none "
                    "(metadata.yaml does not match the storage file, e.g. in topic QoS or type)",
                    field=ex.topic,
                )
            )

    if mapping.ego is not None and mapping.ego.tf is not None:
        try:
            extractors.insert(0, ego_from_tf(mapping.ego, tf, "tf2_msgs/msg/TFMessage"))
        except FrameError as err:
            fail(SourceError(rel, err.reason, field=err.topic))

    world = world_frame_for(mapping, extractors, tf)
    if any(f not in ("", world) for ex in extractors for f in set(ex.obs.frames)):
        load_tf()
    ego_frame = _ego_frame(mapping, extractors)
    while True:
        try:
            wt = to_world(extractors, tf, world, ego_frame)
            break
        except FrameError as err:
            fail(SourceError(rel, err.reason, field=err.topic))
            extractors = [ex for ex in extractors if ex.topic != err.topic]
    spec = ResampleSpec(opts.hz, opts.gap_periods) if opts.hz else None
    table = world_to_table(log_id, wt, spec)
    if table.num_rows == 0 and not opts.allow_empty:
        used = ", ".join(sorted(ex.topic for ex in extractors)) or "none"
        span = (max(wt.t) - min(wt.t)) / 1e9 if len(wt.t) else 0.0
        reason = (
            f"no track rows: sources {used} give {len(wt.t)} samples spanning {span:.3f} s, which hold no "
            f"{opts.hz:g} Hz grid time"
            if opts.hz and len(wt.t)
            else f"no track rows from sources {used}"
        )
        if failures:
            reason += f" ({len(failures)} topic problems: {failures[0].describe()})"
        raise SourceError(rel, reason, field=next(iter(sorted(by_topic)), None))
    attributes: dict[str, Any] = {
        "mapping": mapping.to_dict(),
        "mapping_detected": detected,
        "world_frame": world,
        "ego_frame": ego_frame,
        "topics_used": {
            ex.topic: normalize_type(by_name[ex.topic].msgtype) for ex in extractors if ex.topic in by_name
        },
        "message_counts": _counts(topics),
        "messages_read": counts,
        "frame_ids": sorted({f for ex in extractors for f in ex.obs.frames}),
        "tracks": len(set(wt.track)),
        "source_rows": len(wt.t),
        "resampled_hz": opts.hz,
        # observations outside the time range of the transform that places them (no extrapolation): counted here
        # rather than failing the log, since a few objects before the first ego pose are normal
        "rows_without_transform": wt.dropped,
    }
    if tf_loaded:
        attributes["tf_edges"] = sorted(f"{e.parent}->{c}" for c, e in tf.edges.items())
    if failures:
        attributes["problems"] = [f.describe() for f in failures]
    return Extracted(table, attributes, failures, mapping.map_id)


def _counts(topics: Collection[TopicSummary]) -> dict[str, int | None]:
    return {s.topic: s.count for s in topics}


def _ego_frame(mapping: Mapping, extractors: list[TopicExtractor]) -> str | None:
    if mapping.ego is None:
        return None
    if mapping.ego.frame:
        return mapping.ego.frame.lstrip("/")
    if mapping.ego.tf:
        return mapping.ego.tf[1].lstrip("/")
    for ex in extractors:
        if ex.role == "ego" and ex.child_frames:
            return sorted(ex.child_frames)[0] or "base_link"
    return "base_link"


def _why(err: BaseException) -> str:
    text = str(err).strip().splitlines()[0] if str(err).strip() else ""
    return f"{type(err).__name__}: {text}" if text else type(err).__name__
