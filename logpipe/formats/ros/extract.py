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

from logpipe.dataset.resample import ResampleSpec
from logpipe.errors import SourceError
from logpipe.formats.base import empty_tracks
from logpipe.formats.ros.mapping import (
    AmbiguousMappingError,
    EgoSpec,
    Mapping,
    TopicSummary,
    auto_mapping,
    resolve_mapping,
)
from logpipe.formats.ros.message_types import OBJECT_KINDS, normalize_type, topic_kind, unsupported_reason
from logpipe.formats.ros.messages import TopicExtractor
from logpipe.formats.ros.tf import TfBuffer
from logpipe.formats.ros.world import FrameError, WorldTracks, ego_from_tf, to_world, world_frame_for, world_to_table
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


@dataclass
class _LogRead:
    """The state of reading one log: the reader, problems kept so far and the lazily loaded tf tree.

    Attributes:
        counts: messages read per topic (tf topics and sources, in reading order).
        tf_loaded: whether the tf topics have been read into ``tf``.
    """

    rel: str
    read: MessageSource
    keep_going: bool
    tf_topics: list[str]
    tf: TfBuffer = field(default_factory=TfBuffer)
    tf_loaded: bool = False
    counts: dict[str, int] = field(default_factory=dict)
    failures: list[SourceError] = field(default_factory=list)

    def fail(self, err: SourceError) -> None:
        """Raise ``err``, or keep it when going on past per-topic problems."""
        if not self.keep_going:
            raise err
        self.failures.append(err)

    def load_tf(self) -> None:
        """Read the tf topics once, when a step first needs transforms."""
        if self.tf_loaded or not self.tf_topics:
            return
        self.tf_loaded = True
        for topic, _t, msg in self.read(self.tf_topics):
            self.counts[topic] = self.counts.get(topic, 0) + 1
            if isinstance(msg, BaseException):
                self.fail(SourceError(self.rel, f"cannot decode tf message: {_why(msg)}", line=self.counts[topic],
                                      field=topic))  # fmt: skip
                continue
            self.tf.add_message(msg, static="static" in topic)


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
    run = _LogRead(rel, read, keep_going, [s.topic for s in topics if topic_kind(s.msgtype) == "tf" and s.count != 0])
    detected = opts.mapping is None
    mapping = opts.mapping if opts.mapping is not None else _detect_mapping(run, topics, opts.allow_empty)
    if isinstance(mapping, Extracted):
        return mapping
    by_name = {s.topic: s for s in topics}
    extractors = _make_extractors(run, mapping, by_name)
    if (mapping.ego is not None and mapping.ego.tf) or any(ex.kind in OBJECT_KINDS.values() for ex in extractors):
        run.load_tf()
    source_topics = sorted(ex.topic for ex in extractors)
    extractors = _read_messages(run, extractors, by_name)
    wt, world, ego_frame, extractors = _place_in_world(run, mapping, extractors)
    spec = ResampleSpec(opts.hz, opts.gap_periods) if opts.hz else None
    table = world_to_table(log_id, wt, spec)
    if table.num_rows == 0 and not opts.allow_empty:
        raise SourceError(rel, _no_rows_reason(run, extractors, wt, opts.hz), field=next(iter(source_topics), None))
    attributes: dict[str, Any] = {
        "mapping": mapping.to_dict(),
        "mapping_detected": detected,
        "world_frame": world,
        "ego_frame": ego_frame,
        "topics_used": {
            ex.topic: normalize_type(by_name[ex.topic].msgtype) for ex in extractors if ex.topic in by_name
        },
        "message_counts": _counts(topics),
        "messages_read": run.counts,
        "frame_ids": sorted({f for ex in extractors for f in ex.obs.frames}),
        "tracks": len(set(wt.track)),
        "source_rows": len(wt.t),
        "resampled_hz": opts.hz,
        # observations outside the time range of the transform that places them (no extrapolation): counted here
        # rather than failing the log, since a few objects before the first ego pose are normal
        "rows_without_transform": wt.dropped,
    }
    if run.tf_loaded:
        attributes["tf_edges"] = sorted(f"{e.parent}->{c}" for c, e in run.tf.edges.items())
    if run.failures:
        attributes["problems"] = [f.describe() for f in run.failures]
    return Extracted(table, attributes, run.failures, mapping.map_id)


def _detect_mapping(run: _LogRead, topics: list[TopicSummary], allow_empty: bool) -> Mapping | Extracted:
    """The mapping detected from the topic types (and the moving tf edges when no topic is a track source),
    or an empty result when nothing is trackable and ``allow_empty``.

    Raises:
        SourceError: the detection is ambiguous, or nothing is trackable (without ``allow_empty``).
    """
    if not any(topic_kind(s.msgtype) not in (None, "tf") and s.count != 0 for s in topics):
        run.load_tf()
    try:
        return auto_mapping(topics, run.tf.dynamic_edges())
    except AmbiguousMappingError as err:
        if "no topic" not in str(err):
            raise SourceError(run.rel, str(err)) from None
        reason = f"no topic logpipe can turn into tracks: {_describe_topics(topics)}"
        if allow_empty:
            return Extracted(empty_tracks(), {"empty_reason": reason, "message_counts": _counts(topics)})
        raise SourceError(run.rel, reason, field=_odd_topic(topics)) from None


