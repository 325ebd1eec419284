"""The mapping: which topics of a bag/MCAP are the ego and which are other agents, and how to read them —
written in a mapping file, or detected from the topic types (``auto_mapping``).

A mapping is a small TOML or YAML document; every key is optional::

    map = "barc_lab"            # LogMeta.map_id
    world_frame = "map"         # the fixed frame x/y are expressed in (default: the ego's frame)
    time = "header"             # "header" (message header stamp, log time when it is 0) or "log"

    [ego]
    topic = "/ego_pose"         # nav_msgs/Odometry, geometry_msgs/PoseStamped or PoseWithCovarianceStamped
    # tf = ["odom", "base_footprint"]   # ... or a (parent, child) frame pair read from /tf
    object_type = "vehicle"

    [[agents]]                  # one pose topic per agent ...
    topic = "/red_pose"
    track_id = "red"
    object_type = "vehicle"

    [[agents]]                  # ... or an object-array topic (MarkerArray, ObjectArray, TrackedObjects,
    topic = "/objects"          #     Detection3DArray): one track per object id
    object_type = "vehicle"     # only used when the message carries no class

``logpipe inspect INPUT --format toml`` prints the mapping detected in an input as such a file.

CLI overrides are ``key=value`` strings merged over the file: ``map=lab``, ``world_frame=odom``,
``ego=/odom`` (ego topic), ``ego.tf=odom:base_link``, ``ego.object_type=vehicle``, ``agent=/red_pose``
(appends an agent; ``agent=/red_pose:red:vehicle`` also sets its track id and type), ``time=log``.
"""

from __future__ import annotations

import tomllib
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml

from logpipe.errors import SourceError
from logpipe.formats.ros.message_types import EGO_KINDS, OBJECT_KINDS, topic_kind
from logpipe.storage.regular_files import parse_nested, read_regular_text
from logpipe.types import OBJECT_TYPES

TIME_SOURCES = ("header", "log")


@dataclass(frozen=True)
class EgoSpec:
    """Where the ego pose comes from: one pose/odometry topic, or a tf frame pair.

    Attributes:
        topic: pose topic (Odometry / PoseStamped / PoseWithCovarianceStamped), or None for tf.
        tf: (parent, child) frames; the ego is the child frame's origin expressed in the parent frame.
        track_id: the ego's track id in the track table.
        object_type: normalised class of the ego (``ObjectType`` value).
        frame: the ego's body frame: objects given in it are placed with the ego pose at their stamp
            (default: the Odometry ``child_frame_id``, the tf child, else ``base_link``).
    """

    topic: str | None = None
    tf: tuple[str, str] | None = None
    track_id: str = "ego"
    object_type: str = "vehicle"
    frame: str | None = None


@dataclass(frozen=True)
class AgentSpec:
    """One topic that carries other agents.

    Attributes:
        topic: the topic (pose topic = one agent; object-array topic = one agent per object id).
        track_id: track id for a single-agent pose topic (default: derived from the topic name);
            for object arrays, a prefix put before every object id (default: none).
        object_type: class used when the message gives none (``ObjectType`` value).
    """

    topic: str
    track_id: str | None = None
    object_type: str = "unknown"


@dataclass(frozen=True)
class Mapping:
    """How to turn a log's messages into tracks (see the module docstring for the file format).

    Attributes:
        ego: the ego source, or None (a log of other agents only, e.g. turtlesim).
        agents: other-agent sources.
        map_id: map/city name written to ``LogMeta.map_id``.
        world_frame: fixed frame x/y are expressed in; None = the ego's frame (or the objects' frame).
        time: ``header`` (use ``header.stamp`` when non-zero, else log time) or ``log`` (record time).
    """

    ego: EgoSpec | None = None
    agents: tuple[AgentSpec, ...] = ()
    map_id: str | None = None
    world_frame: str | None = None
    time: str = "header"

    @property
    def topics(self) -> list[str]:
        """Every topic the mapping reads (ego first)."""
        out = [self.ego.topic] if self.ego and self.ego.topic else []
        return out + [a.topic for a in self.agents]

    def to_dict(self) -> dict[str, Any]:
        """Plain dict (for ``inspect --json`` and log attributes)."""
        out: dict[str, Any] = {"time": self.time}
        if self.map_id is not None:
            out["map"] = self.map_id
        if self.world_frame is not None:
            out["world_frame"] = self.world_frame
        if self.ego is not None:
            ego: dict[str, Any] = {"object_type": self.ego.object_type}
            if self.ego.track_id != "ego":
                ego["track_id"] = self.ego.track_id
            if self.ego.topic:
                ego["topic"] = self.ego.topic
            if self.ego.tf:
                ego["tf"] = list(self.ego.tf)
            if self.ego.frame:
                ego["frame"] = self.ego.frame
            out["ego"] = ego
        out["agents"] = [
            {"topic": a.topic, "object_type": a.object_type} | ({"track_id": a.track_id} if a.track_id else {})
            for a in self.agents
        ]
        return out

    def to_toml(self) -> str:
        """The mapping as a TOML mapping file: ``read_mapping_document`` + ``mapping_from_dict`` give it back
        (what ``logpipe inspect --format toml`` prints for ``logpipe ingest --mapping``)."""
        import tomli_w  # only this writes TOML (the standard library reads it only)

        return tomli_w.dumps(self.to_dict())


