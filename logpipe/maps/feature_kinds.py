"""What a map feature is: the kinds every map adapter produces, polylines versus polygons."""

from __future__ import annotations

from enum import StrEnum


class FeatureKind(StrEnum):
    """What a map feature is; polylines (centerlines, boundaries) versus polygons (areas)."""

    LANE_CENTERLINE = "lane_centerline"
    LANE_BOUNDARY = "lane_boundary"
    DRIVABLE_AREA = "drivable_area"
    CROSSING = "crossing"


KINDS: tuple[FeatureKind, ...] = tuple(FeatureKind)
POLYGON_KINDS: frozenset[FeatureKind] = frozenset({FeatureKind.DRIVABLE_AREA, FeatureKind.CROSSING})
