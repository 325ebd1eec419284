"""ROS message → track observations, shared by the rosbag and MCAP adapters.

Decoded messages are read by attribute (rosbags, mcap-ros1/ros2 and namespaced JSON objects all look alike),
collected as observations in the frame the message gives, and transformed to the world frame at the end with
a small vectorised tf buffer (the bag's /tf and /tf_static, plus the ego pose as a world→ego-frame edge).

Frames: the world frame is the log's fixed frame (``map``/``odom``/``world``); an observation's own frame is
its header ``frame_id``. Units: metres, radians (CCW from +x), m/s, nanoseconds.
"""

from __future__ import annotations

import math
import re
from collections import defaultdict
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pyarrow as pa

from logpipe.contracts import conform, tracks_schema
from logpipe.formats.mapping import AgentSpec, EgoSpec, Mapping
from logpipe.resample import ResampleSpec, resample_track
from logpipe.types import NDArrayFloat, NDArrayInt

# --- message kinds -----------------------------------------------------------------------------------

POSE_KINDS: dict[str, str] = {
    "nav_msgs/msg/Odometry": "odometry",
    "geometry_msgs/msg/PoseStamped": "pose",
    "geometry_msgs/msg/PoseWithCovarianceStamped": "pose_cov",
    "turtlesim/msg/Pose": "turtlesim",
    # Foxglove's well-known schemas (JSON or protobuf channels of non-ROS MCAP files)
    "foxglove.PoseInFrame": "foxglove_pose",
    "foxglove_msgs/msg/PoseInFrame": "foxglove_pose",
}
"""Single-agent pose types (one topic = one track)."""

EGO_KINDS = ("odometry", "pose", "pose_cov", "foxglove_pose")
"""Pose kinds that can be the ego (turtlesim has no header, so no frame or stamp to tie an ego to)."""

OBJECT_KINDS: dict[str, str] = {
    "visualization_msgs/msg/MarkerArray": "markers",
    "derived_object_msgs/msg/ObjectArray": "derived_objects",
    "autoware_perception_msgs/msg/TrackedObjects": "autoware_tracked",
    "autoware_auto_perception_msgs/msg/TrackedObjects": "autoware_tracked",
    "vision_msgs/msg/Detection3DArray": "detection3d",
}
"""Object-array types (one topic = one track per object id)."""

TF_TYPES = frozenset(
    {
        "tf2_msgs/msg/TFMessage",
        "tf/msg/tfMessage",
        "foxglove.FrameTransform",
        "foxglove.FrameTransforms",
        "foxglove_msgs/msg/FrameTransform",
        "foxglove_msgs/msg/FrameTransforms",
    }
)


def normalize_type(name: str) -> str:
    """``pkg/msg/Type`` for ``pkg/Type`` (ROS1 / MCAP ros1msg spelling); other names unchanged."""
    parts = name.split("/")
    if len(parts) == 2:
        return f"{parts[0]}/msg/{parts[1]}"
    return name


def topic_kind(msgtype: str) -> str | None:
    """``odometry``/``pose``/``pose_cov``/``turtlesim``/object kinds/``tf`` for a supported type, else None."""
    t = normalize_type(msgtype)
    if t in TF_TYPES:
        return "tf"
    return POSE_KINDS.get(t) or OBJECT_KINDS.get(t)


def unsupported_reason(msgtype: str) -> str:
    """Why a topic of ``msgtype`` gives no tracks, in words."""
    if "/srv/" in msgtype:
        return f"service-event type {msgtype!r} (a request/response record, not a track)"
    if len(msgtype.split("/")) == 2 and msgtype.split("/", maxsplit=1)[0].endswith("_msgs"):
        return f"type name {msgtype!r} has no '/msg/' (non-canonical ROS 2 name) and is not a track type"
    return f"type {msgtype!r} is not a pose, odometry, tf or object-array type"


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
        pose = _Pose(msg.x, msg.y, 0.0, 0.0, 0.0, math.sin(half), math.cos(half))
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