def _make_extractors(run: _LogRead, mapping: Mapping, by_name: dict[str, TopicSummary]) -> list[TopicExtractor]:
    """One extractor per mapped topic (the ego first); a topic missing from the log or of an unsupported type
    is a problem."""
    extractors: list[TopicExtractor] = []
    use_header = mapping.time == "header"
    sources: list[tuple[str, EgoSpec | Any, str]] = []
    if mapping.ego is not None and mapping.ego.topic:
        sources.append((mapping.ego.topic, mapping.ego, "ego"))
    sources += [(a.topic, a, "other") for a in mapping.agents]
    for topic, spec, role in sources:
        info = by_name.get(topic)
        if info is None:
            run.fail(SourceError(run.rel, f"topic is not in the log (topics: {', '.join(sorted(by_name))})",
                                 field=topic))  # fmt: skip
            continue
        try:
            extractors.append(TopicExtractor(topic, info.msgtype, role, spec, use_header))
        except ValueError as err:
            run.fail(SourceError(run.rel, str(err), field=topic))
    return extractors


def _read_messages(
    run: _LogRead, extractors: list[TopicExtractor], by_name: dict[str, TopicSummary]
) -> list[TopicExtractor]:
    """Feed every source topic's messages to its extractor; the extractors of topics that could not be read to
    the end (a message that does not decode or does not fit its type) are dropped, with a problem each."""
    by_topic = {ex.topic: ex for ex in extractors}
    dead: set[str] = set()
    if by_topic:
        for topic, t, msg in run.read(list(by_topic)):
            if topic in dead:
                continue
            run.counts[topic] = run.counts.get(topic, 0) + 1
            line = run.counts[topic]
            if isinstance(msg, BaseException):
                dead.add(topic)
                what = "reading stopped" if isinstance(msg, ReadStopped) else "cannot decode message"
                run.fail(SourceError(run.rel, f"{what}: {_why(msg)}", line=line, field=topic))
                continue
            try:
                by_topic[topic].add(msg, t)
            except (AttributeError, TypeError, ValueError, IndexError, KeyError) as err:
                dead.add(topic)
                run.fail(SourceError(run.rel, f"unexpected message content: {_why(err)}", line=line, field=topic))
    extractors = [ex for ex in extractors if ex.topic not in dead]
    for ex in extractors:
        declared = by_name[ex.topic].count
        if not ex.messages and declared:
            run.fail(
                SourceError(
                    run.rel,
                    f"the log declares {declared} messages on this topic but the reader yields none "
                    "(metadata.yaml does not match the storage file, e.g. in topic QoS or type)",
                    field=ex.topic,
                )
            )
    return extractors


def _place_in_world(
    run: _LogRead, mapping: Mapping, extractors: list[TopicExtractor]
) -> tuple[WorldTracks, str, str | None, list[TopicExtractor]]:
    """The observations in the world frame, that frame, the ego's body frame and the extractors kept: the tf
    ego is added first, and a topic whose frame has no path to the world frame is dropped with a problem."""
    if mapping.ego is not None and mapping.ego.tf is not None:
        try:
            extractors.insert(0, ego_from_tf(mapping.ego, run.tf, "tf2_msgs/msg/TFMessage"))
        except FrameError as err:
            run.fail(SourceError(run.rel, err.reason, field=err.topic))
    world = world_frame_for(mapping, extractors, run.tf)
    if any(f not in ("", world) for ex in extractors for f in set(ex.obs.frames)):
        run.load_tf()
    ego_frame = _ego_frame(mapping, extractors)
    while True:
        try:
            return to_world(extractors, run.tf, world, ego_frame), world, ego_frame, extractors
        except FrameError as err:
            run.fail(SourceError(run.rel, err.reason, field=err.topic))
            extractors = [ex for ex in extractors if ex.topic != err.topic]


def _no_rows_reason(run: _LogRead, extractors: list[TopicExtractor], wt: WorldTracks, hz: float | None) -> str:
    """Why a log gives no track rows, in words: its sources, their samples and span, and the first problem."""
    used = ", ".join(sorted(ex.topic for ex in extractors)) or "none"
    span = (max(wt.t) - min(wt.t)) / 1e9 if len(wt.t) else 0.0
    reason = (
        f"no track rows: sources {used} give {len(wt.t)} samples spanning {span:.3f} s, which hold no "
        f"{hz:g} Hz grid time"
        if hz and len(wt.t)
        else f"no track rows from sources {used}"
    )
    if run.failures:
        reason += f" ({len(run.failures)} topic problems: {run.failures[0].describe()})"
    return reason


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
