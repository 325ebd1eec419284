"""What each channel of ingest's MCAP costs (issue 66): on the real Argoverse 1 logs, per channel its messages, its
bytes (raw, and compressed alone at the stages' zstd level), the CPU of building its messages for every log of the
batch at once (as ``logpipe.mcap.tracks`` does) and the CPU of writing only that channel's messages per log
(``logpipe.mcap.bulk``: headers, join, zstd, file). Interleaved rounds, median CPU seconds per 1,000 logs; the
table's columns are converted once for all channels (``columns`` row)."""

from __future__ import annotations

import itertools
import statistics
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

REPO = Path(__file__).resolve().parents[1]
SOURCE = REPO.parent / "shared" / "data" / "argoverse1" / "data"
FALLBACK = REPO / "tests" / "data" / "argoverse1"


def _channels(table: Any) -> dict[str, Callable[[], tuple[list[Any], list[Any]]]]:
    """Channel name -> build its messages for the batch: (per log, its Pieces or list of bytes; per log, times)."""
    from logpipe.dataset.shards import log_runs
    from logpipe.mcap import foxglove as fx
    from logpipe.mcap import tracks
    from logpipe.storage.io import as_numpy

    rows = tracks.LogRows.of(table)
    codes = as_numpy(table.column("log_id").dictionary_encode().combine_chunks().indices)
    starts, ends = log_runs(codes)
    runs = [(str(i), lo, hi) for i, (lo, hi) in enumerate(zip(starts.tolist(), ends.tolist(), strict=True))]
    n = len(rows)
    log_of_row = np.repeat(np.arange(len(runs)), ends - starts)
    new_step = np.ones(n, bool)
    new_step[1:] = (np.diff(rows.steps) != 0) | (np.diff(log_of_row) != 0)
    step_rows = np.flatnonzero(new_step)
    log_steps = np.searchsorted(step_rows, [*starts.tolist(), n])
    step_ts = rows.ts[step_rows]
    ego = np.flatnonzero(rows.ego)
    log_ego = np.searchsorted(ego, [*starts.tolist(), n])

    def per_log(messages: Any, bounds: Any, times: Any) -> tuple[list[Any], list[Any]]:
        pairs = list(itertools.pairwise(bounds.tolist()))
        if hasattr(messages, "part"):
            return [messages.part(a, b) for a, b in pairs], [times[a:b] for a, b in pairs]
        return [messages[a:b] for a, b in pairs], [times[a:b] for a, b in pairs]

    def agents() -> tuple[list[Any], list[Any]]:
        return per_log(tracks._agent_json(rows, step_rows, [r[0] for r in runs], log_of_row), log_steps, step_ts)

    def headings() -> tuple[Any, Any, Any, Any]:
        width = max(len(rows.track_names), 1)
        local, index = np.unique(log_of_row * width + rows.track_codes, return_inverse=True)
        yaw, has = fx.display_headings(index, rows.ts, rows.x, rows.y, rows.heading_values)
        return local, index, yaw, has

    def scene() -> tuple[list[Any], list[Any]]:
        local, index, yaw, has = headings()
        width = max(len(rows.track_names), 1)
        drawn = fx.LogAgents(steps=np.cumsum(new_step) - 1, ts=rows.ts, x=rows.x, y=rows.y, yaw=yaw, has_heading=has,
                             track=index, track_names=[rows.track_names[c % width] for c in local.tolist()],
                             kind=rows.kind_codes, kinds=rows.kinds)
        return per_log(fx.agent_scene_pieces(drawn, tracks.WORLD_FRAME, log_steps[:-1]), log_steps, step_ts)

    def ego_channel(build: Callable[..., list[bytes]]) -> Callable[[], tuple[list[Any], list[Any]]]:
        def run() -> tuple[list[Any], list[Any]]:
            _, _, yaw, has = headings()
            heading = np.where(has[ego], yaw[ego], np.nan)
            return per_log(build(rows.ts[ego], rows.x[ego], rows.y[ego], heading), log_ego, rows.ts[ego])
        return run

    def root() -> tuple[list[Any], list[Any]]:
        messages = []
        for _, lo, hi in runs:
            cx, cy = fx.log_centre(rows.x[lo:hi], rows.y[lo:hi])
            messages.append([fx.frame_transform(tracks.LOG_FRAME, tracks.WORLD_FRAME, int(rows.ts[lo]),
                                                (-cx, -cy, 0.0))])
        return messages, [rows.ts[lo : lo + 1] for _, lo, _ in runs]

    return {"/logpipe/agents (logpipe.AgentStates JSON)": agents, "/logpipe/scene (foxglove.SceneUpdate)": scene,
            "/logpipe/ego_pose (foxglove.PoseInFrame)": ego_channel(
                lambda t, x, y, h: fx.poses_in_frame(tracks.WORLD_FRAME, t, x, y, h)),
            "/logpipe/tf world->ego (foxglove.FrameTransform)": ego_channel(
                lambda t, x, y, h: fx.frame_transforms(tracks.WORLD_FRAME, tracks.EGO_FRAME, t, x, y, h)),
            "/logpipe/tf log_centre->world (foxglove.FrameTransform)": root}


