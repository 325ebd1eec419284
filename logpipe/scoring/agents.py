"""The ground truth a score compares against: which agents of a dataset count under the protocol flags
(``agents``, ``min_agents``, ``split``), their true futures (metres, world frame) from the track table, and
the nominal step length (seconds) the report's horizons are given in."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc

from logpipe.dataset.reader import Dataset
from logpipe.errors import ScoreError
from logpipe.storage.io import as_numpy, read_table
from logpipe.types import NDArrayFloat

Agents = Literal["all", "focal"]
"""``all``: every target of the protocol; ``focal``: the sample's focal track only."""


@dataclass
class Selection:
    """The agents that count under the protocol flags, and the samples' facts the report needs."""

    samples: pa.Table  # the kept rows of the sample index
    expected: set[tuple[str, str]]  # (sample_id, track_id) that must be scored
    dropped: dict[str, int]


def select_agents(ds: Dataset, sample_ids: set[str], *, split: str | None, agents: Agents,
                  min_agents: int) -> Selection:
    """Samples (of ``split``, else those predicted) with >= ``min_agents`` targets, and the agents to score.

    ``agents="all"``: every target of the protocol (ETH/UCY: every agent present in all steps of the window);
    ``"focal"``: the sample's focal track only (Argoverse). ``min_agents`` counts the sample's targets
    (Social-GAN's loader keeps windows with >= 2 fully observed pedestrians).
    """
    table = ds.samples()
    if split is not None:
        logs = ds.logs_in_split(split)
        table = table.filter(pc.is_in(table.column("log_id"), value_set=pa.array(logs)))
    else:
        table = table.filter(pc.is_in(table.column("sample_id"), value_set=pa.array(sorted(sample_ids), pa.string())))
        unknown = sample_ids - set(table.column("sample_id").to_pylist())
        if unknown:
            raise ScoreError(f"{ds.root}: {len(unknown)} predicted samples are not in the dataset's sample index, "
                             f"e.g. {sorted(unknown)[0]!r} (predictions made on another dataset or protocol?)")
    n_targets = pc.list_value_length(table.column("target_track_ids"))
    few = pc.less(n_targets, min_agents)
    dropped = {"samples_below_min_agents": int(pc.sum(few).as_py() or 0)}
    table = table.filter(pc.invert(few))
    expected: set[tuple[str, str]] = set()
    no_focal = 0
    for sid, targets, focal in zip(table.column("sample_id").to_pylist(), table.column("target_track_ids").to_pylist(),
                                   table.column("focal_track_id").to_pylist(), strict=True):
        if agents == "focal":
            if focal is None:
                no_focal += 1
            else:
                expected.add((sid, focal))
        else:
            expected.update((sid, t) for t in targets)
    dropped["samples_without_focal"] = no_focal
    return Selection(samples=table, expected=expected, dropped=dropped)


def truth_futures(ds: Dataset, sample_table: pa.Table, sample_ids: Any, track_ids: Any,
                  pred_len: int) -> tuple[NDArrayFloat, Any]:
    """True positions (N, T, 2) metres of each (sample, track) at steps current+1 .. current+T, NaN where the
    track has no row, and each row's log id; one join against the track table of the logs involved."""
    n = len(sample_ids)
    agents = pa.table({"i": pa.array(np.arange(n)), "sample_id": pa.array(sample_ids, pa.string()),
                       "track_id": pa.array(track_ids, pa.string())})
    agents = agents.join(sample_table.select(["sample_id", "log_id", "current_step"]), "sample_id")
    agents = agents.sort_by("i")
    if agents.num_rows != n:
        raise ScoreError("internal: agents lost when joining the sample index")
    log_ids = as_numpy(agents.column("log_id")).astype(str)
    cur = as_numpy(agents.column("current_step")).astype(np.int64)
    keys = pa.table({
        "i": pa.array(np.repeat(np.arange(n), pred_len)),
        "t": pa.array(np.tile(np.arange(pred_len), n)),
        "log_id": pa.array(np.repeat(log_ids, pred_len), pa.string()),
        "track_id": pa.array(np.repeat(np.asarray(track_ids, dtype=str), pred_len), pa.string()),
        "step": pa.array((cur[:, None] + np.arange(1, pred_len + 1)).reshape(-1).astype(np.int32)),
    })
    needed = sorted(set(log_ids.tolist()))
    parts = [read_table(p, columns=["log_id", "track_id", "step", "x", "y"], filters=[("log_id", "in", needed)])
             for p in ds.shard_paths]
    tracks = pa.concat_tables(parts)
    joined = keys.join(tracks, ["log_id", "track_id", "step"], join_type="left outer")
    if joined.num_rows != len(keys):
        raise ScoreError(f"{ds.root}: the track table has duplicate (log, track, step) rows; re-ingest the dataset")
    joined = joined.sort_by([("i", "ascending"), ("t", "ascending")])
    truth = np.stack([as_numpy(joined.column("x").fill_null(math.nan)),
                      as_numpy(joined.column("y").fill_null(math.nan))], axis=-1).astype(np.float64)
    return truth.reshape(n, pred_len, 2), log_ids


def step_seconds(ds: Dataset) -> float:
    """Nominal seconds per step from the logs' frame rates (10 Hz → 0.1, ETH/UCY 2.5 Hz → 0.4); the measured
    median step when no rate is known. Nominal because AV1 clocks jitter around 0.1 s."""
    logs = ds.logs()
    rates = as_numpy(logs.column("frame_rate_hz")).astype(np.float64)
    rates = rates[np.isfinite(rates) & (rates > 0)]
    if len(rates):
        return round(1.0 / float(np.median(rates)), 6)
    dts = as_numpy(logs.column("median_dt_ns")).astype(np.float64)
    dts = dts[dts > 0]
    return round(float(np.median(dts)) / 1e9, 6) if len(dts) else math.nan
