"""Rotation maths on unit quaternions (x, y, z, w), vectorised over rows: composing, inverting, rotating
vectors and reading the yaw. Shared by the ROS transform tree and the Argoverse 2 city-frame poses.

Frames: a quaternion ``q`` of frame B in frame A rotates vectors given in B into A. Angles in radians.
"""

from __future__ import annotations

import numpy as np

from logpipe.types import NDArrayFloat


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