class _Pose:
    """A geometry_msgs/Pose look-alike for sources without one (turtlesim)."""

    __slots__ = ("orientation", "position")

    def __init__(self, x: float, y: float, z: float, qx: float, qy: float, qz: float, qw: float) -> None:
        self.position = _Vec(x, y, z)
        self.orientation = _Quat(qx, qy, qz, qw)


# --- quaternion algebra (x, y, z, w), vectorised over rows ---------------------------------------------


def quat_mul(a: NDArrayFloat, b: NDArrayFloat) -> NDArrayFloat:
    """Hamilton product a*b of (N, 4) quaternions (x, y, z, w)."""
    ax, ay, az, aw = a[:, 0], a[:, 1], a[:, 2], a[:, 3]
    bx, by, bz, bw = b[:, 0], b[:, 1], b[:, 2], b[:, 3]
    return np.stack(
        [
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
            aw * bw - ax * bx - ay * by - az * bz,
        ],
        axis=1,
    )


def quat_conj(q: NDArrayFloat) -> NDArrayFloat:
    """Inverse of unit quaternions."""
    out: NDArrayFloat = q * np.array([-1.0, -1.0, -1.0, 1.0])
    return out


def quat_rotate(q: NDArrayFloat, v: NDArrayFloat) -> NDArrayFloat:
    """Rotate (N, 3) vectors by (N, 4) unit quaternions."""
    u = q[:, :3]
    w = q[:, 3:4]
    t = 2.0 * np.cross(u, v)
    out: NDArrayFloat = v + w * t + np.cross(u, t)
    return out


def quat_yaw(q: NDArrayFloat) -> NDArrayFloat:
    """Yaw (rad, CCW about +z) of (N, 4) quaternions."""
    x, y, z, w = q[:, 0], q[:, 1], q[:, 2], q[:, 3]
    out: NDArrayFloat = np.arctan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))
    return out


def normalize_quat(q: NDArrayFloat) -> NDArrayFloat:
    """Unit quaternions; an all-zero quaternion (unset orientation) becomes identity."""
    n = np.linalg.norm(q, axis=1, keepdims=True)
    zero = n[:, 0] < 1e-12
    out: NDArrayFloat = np.where(n > 1e-12, q / np.where(n > 1e-12, n, 1.0), 0.0)
    out[zero, 3] = 1.0
    return out


# --- tf buffer ---------------------------------------------------------------------------------------


@dataclass
class _Edge:
    parent: str
    static: bool
    t: list[int] = field(default_factory=list)
    trans: list[tuple[float, float, float]] = field(default_factory=list)
    rot: list[tuple[float, float, float, float]] = field(default_factory=list)
    arrays: tuple[NDArrayInt, NDArrayFloat, NDArrayFloat] | None = None


