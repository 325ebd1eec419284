"""The agents of one log as ``foxglove.SceneUpdate`` messages (a box per agent per step), for a prediction MCAP
whose original recording has no logpipe scene of its own: a ROS bag or MCAP is copied as it was recorded, so its
agents would be drawn only where the recording itself carries markers. Built like ingest's ``/logpipe/scene``
(``logpipe.mcap.tracks``), in the log's world frame."""

from __future__ import annotations

import numpy as np
import pyarrow as pa

from logpipe.mcap import foxglove as fx
from logpipe.mcap.tracks import LogRows

AGENTS_SCENE_TOPIC = "/logpipe/scene"
"""The same topic as an ingest MCAP's agents, so a viewer layout works for both."""


def agent_scene_messages(tracks: pa.Table, frame: str) -> list[tuple[int, bytes]]:
    """(log time ns, serialized ``SceneUpdate``) per step of one log's ``tracks`` (sorted by time, canonical
    columns), its agents in ``frame``."""
    if tracks.num_rows == 0:
        return []
    rows = LogRows.of(tracks)
    tracks_local, track_index = np.unique(rows.track_codes, return_inverse=True)
    yaw, has_heading = fx.display_headings(track_index, rows.ts, rows.x, rows.y, rows.heading_values)
    agents = fx.LogAgents(steps=rows.steps, ts=rows.ts, x=rows.x, y=rows.y, yaw=yaw, has_heading=has_heading,
                          track=track_index, track_names=[rows.track_names[c] for c in tracks_local.tolist()],
                          kind=rows.kind_codes, kinds=rows.kinds)
    starts = np.concatenate([[0], np.flatnonzero(np.diff(rows.steps)) + 1])
    times = rows.ts[starts].tolist()
    return list(zip(times, fx.agent_scene_updates(agents, frame), strict=True))
