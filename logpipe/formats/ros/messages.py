"""ROS message decoding: one topic's decoded messages → observations, with their class and track ids.

Decoded messages are read by attribute (rosbags, mcap-ros1/ros2 and namespaced JSON objects all look alike)
and collected as ``Observations`` in the frame the message gives (its header ``frame_id``); ``world.py`` places
them in the world frame. Units: metres, radians (CCW from +x), m/s, nanoseconds.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field
from typing import Any

from logpipe.formats.ros.mapping import AgentSpec, EgoSpec
from logpipe.formats.ros.message_types import normalize_type, topic_kind, unsupported_reason

# --- label → ObjectType ------------------------------------------------------------------------------

_LABEL_RULES: tuple[tuple[str, str], ...] = (
    (r"motor", "motorcyclist"),
    (r"ped|person|walker|human|people", "pedestrian"),
    (r"bicycl|cyclist|bike|rider", "cyclist"),
    (r"bus|truck|trailer|lorry", "bus_truck"),
    (r"car|vehicle|van|suv|auto", "vehicle"),
)


def object_type_from_label(label: str, default: str = "unknown") -> str:
    """Normalised ``ObjectType`` value for a free-text class label (keyword match), else ``default``."""
    low = label.lower()
    for pattern, value in _LABEL_RULES:
        if re.search(pattern, low):
            return value
    return default


# derived_object_msgs/Object.classification constants → ObjectType.
DERIVED_CLASSES: dict[int, tuple[str, str]] = {
    0: ("UNKNOWN", "unknown"),
    1: ("UNKNOWN_SMALL", "unknown"),
    2: ("UNKNOWN_MEDIUM", "unknown"),
    3: ("UNKNOWN_BIG", "unknown"),
    4: ("PEDESTRIAN", "pedestrian"),
    5: ("BIKE", "cyclist"),
    6: ("CAR", "vehicle"),
    7: ("TRUCK", "bus_truck"),
    8: ("MOTORCYCLE", "motorcyclist"),
    9: ("OTHER_VEHICLE", "vehicle"),
    10: ("BARRIER", "unknown"),
    11: ("SIGN", "unknown"),
}

# autoware(_auto)_perception_msgs/ObjectClassification.label constants → ObjectType.
AUTOWARE_CLASSES: dict[int, tuple[str, str]] = {
    0: ("UNKNOWN", "unknown"),
    1: ("CAR", "vehicle"),
    2: ("TRUCK", "bus_truck"),
    3: ("BUS", "bus_truck"),
    4: ("TRAILER", "bus_truck"),
    5: ("MOTORCYCLE", "motorcyclist"),
    6: ("BICYCLE", "cyclist"),
    7: ("PEDESTRIAN", "pedestrian"),
}


# --- small field helpers -----------------------------------------------------------------------------


def stamp_ns(stamp: Any) -> int:
    """Nanoseconds of a ROS time (``sec/nanosec`` in ROS 2 and rosbags, ``secs/nsecs`` in genpy ROS 1)."""
    sec: Any = getattr(stamp, "sec", None)
    if sec is None:
        sec = getattr(stamp, "secs", None)
    if sec is None:  # google.protobuf.Timestamp (Foxglove protobuf schemas)
        return int(getattr(stamp, "seconds", 0) or 0) * 1_000_000_000 + int(getattr(stamp, "nanos", 0) or 0)
    nsec: Any = getattr(stamp, "nanosec", None)
    if nsec is None:
        nsec = getattr(stamp, "nsecs", None)
    if nsec is None:
        nsec = getattr(stamp, "nsec", 0)
    return int(sec or 0) * 1_000_000_000 + int(nsec or 0)


def clean_frame(frame: str) -> str:
    """tf frame name without the ROS 1 leading slash."""
    return frame[1:] if frame.startswith("/") else frame


def track_id_from_topic(topic: str) -> str:
    """A readable track id for a one-agent pose topic: ``/red_pose`` → ``red``, ``/turtle1/pose`` → ``turtle1``."""
    name = topic.strip("/")
    for suffix in ("/pose", "_pose", "/odom", "_odom"):
        if name.endswith(suffix) and len(name) > len(suffix):
            name = name[: -len(suffix)]
            break
    return name.replace("/", "_") or topic


# --- observations ------------------------------------------------------------------------------------


@dataclass
class Observations:
    """Per-message observations of one source, in the message's own frame, as growing columns.

    Attributes:
        t: timestamps (ns); px/py/pz: position (m, frame ``frames[i]``); q: orientation quaternion (x, y, z, w)
        in that frame; v: velocity (m/s) expressed in the body frame (``v_body``) or in ``frames[i]``;
        length/width: box size (m, NaN if unknown); track/object_type/source_type: identity and class.
    """

    role: str
    v_body: bool
    t: list[int] = field(default_factory=list)
    track: list[str] = field(default_factory=list)
    frames: list[str] = field(default_factory=list)
    pos: list[tuple[float, float, float]] = field(default_factory=list)
    quat: list[tuple[float, float, float, float]] = field(default_factory=list)
    vel: list[tuple[float, float, float]] = field(default_factory=list)
    size: list[tuple[float, float]] = field(default_factory=list)
    object_type: list[str] = field(default_factory=list)
    source_type: list[str] = field(default_factory=list)

    def add(
        self,
        t: int,
        track: str,
        frame: str,
        pose: Any,
        vel: tuple[float, float, float],
        size: tuple[float, float],
        object_type: str,
        source_type: str,
    ) -> None:
        """Append one observation of ``pose`` (a geometry_msgs/Pose)."""
        p, o = pose.position, pose.orientation
        self.t.append(t)
        self.track.append(track)
        self.frames.append(frame)
        self.pos.append((p.x, p.y, p.z))
        self.quat.append((o.x, o.y, o.z, o.w))
        self.vel.append(vel)
        self.size.append(size)
        self.object_type.append(object_type)
        self.source_type.append(source_type)

    def __len__(self) -> int:
        return len(self.t)


NAN3 = (math.nan, math.nan, math.nan)
NAN2 = (math.nan, math.nan)


class TopicExtractor:
    """Turns the decoded messages of one topic into ``Observations``.

    Attributes:
        topic, kind, msgtype: the topic, its kind (``POSE_KINDS``/``OBJECT_KINDS`` value) and normalised type.
        role: ``ego`` or ``other``.
        spec: the mapping entry it implements.
    """

    def __init__(
        self,
        topic: str,
        msgtype: str,
        role: str,
        spec: EgoSpec | AgentSpec,
        use_header: bool,
        *,
        kind: str | None = None,
    ) -> None:
        """``kind`` is detected from ``msgtype``; only the tf ego (filled by ``ego_from_tf``) passes ``tf_ego``.

        Raises:
            ValueError: ``msgtype`` is not a pose or object-array type.
        """
        self.topic = topic
        self.msgtype = normalize_type(msgtype)
        kind = kind or topic_kind(self.msgtype)
        if kind is None or kind == "tf":
            raise ValueError(unsupported_reason(msgtype))
        self.kind = kind
        self.role = role
        self.spec = spec
        self.use_header = use_header
        self.source_type = self.msgtype
        if isinstance(spec, EgoSpec):
            self.track_id = spec.track_id
            self.prefix = ""
        else:
            self.track_id = spec.track_id or track_id_from_topic(topic)
            self.prefix = f"{spec.track_id}/" if spec.track_id else ""
        self.default_type = spec.object_type
        self.obs = Observations(role=role, v_body=kind in {"odometry", "turtlesim", "autoware_tracked"})
        self.child_frames: set[str] = set()
        self.messages = 0
        self._handler = getattr(self, f"_add_{kind}", None)

    def _time(self, header: Any, log_time: int) -> int:
        if self.use_header and header is not None:
            t = stamp_ns(header.stamp)
            if t:
                return t
        return log_time

    def add(self, msg: Any, log_time: int) -> None:
        """Consume one decoded message received at ``log_time`` (ns)."""
        self.messages += 1
        if self._handler is None:
            raise TypeError(f"{self.kind} observations are not read from messages")
        self._handler(msg, log_time)

    # one-agent poses

    def _add_pose(self, msg: Any, log_time: int) -> None:
        h = msg.header
        self.obs.add(
            self._time(h, log_time), self.track_id, clean_frame(h.frame_id), msg.pose,
            NAN3, NAN2, self.default_type, self.source_type,
        )  # fmt: skip

    def _add_pose_cov(self, msg: Any, log_time: int) -> None:
        h = msg.header
        self.obs.add(
            self._time(h, log_time), self.track_id, clean_frame(h.frame_id), msg.pose.pose,
            NAN3, NAN2, self.default_type, self.source_type,
        )  # fmt: skip

    def _add_foxglove_pose(self, msg: Any, log_time: int) -> None:
        t = stamp_ns(msg.timestamp) if self.use_header else 0
        self.obs.add(
            t or log_time, self.track_id, clean_frame(msg.frame_id), msg.pose,
            NAN3, NAN2, self.default_type, self.source_type,
        )  # fmt: skip

    def _add_odometry(self, msg: Any, log_time: int) -> None:
        h = msg.header
        lin = msg.twist.twist.linear
        self.child_frames.add(clean_frame(msg.child_frame_id))
        self.obs.add(
            self._time(h, log_time), self.track_id, clean_frame(h.frame_id), msg.pose.pose,
            (lin.x, lin.y, lin.z), NAN2, self.default_type, self.source_type,
        )  # fmt: skip

    def _add_turtlesim(self, msg: Any, log_time: int) -> None:
        # turtlesim/Pose has no header: its plane is its own world, and speed is along theta.
        half = 0.5 * float(msg.theta)
        pose = Pose(msg.x, msg.y, 0.0, 0.0, 0.0, math.sin(half), math.cos(half))
        self.obs.add(
            log_time, self.track_id, "", pose, (float(msg.linear_velocity), 0.0, 0.0), NAN2,
            self.default_type, self.source_type,
        )  # fmt: skip

    # object arrays

    def _add_markers(self, msg: Any, log_time: int) -> None:
        for m in msg.markers:
            if int(m.action) not in (0, 1):  # ADD / MODIFY; DELETE (2) and DELETEALL (3) carry no pose
                continue
            ns = str(m.ns)
            tid = f"{self.prefix}{ns}/{m.id}" if ns else f"{self.prefix}{m.id}"
            self.obs.add(
                self._time(m.header, log_time), tid, clean_frame(m.header.frame_id), m.pose, NAN3,
                (float(m.scale.x), float(m.scale.y)), object_type_from_label(ns, self.default_type),
                f"{self.source_type}:{ns}" if ns else self.source_type,
            )  # fmt: skip

    def _add_derived_objects(self, msg: Any, log_time: int) -> None:
        for o in msg.objects:
            h = o.header if clean_frame(o.header.frame_id) else msg.header
            t = self._time(o.header, 0) or self._time(msg.header, log_time)
            name, otype = DERIVED_CLASSES.get(int(o.classification), ("UNKNOWN", "unknown"))
            if otype == "unknown":
                otype = self.default_type
            dims = list(o.shape.dimensions)
            size = (float(dims[0]), float(dims[1])) if len(dims) >= 2 else NAN2
            lin = o.twist.linear
            self.obs.add(
                t, f"{self.prefix}{o.id}", clean_frame(h.frame_id), o.pose, (lin.x, lin.y, lin.z), size,
                otype, f"{self.source_type}:{name}",
            )  # fmt: skip

    def _add_autoware_tracked(self, msg: Any, log_time: int) -> None:
        t = self._time(msg.header, log_time)
        frame = clean_frame(msg.header.frame_id)
        for o in msg.objects:
            uuid = getattr(o, "object_id", None)
            raw = getattr(uuid, "uuid", uuid)
            tid = bytes(bytearray(raw)).hex() if raw is not None and not isinstance(raw, int) else str(raw)
            best = max(o.classification, key=lambda c: float(c.probability), default=None)
            name, otype = AUTOWARE_CLASSES.get(int(best.label), ("UNKNOWN", "unknown")) if best else ("?", "unknown")
            if otype == "unknown":
                otype = self.default_type
            k = o.kinematics
            lin = k.twist_with_covariance.twist.linear
            shape = o.shape[0] if isinstance(o.shape, list | tuple) else o.shape
            dims = shape.dimensions
            self.obs.add(
                t, f"{self.prefix}{tid}", frame, k.pose_with_covariance.pose, (lin.x, lin.y, lin.z),
                (float(dims.x), float(dims.y)), otype, f"{self.source_type}:{name}",
            )  # fmt: skip

    def _add_detection3d(self, msg: Any, log_time: int) -> None:
        for d in msg.detections:
            tid = str(getattr(d, "id", "") or getattr(d, "tracking_id", "") or "")
            if not tid:
                raise ValueError("Detection3D without a tracking id ('id' is empty): detections are not tracks")
            h = d.header if clean_frame(d.header.frame_id) else msg.header
            t = self._time(d.header, 0) or self._time(msg.header, log_time)
            label = ""
            if len(d.results):
                r = d.results[0]
                hyp = getattr(r, "hypothesis", None)
                label = str(getattr(hyp, "class_id", "") if hyp is not None else getattr(r, "id", ""))
            size = d.bbox.size
            self.obs.add(
                t, f"{self.prefix}{tid}", clean_frame(h.frame_id), d.bbox.center, NAN3,
                (float(size.x), float(size.y)), object_type_from_label(label, self.default_type),
                f"{self.source_type}:{label}" if label else self.source_type,
            )  # fmt: skip


@dataclass
class _Vec:
    x: float
    y: float
    z: float


@dataclass
class _Quat:
    x: float
    y: float
    z: float
    w: float


class Pose:
    """A geometry_msgs/Pose look-alike for sources without one (turtlesim, the tf ego)."""

    __slots__ = ("orientation", "position")

    def __init__(self, x: float, y: float, z: float, qx: float, qy: float, qz: float, qw: float) -> None:
        self.position = _Vec(x, y, z)
        self.orientation = _Quat(qx, qy, qz, qw)

