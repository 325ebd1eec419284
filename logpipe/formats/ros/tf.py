"""The tf transform tree of one log: parent→child edges over time, looked up vectorised.

Fed by the bag's /tf and /tf_static messages (tf2_msgs/TFMessage, tf/tfMessage, Foxglove FrameTransform(s))
and by the ego pose as a world→ego-frame edge. Units: metres, nanoseconds; rotations as (x, y, z, w) quaternions.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from logpipe.formats.ros.messages import clean_frame, stamp_ns
from logpipe.geometry import normalize_quat, quat_conj, quat_mul, quat_rotate
from logpipe.types import NDArrayFloat, NDArrayInt


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

