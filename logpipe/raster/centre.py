"""Where a sample's raster is centred and which way it is turned (``logpipe rasterise``'s centre and heading rules).

Centre: ``centre="ego"`` uses the ego track at the sample's current step, falling back to the focal track
when the log has no ego (or the ego is not observed then), and, in logs with neither (CommonRoad scenarios), to
the sample's central target: the target nearest the median of the targets' current positions, so the raster
covers as many of them as one window can; ``centre="focal"`` always uses the focal track.
Heading (``rotate=True``): the track's ``heading`` column at the current step when present, else the
direction of its own motion over the observed steps (``heading_from_motion``), else (a stationary agent)
the direction of the nearest lane centerline within 3 m; without any of these the raster is drawn north up
and the index says ``heading_source="none"``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
import pyarrow as pa

from logpipe.dataset.windows import LogWindows
from logpipe.maps import MapStore
from logpipe.raster.rasteriser import heading_from_motion
from logpipe.raster.runs import LANE_HEADING_MAX_DIST_M, MIN_HEADING_DISP_M
from logpipe.storage.io import as_numpy
from logpipe.types import NDArrayInt


@dataclass
class Centre:
    """Where one raster is centred.

    Attributes:
        track_id: the centre track, None when none was observed at the current step.
        role: ``ego``, ``focal`` or ``target`` (the central target of a log without ego and focal).
        x, y: metres, world frame.
        heading: rad CCW from world +x, or None.
        heading_source: ``column`` | ``motion`` | ``lane`` | ``none``.
    """

    track_id: str | None
    role: str | None
    x: float
    y: float
    heading: float | None
    heading_source: str


class LogView:
    """One log's tracks for picking centres quickly: ``LogWindows``' per-track row lookups, roles and headings.

    Attributes:
        windows: the log's ``LogWindows``; ``step``, ``x``, ``y`` (metres, world frame) its per-row columns.
        role: each row's track role; ``heading``: each row's heading column (rad, NaN where null).
        ego: the log's ego track id (the smallest when several), or None.
    """

    def __init__(self, tracks: pa.Table) -> None:
        self.windows = LogWindows(tracks)
        self.step, self.x, self.y = self.windows.steps, self.windows.x, self.windows.y
        self.role = as_numpy(tracks.column("role")).astype(str)
        head = tracks.column("heading")
        self.heading = np.asarray(as_numpy(head.fill_null(float("nan"))), dtype=np.float64)
        egos = [self.windows.names[c] for c in np.unique(self.windows.codes[self.windows.ego]).tolist()]
        self.ego: str | None = min(egos) if egos else None

    def rows(self, track_id: str, first: int, last: int) -> NDArrayInt:
        """Indices of the track's rows with ``first <= step <= last``, sorted by step."""
        return self.windows.track_rows(track_id, first, last)

    def centre(self, sample: dict[str, Any], rule: str, store: MapStore | None = None) -> Centre | None:
        """The centre of one sample under ``rule`` (see module doc), or None when nobody is observed."""
        cur, start = int(sample["current_step"]), int(sample["start_step"])
        choices: list[tuple[str | None, str]] = []
        if rule == "ego" and self.ego is not None:
            choices.append((self.ego, "ego"))
        choices.append((sample.get("focal_track_id"), "focal"))
        if rule == "ego" and self.ego is None and sample.get("focal_track_id") is None:
            choices.append((self.central_target(sample), "target"))
        for track_id, role in choices:
            if track_id is None:
                continue
            rows = self.rows(str(track_id), start, cur)
            if not len(rows) or self.step[rows[-1]] != cur:
                continue  # not observed at the current step
            last = rows[-1]
            h = float(self.heading[last])
            if math.isfinite(h):
                return Centre(str(track_id), role, float(self.x[last]), float(self.y[last]), h, "column")
            xy = np.stack([self.x[rows], self.y[rows]], axis=1)
            hm = heading_from_motion(xy, MIN_HEADING_DISP_M)
            source = "motion" if hm is not None else "none"
            if hm is None and store is not None:
                # A stationary agent: take the direction of the lane it stands on (observed-time map data).
                hm = store.lane_direction_at(float(self.x[last]), float(self.y[last]), LANE_HEADING_MAX_DIST_M)
                source = "lane" if hm is not None else "none"
            return Centre(str(track_id), role, float(self.x[last]), float(self.y[last]), hm, source)
        return None

    def central_target(self, sample: dict[str, Any]) -> str | None:
        """The target observed at the current step nearest the median of all such targets' positions (the
        first in id order on a tie), or None when no target is observed then."""
        cur, start = int(sample["current_step"]), int(sample["start_step"])
        found: list[tuple[str, float, float]] = []
        for track_id in sorted(str(t) for t in sample.get("target_track_ids") or ()):
            rows = self.rows(track_id, start, cur)
            if len(rows) and self.step[rows[-1]] == cur:
                found.append((track_id, float(self.x[rows[-1]]), float(self.y[rows[-1]])))
        if not found:
            return None
        xy = np.array([(x, y) for _, x, y in found])
        return found[int(np.argmin(np.hypot(*(xy - np.median(xy, axis=0)).T)))][0]