def _check_type(value: Any, where: str, source: str) -> str:
    text = str(value)
    if text not in OBJECT_TYPES:
        raise SourceError(source, f"object_type {text!r} is not one of {list(OBJECT_TYPES)}", field=where)
    return text


def mapping_from_dict(data: dict[str, Any], source: str = "<mapping>") -> Mapping:
    """Validate a parsed mapping document.

    Raises:
        SourceError: unknown keys, wrong types or unknown object types, naming the key.
    """
    known = {"map", "world_frame", "time", "ego", "agents"}
    unknown = sorted(set(data) - known)
    if unknown:
        raise SourceError(source, f"unknown mapping keys {unknown}; known: {sorted(known)}", field=unknown[0])
    ego: EgoSpec | None = None
    raw_ego = data.get("ego")
    if isinstance(raw_ego, str):
        raw_ego = {"topic": raw_ego}
    if raw_ego is not None:
        if not isinstance(raw_ego, dict):
            raise SourceError(source, "must be a table with 'topic' or 'tf'", field="ego")
        tf = raw_ego.get("tf")
        if isinstance(tf, str):
            tf = tf.split(":")
        if tf is not None and (not isinstance(tf, list | tuple) or len(tf) != 2):
            raise SourceError(source, "tf must be a [parent, child] frame pair", field="ego.tf")
        topic = raw_ego.get("topic")
        if (topic is None) == (tf is None):
            raise SourceError(source, "give exactly one of 'topic' and 'tf'", field="ego")
        ego = EgoSpec(
            topic=str(topic) if topic is not None else None,
            tf=(str(tf[0]), str(tf[1])) if tf is not None else None,
            track_id=str(raw_ego.get("track_id", "ego")),
            object_type=_check_type(raw_ego.get("object_type", "vehicle"), "ego.object_type", source),
            frame=str(raw_ego["frame"]) if raw_ego.get("frame") is not None else None,
        )
    agents: list[AgentSpec] = []
    raw_agents = data.get("agents", [])
    if not isinstance(raw_agents, list):
        raise SourceError(source, "must be a list of tables", field="agents")
    for i, item in enumerate(raw_agents):
        raw = {"topic": item} if isinstance(item, str) else item
        if not isinstance(raw, dict) or "topic" not in raw:
            raise SourceError(source, "each agent needs a 'topic'", field=f"agents[{i}]")
        agents.append(
            AgentSpec(
                topic=str(raw["topic"]),
                track_id=str(raw["track_id"]) if raw.get("track_id") is not None else None,
                object_type=_check_type(raw.get("object_type", "unknown"), f"agents[{i}].object_type", source),
            )
        )
    time = str(data.get("time", "header"))
    if time not in TIME_SOURCES:
        raise SourceError(source, f"time must be one of {list(TIME_SOURCES)}", field="time")
    return Mapping(
        ego=ego,
        agents=tuple(agents),
        map_id=str(data["map"]) if data.get("map") is not None else None,
        world_frame=str(data["world_frame"]) if data.get("world_frame") is not None else None,
        time=time,
    )


def read_mapping_document(path: Path) -> dict[str, Any]:
    """Parse a TOML (``.toml``) or YAML (anything else) mapping file into a dict.

    Raises:
        SourceError: unreadable file or syntax error.
    """
    try:
        text = read_regular_text(path)  # a FIFO would block forever
        data = parse_nested(tomllib.loads if path.suffix == ".toml" else yaml.safe_load, text)
    except (OSError, ValueError, tomllib.TOMLDecodeError, yaml.YAMLError) as err:  # ValueError: not UTF-8
        raise SourceError(str(path), f"cannot read mapping: {err}") from None
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise SourceError(str(path), "a mapping file must hold a table/dict at the top level")
    return data


