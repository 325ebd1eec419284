"""Validation data a training run picks for itself (``logpipe train`` on driving data without ``--config``).

Two ways, whichever the data allows:

* **whole recordings** when there are at least ``MIN_GROUPS`` groups of logs: logs that share tracks
  (``logpipe.dataset.locations.shared_tracks``, recorded in the later log's ``attributes["shared_tracks"]``) form
  one group, so one agent is never on both sides; groups go to validation in the order of ``hash_fraction`` of
  their first log (stable, unrelated to names or time) until they hold ``VAL_SHARE`` of the windows (skipping a
  group that would take them past 1.5 times that);
* otherwise **the later part of each recording**: per log, the windows starting at or after a cut step (the start
  of the window at ``1 - VAL_SHARE`` of its windows) validate, the windows ending before it train, and the windows
  that straddle the cut are used for neither (no validation window overlaps a training one in time). A log of one
  window cannot be cut and trains.

When neither is possible (one recording too short to cut without overlap), nothing validates (``how`` ``none``):
every window trains, and the run says so (``logpipe train`` then keeps physics as the K = 1 forecast).

Nothing here reads tracks: the logs table and the sample index are enough.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pyarrow as pa

from logpipe.dataset.locations import track_sharing_groups
from logpipe.dataset.reader import hash_fraction

MIN_GROUPS = 5
"""Fewer groups of logs than this validate on the later part of each recording instead of whole recordings."""
VAL_SHARE = 0.2
"""Share of the windows that validate."""


@dataclass
class Holdout:
    """The split of one run: per dataset (in the order given) the sample ids that train and that validate.

    Attributes:
        how: ``recordings`` (whole groups of logs) or ``later_part`` (each recording cut in time).
        train_ids, val_ids: per dataset, sample ids.
        val_logs: per dataset, the logs that validate (whole, or their later part).
        groups: how many groups of logs there were (logs joined by shared tracks).
        straddling: windows used for neither side (they overlap the cut).
        cut_steps: ``later_part``: per log cut, its first validation step.
    """

    how: str
    train_ids: list[list[str]]
    val_ids: list[list[str]]
    val_logs: list[list[str]]
    groups: int
    straddling: int = 0
    cut_steps: dict[str, int] = field(default_factory=dict)

    def describe(self) -> str:
        """One line for the summary."""
        n_train, n_val = sum(map(len, self.train_ids)), sum(map(len, self.val_ids))
        if self.how == "none":
            return (f"none: {self.groups} recording(s) of {n_train} window(s), too short to hold out a later part "
                    "without overlapping the training windows; all of them train")
        if self.how == "recordings":
            logs = sum(map(len, self.val_logs))
            return (f"{logs} whole recording(s) of {self.groups} groups (recordings sharing tracks kept on one side): "
                    f"{n_train} training and {n_val} validation windows")
        return (f"the later {VAL_SHARE:.0%} of each recording ({self.groups} group(s) of recordings, too few to hold "
                f"whole ones out): {n_train} training and {n_val} validation windows, {self.straddling} windows "
                "overlapping the cut unused")

    def record(self) -> dict[str, Any]:
        """The summary's ``validation`` record."""
        return {"how": self.how, "groups": self.groups, "train_windows": sum(map(len, self.train_ids)),
                "val_windows": sum(map(len, self.val_ids)), "val_logs": [sorted(v) for v in self.val_logs],
                "straddling_windows": self.straddling, "cut_steps": self.cut_steps, "description": self.describe()}


def log_groups(logs: Sequence[pa.Table]) -> list[list[tuple[int, str]]]:
    """Groups of (dataset number, log id): logs of one dataset that share tracks are one group
    (``logpipe.dataset.locations.track_sharing_groups``), every other log a group of its own; in dataset and log
    order."""
    groups: dict[tuple[int, str], list[tuple[int, str]]] = {}
    for number, table in enumerate(logs):
        ids = [str(i) for i in table.column("log_id").to_pylist()]
        for log_id, first in track_sharing_groups(ids, table.column("attributes").to_pylist()).items():
            groups.setdefault((number, first), []).append((number, log_id))
    return list(groups.values())