class TfBuffer:
    """Transforms parent→child over time, read from tf messages (and the ego pose), looked up vectorised.

    Lookups interpolate linearly between the two nearest stamps (translation lerp, rotation nlerp) and hold the
    end values up to ``tolerance_ns`` beyond the first/last stamp; further out they are NaN (no extrapolation).
    """

    def __init__(self, tolerance_ns: int = 200_000_000) -> None:
        self.edges: dict[str, _Edge] = {}
        self.tolerance_ns = tolerance_ns
        self.messages = 0

    def add_message(self, msg: Any, static: bool) -> None:
        """Add the transforms of a tf2_msgs/TFMessage (or tf/tfMessage, foxglove FrameTransform(s))."""
        self.messages += 1
        transforms = getattr(msg, "transforms", None)
        for tr in transforms if transforms is not None else [msg]:
            if hasattr(tr, "parent_frame_id"):  # foxglove.FrameTransform
                tt, r = tr.translation, tr.rotation
                self.add(
                    clean_frame(tr.parent_frame_id), clean_frame(tr.child_frame_id), stamp_ns(tr.timestamp),
                    (tt.x, tt.y, tt.z), (r.x, r.y, r.z, r.w), static,
                )  # fmt: skip
                continue
            tt, r = tr.transform.translation, tr.transform.rotation
            self.add(
                clean_frame(tr.header.frame_id), clean_frame(tr.child_frame_id), stamp_ns(tr.header.stamp),
                (tt.x, tt.y, tt.z), (r.x, r.y, r.z, r.w), static,
            )  # fmt: skip

    def add(
        self,
        parent: str,
        child: str,
        t: int,
        trans: tuple[float, float, float],
        rot: tuple[float, float, float, float],
        static: bool,
    ) -> None:
        """Add one parent→child transform (a child keeps the first parent it was given)."""
        edge = self.edges.get(child)
        if edge is None:
            edge = self.edges[child] = _Edge(parent=parent, static=static)
        elif edge.parent != parent:
            return  # tf is a tree: a second parent for the same child is a publisher conflict; keep the first
        edge.static = edge.static and static
        edge.t.append(t)
        edge.trans.append(trans)
        edge.rot.append(rot)
        edge.arrays = None

    def add_track(self, parent: str, child: str, t: NDArrayInt, pos: NDArrayFloat, quat: NDArrayFloat) -> bool:
        """Add a dynamic parent→child edge from a pose track (the ego); False if ``child`` is already in tf."""
        if child in self.edges or not len(t):
            return False
        edge = self.edges[child] = _Edge(parent=parent, static=False)
        edge.arrays = self._sorted(t, pos, quat)
        return True

    @staticmethod
    def _sorted(t: NDArrayInt, pos: NDArrayFloat, quat: NDArrayFloat) -> tuple[NDArrayInt, NDArrayFloat, NDArrayFloat]:
        order = np.argsort(t, kind="stable")
        t, pos, quat = t[order], pos[order], normalize_quat(quat[order])
        keep = np.ones(len(t), dtype=bool)
        keep[1:] = t[1:] != t[:-1]
        return t[keep], pos[keep], quat[keep]

    def _arrays(self, edge: _Edge) -> tuple[NDArrayInt, NDArrayFloat, NDArrayFloat]:
        if edge.arrays is None:
            edge.arrays = self._sorted(
                np.asarray(edge.t, dtype=np.int64),
                np.asarray(edge.trans, dtype=np.float64).reshape(-1, 3),
                np.asarray(edge.rot, dtype=np.float64).reshape(-1, 4),
            )
        return edge.arrays

    def frames(self) -> set[str]:
        """Every frame named in the buffer."""
        return set(self.edges) | {e.parent for e in self.edges.values()}

    def chain(self, frame: str) -> list[str]:
        """``frame`` and its ancestors up to the root."""
        out = [frame]
        while out[-1] in self.edges and len(out) < 64:
            out.append(self.edges[out[-1]].parent)
        return out

    def root(self, frame: str) -> str:
        """The root of ``frame``'s tree."""
        return self.chain(frame)[-1]

    def can_transform(self, target: str, source: str) -> bool:
        """Whether ``source`` and ``target`` are in the same tree."""
        return target == source or self.root(target) == self.root(source)

    def dynamic_edges(self) -> list[tuple[str, str]]:
        """(parent, child) pairs that change over time."""
        return sorted((e.parent, c) for c, e in self.edges.items() if not e.static)

    def edge_times(self, child: str) -> NDArrayInt:
        """Stamps of the edge into ``child``."""
        return self._arrays(self.edges[child])[0]

    def _edge_at(self, child: str, times: NDArrayInt) -> tuple[NDArrayFloat, NDArrayFloat]:
        t, pos, quat = self._arrays(self.edges[child])
        n = len(times)
        if len(t) == 1 or self.edges[child].static:
            return np.repeat(pos[-1:], n, axis=0), np.repeat(quat[-1:], n, axis=0)
        i = np.clip(np.searchsorted(t, times, side="right") - 1, 0, len(t) - 2)
        t0, t1 = t[i], t[i + 1]
        w = np.clip((times - t0) / np.maximum(t1 - t0, 1), 0.0, 1.0)[:, None]
        p = pos[i] * (1 - w) + pos[i + 1] * w
        q0, q1 = quat[i], quat[i + 1]
        q1 = np.where(np.sum(q0 * q1, axis=1, keepdims=True) < 0, -q1, q1)
        q = normalize_quat(q0 * (1 - w) + q1 * w)
        outside = (times < t[0] - self.tolerance_ns) | (times > t[-1] + self.tolerance_ns)
        p[outside] = np.nan
        q[outside] = np.nan
        return p, q

    def _to_root(self, frame: str, times: NDArrayInt) -> tuple[NDArrayFloat, NDArrayFloat]:
        n = len(times)
        p = np.zeros((n, 3))
        q = np.tile(np.array([0.0, 0.0, 0.0, 1.0]), (n, 1))
        for child in self.chain(frame)[:-1]:
            ep, eq = self._edge_at(child, times)
            # T_parent_child ∘ T_child_frame
            p = quat_rotate(eq, p) + ep
            q = quat_mul(eq, q)
        return p, q

    def lookup(self, target: str, source: str, times: NDArrayInt) -> tuple[NDArrayFloat, NDArrayFloat]:
        """Translation (N, 3) and rotation (N, 4) of ``source`` in ``target`` at ``times`` (NaN where unknown)."""
        ps, qs = self._to_root(source, times)
        if target == self.root(source):
            return ps, qs
        pt, qt = self._to_root(target, times)
        qti = quat_conj(qt)
        return quat_rotate(qti, ps - pt), quat_mul(qti, qs)