def apply_overrides(data: dict[str, Any], overrides: Sequence[str], source: str = "<cli>") -> dict[str, Any]:
    """``data`` with CLI ``key=value`` overrides merged over it (see the module docstring)."""
    out = dict(data)
    for item in overrides:
        key, sep, value = item.partition("=")
        key = key.strip()
        if not sep or not key:
            raise SourceError(source, f"override {item!r} is not key=value")
        if key == "agent":
            topic, _, rest = value.partition(":")
            track_id, _, object_type = rest.partition(":")
            agent: dict[str, Any] = {"topic": topic}
            if track_id:
                agent["track_id"] = track_id
            if object_type:
                agent["object_type"] = object_type
            out["agents"] = [*out.get("agents", []), agent]
        elif key == "ego":
            out["ego"] = {"topic": value}
        elif key.startswith("ego."):
            sub = key.removeprefix("ego.")
            ego = dict(out.get("ego") or {}) if isinstance(out.get("ego"), dict) else {}
            if sub == "tf":
                ego.pop("topic", None)
                ego["tf"] = value.split(":")
            elif sub == "topic":
                ego.pop("tf", None)
                ego["topic"] = value
            else:
                ego[sub] = value
            out["ego"] = ego
        elif key in {"map", "world_frame", "time"}:
            out[key] = value
        else:
            raise SourceError(source, f"unknown override key {key!r}", field=key)
    return out


def load_mapping(path: Path | None = None, overrides: Sequence[str] = ()) -> Mapping | None:
    """The mapping from ``path`` (TOML/YAML) with ``overrides`` merged over it; None when neither is given."""
    if path is None and not overrides:
        return None
    data = read_mapping_document(path) if path is not None else {}
    data = apply_overrides(data, overrides)
    return mapping_from_dict(data, str(path) if path is not None else "<cli>")


def resolve_mapping(mapping: Mapping | str | Path | None, overrides: Sequence[str] = ()) -> Mapping | None:
    """A ``Mapping`` from a ``Mapping``, a TOML/YAML path or None, with CLI ``key=value`` overrides merged over it
    (what the adapters' ``mapping=`` / ``mapping_overrides=`` constructor options accept)."""
    if isinstance(mapping, Mapping):
        return mapping_from_dict(apply_overrides(mapping.to_dict(), overrides)) if overrides else mapping
    return load_mapping(Path(mapping) if mapping is not None else None, overrides)


# --- automatic mapping ----------------------------------------------------------------------------------


@dataclass(frozen=True)
class TopicSummary:
    """What a reader says about one topic before reading it.

    Attributes:
        topic: name; msgtype: type as stored; count: messages (None if unknown).
    """

    topic: str
    msgtype: str
    count: int | None


class AmbiguousMappingError(ValueError):
    """Automatic detection found no or several possible choices."""


def auto_mapping(topics: Iterable[TopicSummary], tf_edges: Sequence[tuple[str, str]] = ()) -> Mapping:
    """Choose ego and agents from the topic types alone, when the choice is unambiguous.

    Rules: every object-array and turtlesim/Pose topic is an agent source. The ego is the only
    Odometry/PoseStamped/PoseWithCovarianceStamped topic; or the only one whose name contains ``ego`` (the
    other PoseStamped topics are then agents, as in the datmo bags); or the only Odometry topic (other pose
    topics are taken as the same robot, e.g. AMCL, and ignored); else the only moving tf edge when no pose
    topic exists. Topics with no messages are ignored.

    Raises:
        AmbiguousMappingError: several candidates and no rule picks one, or nothing trackable.
    """
    live = [s for s in topics if s.count is None or s.count > 0]
    kinds = {s.topic: topic_kind(s.msgtype) for s in live}
    agents = [
        AgentSpec(topic=s.topic)
        for s in live
        if kinds[s.topic] in OBJECT_KINDS.values() or kinds[s.topic] == "turtlesim"
    ]
    candidates = [s.topic for s in live if kinds[s.topic] in EGO_KINDS]
    odometry = [t for t in candidates if kinds[t] == "odometry"]
    named = [t for t in candidates if "ego" in t.lower()]
    ego: EgoSpec | None = None
    if len(candidates) == 1:
        ego = EgoSpec(topic=candidates[0])
    elif len(named) == 1:
        ego = EgoSpec(topic=named[0])
        agents += [AgentSpec(topic=t) for t in candidates if t != named[0] and kinds[t] == "pose"]
    elif len(odometry) == 1:
        ego = EgoSpec(topic=odometry[0])
    elif candidates:
        raise AmbiguousMappingError(
            f"{len(candidates)} pose topics could be the ego ({', '.join(sorted(candidates))}) and none is named "
            "'ego' or is the only Odometry: give a mapping (ego=TOPIC, agent=TOPIC)"
        )
    elif not agents and len(tf_edges) == 1:
        ego = EgoSpec(tf=tf_edges[0])
    elif not agents and len(tf_edges) > 1:
        raise AmbiguousMappingError(
            "no pose topic, and several moving tf edges could be the ego "
            f"({', '.join(f'{p}->{c}' for p, c in tf_edges)}): give a mapping (ego.tf=PARENT:CHILD)"
        )
    if ego is None and not agents:
        raise AmbiguousMappingError("no topic logpipe can turn into tracks")
    return Mapping(ego=ego, agents=tuple(agents))
