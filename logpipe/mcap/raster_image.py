"""Foxglove messages of a sample's map raster (predict's MCAPs): the raster as a ``foxglove.CompressedImage``
(PNG), as a ``foxglove.Grid`` the 3D panel draws under the scene, and the ``foxglove.FrameTransform`` placing
the raster frame (see ``logpipe.mcap.foxglove`` for the files' frames).

The raster frame is the image's own frame scaled to metres: origin at the image's top-left corner, x along
columns, y down the rows, z into the ground (the camera-frame convention of ``CompressedImage``: a camera
looking straight down), so pixel ``(u, v)`` covers x in ``[u, u + 1] * res`` and y in ``[v, v + 1] * res``.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence

import numpy as np
from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage
from foxglove_schemas_protobuf.Grid_pb2 import Grid
from foxglove_schemas_protobuf.PackedElementField_pb2 import PackedElementField
from foxglove_schemas_protobuf.Pose_pb2 import Pose
from foxglove_schemas_protobuf.Quaternion_pb2 import Quaternion
from foxglove_schemas_protobuf.Vector2_pb2 import Vector2
from foxglove_schemas_protobuf.Vector3_pb2 import Vector3

from logpipe.mcap.foxglove import frame_transform, timestamp
from logpipe.mcap.protobuf_splice import serialize
from logpipe.types import NDArrayByte, NDArrayFloat

_RASTER_Z = -0.05  # the raster lies just under the ground plane the boxes stand on


def raster_rgb(raster: NDArrayByte, channels: Sequence[str]) -> NDArrayByte:
    """(C, H, W) uint8 map layers -> (H, W, 3) uint8 for viewing: red drivable area, green lanes, blue lane
    boundaries and crossings (the first three channels when the names are not these)."""
    names = list(channels)

    def layer(pick: Callable[[str], bool]) -> NDArrayByte:
        idx = [i for i, n in enumerate(names) if pick(n)]
        return raster[idx].max(axis=0) if idx else np.zeros(raster.shape[1:], np.uint8)

    if any(n in ("drivable_area", "lane_boundary") or n.startswith("lane_") for n in names):
        rgb = [layer(lambda n: n == "drivable_area"),
               layer(lambda n: n.startswith("lane_") and n != "lane_boundary"),
               layer(lambda n: n in ("lane_boundary", "crossing"))]
    else:
        rgb = [raster[i] if i < len(raster) else np.zeros(raster.shape[1:], np.uint8) for i in range(3)]
    return np.ascontiguousarray(np.stack(rgb, axis=-1).astype(np.uint8))


def raster_resolution(world_to_raster: NDArrayFloat) -> float:
    """Metres per pixel of a raster's (2, 3) world → pixel affine (a similarity: one scale for both axes)."""
    return 1.0 / math.sqrt(abs(float(np.linalg.det(np.asarray(world_to_raster, np.float64)[:, :2]))))


def raster_transform(parent: str, child: str, now_ns: int, world_to_raster: NDArrayFloat) -> bytes:
    """The serialized ``foxglove.FrameTransform`` placing raster frame ``child`` (module docstring) in ``parent``,
    the frame the affine's world coordinates are in; the raster lies ``_RASTER_Z`` m under the ground.

    The affine maps world (x, y) to pixel (u, v) with pixel centres at integers: a similarity whose image
    rows grow downwards (``logpipe.raster.rasteriser``), i.e. a reflection of world x/y, which with z into the ground is
    the rotation by pi about an axis in the ground plane.

    Raises:
        ValueError: the affine keeps orientation (rows growing upwards), which no logpipe raster does.
    """
    a = np.asarray(world_to_raster, np.float64)
    res = raster_resolution(a)
    m = a[:, :2] * res  # world → raster-frame axes, orthonormal
    if np.linalg.det(m) > 0:
        raise ValueError("raster affine keeps orientation: image rows must grow downwards (logpipe.raster.rasteriser)")
    origin = np.linalg.solve(a[:, :2], np.array([-0.5, -0.5]) - a[:, 2])  # the image's top-left corner
    # m = [[cos f, sin f], [sin f, -cos f]] mirrors about the line at f / 2: the raster's axes are world's turned
    # by pi about that line.
    half = math.atan2(m[1, 0], m[0, 0]) / 2.0
    rotation = Quaternion(x=math.cos(half), y=math.sin(half), z=0.0, w=0.0)
    return frame_transform(parent, child, now_ns, (origin[0], origin[1], _RASTER_Z), rotation)


def compressed_raster(frame: str, now_ns: int, rgb: NDArrayByte) -> bytes:
    """A serialized ``foxglove.CompressedImage``: ``rgb`` (H, W, 3) as PNG in ``frame``."""
    import cv2  # here: ingest, which writes no image, does not pay for loading OpenCV

    ok, png = cv2.imencode(".png", np.ascontiguousarray(rgb[..., ::-1]))  # OpenCV writes BGR
    if not ok:
        raise ValueError("PNG encoding of the raster failed")
    return serialize(CompressedImage(timestamp=timestamp(now_ns), frame_id=frame, data=png.tobytes(), format="png"))


_GRID_FIELDS = [PackedElementField(name=name, offset=i, type=PackedElementField.UINT8)
                for i, name in enumerate(("red", "green", "blue", "alpha"))]


def raster_grid(frame: str, now_ns: int, rgb: NDArrayByte, resolution_m: float) -> bytes:
    """A serialized ``foxglove.Grid`` of ``rgb`` (H, W, 3) in raster frame ``frame``, cells ``resolution_m``
    wide, facing up: empty cells dim (alpha 64), drawn ones opaque.

    The raster frame's z points into the ground and the 3D panel draws a grid on its +z side, so the grid is
    turned by pi about x (its y runs up the image from the bottom row) and its rows are stored bottom first.
    """
    h, w, _ = rgb.shape
    rgba = np.empty((h, w, 4), np.uint8)
    bottom_first = rgba[::-1]
    bottom_first[..., :3] = rgb
    # OR of the three channels: numpy's any() over a length-3 axis is ~4x slower here (one Grid per sample).
    drawn = (rgb[..., 0] | rgb[..., 1] | rgb[..., 2]) != 0
    bottom_first[..., 3] = np.where(drawn, np.uint8(255), np.uint8(64))
    return serialize(Grid(
        timestamp=timestamp(now_ns), frame_id=frame,
        pose=Pose(position=Vector3(y=h * resolution_m), orientation=Quaternion(x=1.0)),
        column_count=w, cell_size=Vector2(x=resolution_m, y=resolution_m), row_stride=w * 4, cell_stride=4,
        fields=_GRID_FIELDS, data=rgba.tobytes()))