# --- world-frame assembly ------------------------------------------------------------------------------


@dataclass
class WorldTracks:
    """Observations of every source in the world frame, as flat arrays (one row per observation).

    Attributes:
        t: ns; x, y: m (world); heading: rad (world); vx, vy: m/s (world, NaN unknown); length, width: m.
        track, role, object_type, source_type: per-row identity.
        dropped: rows dropped per topic because their frame could not be placed in the world frame then.
    """

    t: NDArrayInt
    x: NDArrayFloat
    y: NDArrayFloat
    heading: NDArrayFloat
    vx: NDArrayFloat
    vy: NDArrayFloat
    length: NDArrayFloat
    width: NDArrayFloat
    track: list[str]
    role: list[str]
    object_type: list[str]
    source_type: list[str]
    dropped: dict[str, int]


class FrameError(ValueError):
    """A topic's frame cannot be placed in the world frame."""

    def __init__(self, topic: str, reason: str) -> None:
        self.topic = topic
        self.reason = reason
        super().__init__(reason)


def world_frame_for(mapping: Mapping, extractors: Sequence[TopicExtractor], tf: TfBuffer) -> str:
    """The world frame: the mapping's, else the ego's frame (tf parent / header frame), else the objects' root."""
    if mapping.world_frame:
        return clean_frame(mapping.world_frame)
    if mapping.ego is not None and mapping.ego.tf is not None:
        return clean_frame(mapping.ego.tf[0])
    for ex in extractors:
        if ex.role == "ego" and len(ex.obs):
            return ex.obs.frames[0]
    for ex in extractors:
        if len(ex.obs) and ex.obs.frames[0]:
            return tf.root(ex.obs.frames[0]) if ex.obs.frames[0] in tf.frames() else ex.obs.frames[0]
    return ""


def ego_from_tf(spec: EgoSpec, tf: TfBuffer, source_type: str) -> TopicExtractor:
    """An ego extractor filled from the tf pair ``spec.tf`` (sampled at the stamps of its moving edges)."""
    assert spec.tf is not None
    parent, child = (clean_frame(f) for f in spec.tf)
    if child not in tf.edges or not tf.can_transform(parent, child):
        known = ", ".join(f"{p}->{c}" for p, c in tf.dynamic_edges()) or "none"
        raise FrameError("/tf", f"no tf path from {parent!r} to {child!r} (moving edges: {known})")
    chain = tf.chain(child)
    moving = [c for c in chain[: chain.index(parent)] if not tf.edges[c].static] if parent in chain else []
    moving = moving or [c for c in chain[:-1] if not tf.edges[c].static]
    times = tf.edge_times(moving[0]) if moving else tf.edge_times(child)
    p, q = tf.lookup(parent, child, times)
    ex = TopicExtractor("/tf", source_type, "ego", spec, True, kind="tf_ego")
    ex.child_frames = {child}
    ex.messages = len(times)
    ok = np.isfinite(p[:, 0])
    for ti, pi, qi in zip(times[ok].tolist(), p[ok].tolist(), q[ok].tolist(), strict=True):
        pose = _Pose(pi[0], pi[1], pi[2], qi[0], qi[1], qi[2], qi[3])
        ex.obs.add(ti, spec.track_id, parent, pose, NAN3, NAN2, spec.object_type, source_type)
    return ex