def choose_holdout(logs: Sequence[pa.Table], samples: Sequence[pa.Table]) -> Holdout:
    """The validation split of datasets with these logs tables and sample indexes (see the module docstring)."""
    groups = log_groups(logs)
    windows = {(n, str(log_id)) for n, table in enumerate(samples) for log_id in table.column("log_id").to_pylist()}
    groups = [g for g in groups if any(key in windows for key in g)]  # logs without windows count for nothing
    if len(groups) >= MIN_GROUPS:
        return _by_recordings(groups, samples)
    cut = _by_later_part(groups, samples)
    if sum(map(len, cut.val_ids)) and sum(map(len, cut.train_ids)):
        return cut
    if len(groups) >= 2:  # recordings of a single window each cannot be cut in time; hold out whole ones
        return _by_recordings(groups, samples)
    every = [[str(i) for i in t.column("sample_id").to_pylist()] for t in samples]
    return Holdout("none", every, [[] for _ in samples], [[] for _ in samples], len(groups))


def _by_recordings(groups: list[list[tuple[int, str]]], samples: Sequence[pa.Table]) -> Holdout:
    """Whole groups to validation by hash order until they hold ``VAL_SHARE`` of the windows (at least one group,
    never all)."""
    per_log: dict[tuple[int, str], int] = {}
    for n, table in enumerate(samples):
        for log_id in table.column("log_id").to_pylist():
            per_log[(n, str(log_id))] = per_log.get((n, str(log_id)), 0) + 1
    total = sum(per_log.values())
    ranked = sorted(groups, key=lambda g: hash_fraction(g[0][1]))
    chosen: set[tuple[int, str]] = set()
    held = 0
    for group in ranked[: len(ranked) - 1]:
        if held >= VAL_SHARE * total:
            break
        size = sum(per_log.get(key, 0) for key in group)
        if held and held + size > 1.5 * VAL_SHARE * total:  # a big group would overshoot: try the next one
            continue
        chosen.update(group)
        held += size
    train_ids, val_ids, val_logs = [], [], []
    for n, table in enumerate(samples):
        ids = [str(i) for i in table.column("sample_id").to_pylist()]
        logs_of = [str(i) for i in table.column("log_id").to_pylist()]
        val_ids.append([s for s, log in zip(ids, logs_of, strict=True) if (n, log) in chosen])
        train_ids.append([s for s, log in zip(ids, logs_of, strict=True) if (n, log) not in chosen])
        val_logs.append(sorted({log for (m, log) in chosen if m == n}))
    return Holdout("recordings", train_ids, val_ids, val_logs, len(groups))


def _by_later_part(groups: list[list[tuple[int, str]]], samples: Sequence[pa.Table]) -> Holdout:
    """Each log's windows from its cut step on validate, those ending before it train."""
    train_ids: list[list[str]] = []
    val_ids: list[list[str]] = []
    val_logs: list[list[str]] = []
    straddling = 0
    cuts: dict[str, int] = {}
    for table in samples:
        ids = np.asarray([str(i) for i in table.column("sample_id").to_pylist()], dtype=object)
        logs_of = np.asarray([str(i) for i in table.column("log_id").to_pylist()], dtype=object)
        start = np.asarray(table.column("start_step").to_numpy(), np.int64)
        end = np.asarray(table.column("end_step").to_numpy(), np.int64)
        train, val, held = [], [], []
        for log_id in dict.fromkeys(logs_of.tolist()):
            rows = np.flatnonzero(logs_of == log_id)
            rows = rows[np.argsort(start[rows], kind="stable")]
            if len(rows) < 2:
                train += ids[rows].tolist()
                continue
            at = min(max(math.floor(len(rows) * (1 - VAL_SHARE)), 1), len(rows) - 1)
            cut = int(start[rows[at]])
            later, earlier = rows[start[rows] >= cut], rows[end[rows] < cut]
            if not len(earlier):  # every window overlaps the first validation window: keep the log for training
                train += ids[rows].tolist()
                continue
            cuts[log_id] = cut
            val += ids[later].tolist()
            train += ids[earlier].tolist()
            held.append(log_id)
            straddling += len(rows) - len(later) - len(earlier)
        train_ids.append(train)
        val_ids.append(val)
        val_logs.append(held)
    return Holdout("later_part", train_ids, val_ids, val_logs, len(groups), straddling, cuts)
