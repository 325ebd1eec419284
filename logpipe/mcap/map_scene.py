"""A log's lane map as one Foxglove ``SceneUpdate``, drawn under the agents of an ingest MCAP (``/logpipe/map``).

One message at the log's first time holds one entity per feature kind (ids ``lanes/boundaries``,
``lanes/centerlines``, ``lanes/crossings``), each a set of line strips in the log's world frame: lane boundaries in
light grey (painted ones by their marking: solid lines thicker), lane centerlines thin and dim blue, crossings
as closed yellow outlines. Entities live forever (lifetime 0), and Foxglove shows a topic's latest message after
a seek, so the road stays drawn wherever the user jumps. Built once per log with the Protobuf classes (a few
hundred lines per scenario; no per-step work).
"""

from __future__ import annotations

from foxglove_schemas_protobuf.Color_pb2 import Color
from foxglove_schemas_protobuf.KeyValuePair_pb2 import KeyValuePair
from foxglove_schemas_protobuf.LinePrimitive_pb2 import LinePrimitive
from foxglove_schemas_protobuf.Point3_pb2 import Point3
from foxglove_schemas_protobuf.Pose_pb2 import Pose
from foxglove_schemas_protobuf.Quaternion_pb2 import Quaternion
from foxglove_schemas_protobuf.SceneEntity_pb2 import SceneEntity
from foxglove_schemas_protobuf.SceneUpdate_pb2 import SceneUpdate
from foxglove_schemas_protobuf.Vector3_pb2 import Vector3

from logpipe.maps import FeatureKind, MapStore
from logpipe.mcap.foxglove import POSITION_QUANTUM, snap, timestamp

MAP_TOPIC = "/logpipe/map"
BOUNDARY_RGBA = (0.85, 0.85, 0.85, 0.9)
"""Lane boundaries: light grey (RGBA 0..1)."""
CENTERLINE_RGBA = (0.35, 0.45, 0.75, 0.6)
"""Lane centerlines: dim blue, thinner than the boundaries."""
CROSSING_RGBA = (0.95, 0.8, 0.2, 0.9)
"""Crossings (crosswalks): yellow outlines."""
_MAP_Z = -0.05  # metres: just below the agents' boxes and the forecast lines (z >= 0)
_STYLE: dict[FeatureKind, tuple[str, tuple[float, float, float, float], float]] = {
    FeatureKind.LANE_BOUNDARY: ("lanes/boundaries", BOUNDARY_RGBA, 0.12),
    FeatureKind.LANE_CENTERLINE: ("lanes/centerlines", CENTERLINE_RGBA, 0.06),
    FeatureKind.CROSSING: ("lanes/crossings", CROSSING_RGBA, 0.15),
}


def map_scene_update(store: MapStore, frame: str, t_ns: int) -> bytes:
    """The serialized ``SceneUpdate`` of ``store``'s boundaries, centerlines and crossings in ``frame`` at
    ``t_ns`` (metres, snapped to ``POSITION_QUANTUM``); entities of kinds the map lacks are left out."""
    pose = Pose(position=Vector3(z=_MAP_Z), orientation=Quaternion(w=1.0))
    entities = []
    for kind, (entity_id, colour, thickness) in _STYLE.items():
        lines = []
        for row in store.rows(kind).tolist():
            points = snap(store.geometry(row), POSITION_QUANTUM)
            line_type = LinePrimitive.LINE_LOOP if kind == FeatureKind.CROSSING else LinePrimitive.LINE_STRIP
            width = thickness * (1.5 if kind == FeatureKind.LANE_BOUNDARY and _is_solid(store, row) else 1.0)
            lines.append(LinePrimitive(type=line_type, pose=pose, thickness=width, scale_invariant=False,
                                       points=[Point3(x=x, y=y) for x, y in points.tolist()],
                                       color=Color(r=colour[0], g=colour[1], b=colour[2], a=colour[3])))
        if lines:
            entities.append(SceneEntity(timestamp=timestamp(t_ns), frame_id=frame, id=entity_id, lines=lines,
                                        metadata=[KeyValuePair(key="map_id", value=store.map_id),
                                                  KeyValuePair(key="kind", value=str(kind))]))
    return bytes(SceneUpdate(entities=entities).SerializeToString())


def _is_solid(store: MapStore, row: int) -> bool:
    mark = store.table.column("mark_type")[row].as_py()
    return bool(mark) and "solid" in str(mark)
