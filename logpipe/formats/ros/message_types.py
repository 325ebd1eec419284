"""The ROS (and Foxglove) message types logpipe turns into tracks, by kind, with their spelling normalised.

A kind says how a topic is read: a one-agent pose (``POSE_KINDS``), an array of objects with ids
(``OBJECT_KINDS``), or transforms (``TF_TYPES``). Type names are ``pkg/msg/Type``; the ROS 1 / MCAP ros1msg
spelling ``pkg/Type`` is normalised to it.
"""

from __future__ import annotations

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