def to_world(extractors: Sequence[TopicExtractor], tf: TfBuffer, world: str, ego_frame: str | None) -> WorldTracks:
    """Every extractor's observations in ``world`` (frame ``""`` counts as the world frame).

    The ego track (if any) is added to ``tf`` as the edge ``world → ego_frame`` first, so that objects given in
    the vehicle frame are placed with the ego pose at their own timestamps.

    Raises:
        FrameError: a topic's frame has no path to the world frame.
    """
    ego = next((ex for ex in extractors if ex.role == "ego" and len(ex.obs)), None)
    if ego is not None and ego_frame and ego.obs.frames[0] in ("", world):
        tf.add_track(
            world, ego_frame, np.asarray(ego.obs.t, dtype=np.int64),
            np.asarray(ego.obs.pos, dtype=np.float64), np.asarray(ego.obs.quat, dtype=np.float64),
        )  # fmt: skip
    cols: dict[str, list[Any]] = defaultdict(list)
    dropped: dict[str, int] = {}
    for ex in extractors:
        o = ex.obs
        n = len(o)
        if not n:
            continue
        t = np.asarray(o.t, dtype=np.int64)
        pos = np.asarray(o.pos, dtype=np.float64)
        quat = normalize_quat(np.asarray(o.quat, dtype=np.float64))
        vel = np.asarray(o.vel, dtype=np.float64)
        frames = np.asarray(o.frames, dtype=object)
        ok = np.ones(n, dtype=bool)
        for frame in set(o.frames):
            if frame in ("", world):
                continue
            if not tf.can_transform(world, frame):
                raise FrameError(
                    ex.topic,
                    f"frame {frame!r} cannot be placed in the world frame {world!r}: no tf path"
                    + (f" and it is not the ego frame {ego_frame!r}" if ego_frame else "")
                    + " (set world_frame or ego in the mapping)",
                )
            rows = np.flatnonzero(frames == frame)
            tp, tq = tf.lookup(world, frame, t[rows])
            pos[rows] = quat_rotate(tq, pos[rows]) + tp
            if not o.v_body:
                vel[rows] = quat_rotate(tq, vel[rows])
            quat[rows] = quat_mul(tq, quat[rows])
            ok[rows] &= np.isfinite(tp[:, 0])
        if o.v_body:
            vel = quat_rotate(quat, vel)
        if not ok.all():
            dropped[ex.topic] = dropped.get(ex.topic, 0) + int((~ok).sum())
        idx = np.flatnonzero(ok)
        sizes = np.asarray(o.size, dtype=np.float64)[idx]
        cols["t"].append(t[idx])
        cols["x"].append(pos[idx, 0])
        cols["y"].append(pos[idx, 1])
        cols["heading"].append(quat_yaw(quat[idx]))
        cols["vx"].append(vel[idx, 0])
        cols["vy"].append(vel[idx, 1])
        cols["length"].append(sizes[:, 0])
        cols["width"].append(sizes[:, 1])
        sel = idx.tolist()
        cols["track"].extend(o.track[i] for i in sel)
        cols["role"].extend([ex.role] * len(sel))
        cols["object_type"].extend(o.object_type[i] for i in sel)
        cols["source_type"].extend(o.source_type[i] for i in sel)

    def cat(name: str, dtype: type) -> Any:
        return np.concatenate(cols[name]).astype(dtype) if cols[name] else np.zeros(0, dtype=dtype)

    return WorldTracks(
        t=cat("t", np.int64), x=cat("x", np.float64), y=cat("y", np.float64),
        heading=cat("heading", np.float64), vx=cat("vx", np.float64), vy=cat("vy", np.float64),
        length=cat("length", np.float64), width=cat("width", np.float64),
        track=list(cols["track"]), role=list(cols["role"]), object_type=list(cols["object_type"]),
        source_type=list(cols["source_type"]), dropped=dropped,
    )  # fmt: skip


