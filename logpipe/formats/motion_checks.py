"""Physically impossible motion, found at ingest for every format: a track whose position jumps faster than
anything on a road or a pavement moves, or whose recorded velocity says so.

Why at ingest: downstream, a track that teleports 1 km in one 0.4 s step scored an out-of-distribution score of
0 (the score looks at the whole window's shape, not its physics) and its forecast ended 1.4 km away. The bound
is loose on purpose, far above any real agent, so that tracker noise in real logs never trips it: the fastest
step in the real logs of ../shared/data is well under it (``tests/formats/test_motion_checks.py`` measures it).
"""

from __future__ import annotations

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc

MAX_SPEED_M_S = 150.0
"""Fastest plausible speed between two observations of one track, m/s (540 km/h): above any road vehicle,
cyclist or pedestrian; a jump that needs more is damage or a tracker swapping ids across the scene."""


def _codes(column: pa.ChunkedArray | pa.Array) -> np.ndarray:
    encoded = pc.dictionary_encode(pc.cast(column, pa.string()))
    if isinstance(encoded, pa.ChunkedArray):
        encoded = encoded.combine_chunks()
    return np.asarray(encoded.indices.to_numpy(zero_copy_only=False), dtype=np.int64)


def impossible_motion(tracks: pa.Table) -> dict[str, tuple[str, str]]:
    """(field, reason) for each log of ``tracks`` with a track moving faster than ``MAX_SPEED_M_S`` between two
    consecutive observations, or a recorded velocity (``vx``, ``vy``) above it. One sort of the batch."""
    if tracks.num_rows < 2:
        return {}
    logs = pc.cast(tracks.column("log_id"), pa.string())
    found: dict[str, tuple[str, str]] = {}
    names = tracks.column_names
    if "vx" in names and "vy" in names:
        vx = np.asarray(tracks.column("vx").to_numpy(zero_copy_only=False), dtype=np.float64)
        vy = np.asarray(tracks.column("vy").to_numpy(zero_copy_only=False), dtype=np.float64)
        fast = np.flatnonzero(np.nan_to_num(np.hypot(vx, vy)) > MAX_SPEED_M_S)
        for row in fast[:1000].tolist():
            found.setdefault(logs[row].as_py(), ("vx", f"track {tracks.column('track_id')[row].as_py()!r} has a "
                             f"velocity of {float(np.hypot(vx[row], vy[row])):.4g} m/s, over the "
                             f"{MAX_SPEED_M_S:g} m/s anything on a road or pavement reaches"))
    log_codes, track_codes = _codes(tracks.column("log_id")), _codes(tracks.column("track_id"))
    ts = np.asarray(tracks.column("timestamp_ns").to_numpy(zero_copy_only=False), dtype=np.int64)
    x = np.asarray(tracks.column("x").to_numpy(zero_copy_only=False), dtype=np.float64)
    y = np.asarray(tracks.column("y").to_numpy(zero_copy_only=False), dtype=np.float64)
    order = np.lexsort((ts, track_codes, log_codes))
    same = (log_codes[order][1:] == log_codes[order][:-1]) & (track_codes[order][1:] == track_codes[order][:-1])
    dt = np.diff(ts[order]).astype(np.float64) / 1e9
    step = np.hypot(np.diff(x[order]), np.diff(y[order]))
    with np.errstate(divide="ignore", invalid="ignore"):
        speed = np.where(same & (dt > 0), step / np.where(dt > 0, dt, 1.0), 0.0)
    for i in np.flatnonzero(np.nan_to_num(speed) > MAX_SPEED_M_S)[:1000].tolist():
        row = int(order[i + 1])
        found.setdefault(logs[row].as_py(), ("x", f"track {tracks.column('track_id')[row].as_py()!r} jumps "
                         f"{step[i]:.4g} m in {dt[i]:.4g} s at {int(ts[row])} ns ({speed[i]:.4g} m/s, over the "
                         f"{MAX_SPEED_M_S:g} m/s anything on a road or pavement reaches)"))
    return found