def _write(folder: Path, topic: str, logs: tuple[list[Any], list[Any]]) -> int:
    """Each log's messages of one channel as a file of their own; the bytes written."""
    from logpipe.mcap.bulk import BulkMcap

    total = 0
    for i, (messages, times) in enumerate(zip(*logs, strict=True)):
        writer = BulkMcap()
        writer.log(writer.channel(topic.split(maxsplit=1)[0], "protobuf", None), times, messages)
        total += writer.write(folder / f"{i}.mcap")[0]
    return total


def run(quick: bool = False) -> dict[str, Any]:
    """Measure and return the figures (JSON-able)."""
    import pyarrow.parquet as pq

    from logpipe.mcap.bulk import Pieces
    from logpipe.mcap.tracks import LogRows
    from logpipe.stages.ingest import IngestOptions, ingest

    rounds = 3 if quick else 5
    source = SOURCE if SOURCE.is_dir() else FALLBACK
    with tempfile.TemporaryDirectory(prefix="logpipe-mcap-channels-") as tmp:
        ingest([source], IngestOptions(out=Path(tmp) / "ds", write_mcap=False, workers=1))
        table = pq.read_table(sorted((Path(tmp) / "ds" / "tracks").glob("*.parquet")))
        logs = table.column("log_id").unique()
        builders = _channels(table)
        build: dict[str, list[float]] = {name: [] for name in ["columns", *builders]}
        write: dict[str, list[float]] = {name: [] for name in builders}
        sizes: dict[str, dict[str, int]] = {}
        for _ in range(rounds):
            start = time.process_time()
            LogRows.of(table)
            build["columns"].append(time.process_time() - start)
            for k, (name, make) in enumerate(builders.items()):
                start = time.process_time()
                messages = make()
                build[name].append(time.process_time() - start)
                folder = Path(tmp) / f"w{k}"
                folder.mkdir(exist_ok=True)
                start = time.process_time()
                compressed = _write(folder, name, messages)
                write[name].append(time.process_time() - start)
                per_log = [m if isinstance(m, Pieces) else Pieces.of_messages(m) for m in messages[0]]
                sizes[name] = {"messages": sum(len(m) for m in per_log),
                               "raw_bytes": int(sum(m.lengths.sum() for m in per_log)),
                               "file_bytes": compressed}
    scale = 1000 / len(logs)
    rows: dict[str, Any] = {"columns": {"build_cpu_s_per_1000_logs": round(statistics.median(build["columns"]) * scale,
                                                                          3)}}
    for name in builders:
        rows[name] = {**sizes[name], "build_cpu_s_per_1000_logs": round(statistics.median(build[name]) * scale, 3),
                      "write_cpu_s_per_1000_logs": round(statistics.median(write[name]) * scale, 3)}
    return {"benchmark": "mcap_channels", "logs": len(logs), "rounds": rounds, "channels": rows}


if __name__ == "__main__":
    import json
    import sys

    print(json.dumps(run(quick="--quick" in sys.argv), indent=2))