# --- automatic mapping ---------------------------------------------------------------------------------


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


# --- track table ---------------------------------------------------------------------------------------


def world_to_table(log_id: str, wt: WorldTracks, spec: ResampleSpec | None) -> pa.Table:
    """Rows of the canonical track table (without ``step``) for one log, resampled per track when ``spec``."""
    n = len(wt.t)
    if spec is None or n == 0:
        table = pa.table(
            {
                "log_id": pa.array([log_id] * n, pa.string()),
                "timestamp_ns": wt.t, "track_id": wt.track, "object_type": wt.object_type, "role": wt.role,
                "x": wt.x, "y": wt.y, "heading": _nulls(wt.heading), "vx": _nulls(wt.vx), "vy": _nulls(wt.vy),
                "length": _nulls(wt.length), "width": _nulls(wt.width), "source_type": wt.source_type,
            }
        )  # fmt: skip
        return conform_tracks(table)
    track = np.asarray(wt.track, dtype=object)
    order = np.argsort(track, kind="stable")
    bounds = np.flatnonzero(track[order][1:] != track[order][:-1]) + 1
    parts: dict[str, list[Any]] = defaultdict(list)
    for rows in np.split(order, bounds):
        values = {
            "x": wt.x[rows], "y": wt.y[rows], "heading": wt.heading[rows], "vx": wt.vx[rows],
            "vy": wt.vy[rows], "length": wt.length[rows], "width": wt.width[rows],
        }  # fmt: skip
        grid, res = resample_track(wt.t[rows], values, spec)
        if not len(grid):
            continue
        # class/role/source type of the nearest source sample at or before each grid time
        src_t = np.sort(wt.t[rows], kind="stable")
        src_rows = rows[np.argsort(wt.t[rows], kind="stable")]
        at = src_rows[np.clip(np.searchsorted(src_t, grid, side="right") - 1, 0, len(rows) - 1)]
        parts["timestamp_ns"].append(grid)
        for k, v in res.items():
            parts[k].append(v)
        for k, src in (("track_id", wt.track), ("role", wt.role), ("object_type", wt.object_type),
                       ("source_type", wt.source_type)):  # fmt: skip
            parts[k].extend(src[i] for i in at.tolist())
    if not parts:
        return world_to_table(log_id, _empty_world(), None)
    total = sum(len(g) for g in parts["timestamp_ns"])
    table = pa.table(
        {
            "log_id": pa.array([log_id] * total, pa.string()),
            "timestamp_ns": np.concatenate(parts["timestamp_ns"]),
            "track_id": parts["track_id"], "object_type": parts["object_type"], "role": parts["role"],
            **{k: _nulls(np.concatenate(parts[k])) for k in ("x", "y", "heading", "vx", "vy", "length", "width")},
            "source_type": parts["source_type"],
        }
    )  # fmt: skip
    return conform_tracks(table)


def _nulls(v: NDArrayFloat) -> pa.Array:
    """Float column with NaN as null."""
    return pa.array(v, type=pa.float64(), from_pandas=True)


def _empty_world() -> WorldTracks:
    z = np.zeros(0)
    return WorldTracks(np.zeros(0, dtype=np.int64), z, z, z, z, z, z, z, [], [], [], [], {})


def adapter_schema() -> pa.Schema:
    """The canonical track schema without ``step`` (the ingest stage computes it)."""
    schema = tracks_schema()
    return pa.schema([f for f in schema if f.name != "step"], metadata=schema.metadata)


def conform_tracks(table: pa.Table) -> pa.Table:
    """``table`` cast to ``adapter_schema()``."""
    return conform(table, adapter_schema())


def empty_tracks() -> pa.Table:
    """A table with no rows in ``adapter_schema()``."""
    return adapter_schema().empty_table()
