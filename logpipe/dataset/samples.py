"""The prediction-sample index: windows of ``obs_len + pred_len`` steps cut from continuous logs.

Counting follows Social-GAN's loader: windows are consecutive *distinct timestamps* of a log (steps), and
an agent is a target when it has a row at every step of the window. Times stay true: each sample records
the timestamps of its first, current and last step, and whether its steps are regular.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Iterable, Sequence
from dataclasses import dataclass

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc

from logpipe.contracts import arrow_schema, conform
from logpipe.dataset.shards import log_runs
from logpipe.storage.io import as_numpy
from logpipe.types import LogMeta, NDArrayBool, NDArrayInt, Role, SampleProtocol

REGULAR_TOLERANCE = 0.5
"""A step is regular within 50% of the nominal period 1 / frame_rate_hz: sensor jitter (AV1: ±15%) passes,
a dropped frame (2x) does not."""


@dataclass
class TrackCodes:
    """Integer codes of the string columns of a track table (hash each string column once per batch).

    Attributes:
        log_code: (rows,) index into ``log_names``.
        log_names: distinct log ids.
        track_code: (rows,) index into ``track_names``.
        track_names: (tracks,) distinct track ids (object array).
    """

    log_code: NDArrayInt
    log_names: list[str]
    track_code: NDArrayInt
    track_names: np.ndarray

    @classmethod
    def of(cls, tracks: pa.Table) -> TrackCodes:
        """Codes of ``tracks``' ``log_id`` and ``track_id``."""
        log_col = pc.dictionary_encode(tracks.column("log_id")).combine_chunks()
        track_col = pc.dictionary_encode(tracks.column("track_id")).combine_chunks()
        return cls(
            log_code=as_numpy(log_col.indices).astype(np.int64),
            log_names=log_col.dictionary.to_pylist(),
            track_code=as_numpy(track_col.indices).astype(np.int64),
            track_names=np.array(track_col.dictionary.to_pylist(), dtype=object),
        )


def build_samples(
    tracks: pa.Table, logs: Sequence[LogMeta], protocol: SampleProtocol, codes: TrackCodes | None = None
) -> pa.Table:
    """Sample index rows for the logs of ``tracks`` (rows sorted by log, then step), in log order.

    Args:
        tracks: canonical track rows of whole logs, each log contiguous and sorted by step.
        logs: metadata of those logs (for the nominal frame rate).
        protocol: the window and target rules.
        codes: ``TrackCodes.of(tracks)`` when the caller has them already.
    """
    schema = arrow_schema("samples")
    if tracks.num_rows == 0:
        return schema.empty_table()
    codes = codes or TrackCodes.of(tracks)
    log_code, log_names = codes.log_code, codes.log_names
    track_code, track_names = codes.track_code, codes.track_names
    steps = as_numpy(tracks.column("step")).astype(np.int64)
    ts = as_numpy(tracks.column("timestamp_ns"))
    focal = as_numpy(pc.equal(tracks.column("role"), Role.FOCAL.value))
    excluded = _excluded_rows(tracks, protocol)
    rate = {m.log_id: m.frame_rate_hz for m in logs}
    if protocol.window == "first":
        return conform(pa.table(_first_windows(log_code, log_names, track_code, track_names, steps, ts, focal,
                                               protocol, rate, excluded)), schema)

    starts, ends = log_runs(log_code)
    columns: dict[str, list[object]] = {name: [] for name in schema.names}
    for lo, hi in zip(starts.tolist(), ends.tolist(), strict=True):
        log_id = log_names[log_code[lo]]
        _log_windows(
            columns, log_id, steps[lo:hi], ts[lo:hi], track_code[lo:hi], track_names, focal[lo:hi],
            protocol, 1e9 / rate[log_id] if rate.get(log_id) else 0.0, None if excluded is None else excluded[lo:hi],
        )
    return conform(pa.table(columns), schema)


def _excluded_rows(tracks: pa.Table, protocol: SampleProtocol) -> NDArrayBool | None:
    """Rows of tracks that may not be targets under ``protocol`` (the ego for ``fully_observed_no_ego``, types
    outside ``target_types``), or None when the rule excludes nobody: the presets' index is built as before."""
    no_ego = protocol.targets == "fully_observed_no_ego"
    if not no_ego and not protocol.target_types:
        return None
    excluded = np.zeros(tracks.num_rows, dtype=bool)
    if no_ego:
        excluded |= as_numpy(pc.equal(tracks.column("role"), Role.EGO.value))
    if protocol.target_types:
        kinds = tracks.column("object_type")
        if pa.types.is_dictionary(kinds.type):
            kinds = kinds.cast(pa.string())
        excluded |= ~as_numpy(pc.is_in(kinds, value_set=pa.array(list(protocol.target_types), pa.string())))
    return excluded


def _log_windows(  # noqa: PLR0913  one log's parallel column arrays; a holder would only be unpacked
    out: dict[str, list[object]],
    log_id: str,
    steps: NDArrayInt,
    ts: NDArrayInt,
    tracks: NDArrayInt,
    track_names: np.ndarray,
    focal: np.ndarray,
    protocol: SampleProtocol,
    period_ns: float,
    excluded: NDArrayBool | None = None,
) -> None:
    n_steps = int(steps[-1]) + 1
    seq = protocol.seq_len
    if n_steps < seq:
        return
    # Timestamp of each step (rows are sorted by step, so the first row of each step carries it).
    first_rows = np.flatnonzero(np.diff(steps, prepend=-1))
    step_ts = ts[first_rows]
    windows = _window_targets(steps, tracks, focal, protocol, excluded)
    focal_ids = windows.focal_ids
    if protocol.targets == "focal" and not len(focal_ids):
        return
    window_starts, local_ids, target_rows = windows.starts, windows.local_ids, windows.targets
    focal_name = str(track_names[local_ids[focal_ids[0]]]) if len(focal_ids) else None
    counts = target_rows.sum(axis=0)
    dt = np.diff(step_ts)
    if period_ns > 0:
        regular_step = np.abs(dt - period_ns) <= REGULAR_TOLERANCE * period_ns
        bad_cumulative = np.concatenate([[0], np.cumsum(~regular_step)])
    else:
        bad_cumulative = np.zeros(n_steps, dtype=np.int64)
    for w, start in enumerate(window_starts.tolist()):
        if counts[w] < protocol.min_targets:
            continue
        end = start + seq - 1
        current = start + protocol.obs_len - 1
        names = sorted(str(track_names[local_ids[t]]) for t in np.flatnonzero(target_rows[:, w]))
        out["sample_id"].append(f"{log_id}:{start}")
        out["log_id"].append(log_id)
        out["start_step"].append(start)
        out["current_step"].append(current)
        out["end_step"].append(end)
        out["start_ns"].append(int(step_ts[start]))
        out["current_ns"].append(int(step_ts[current]))
        out["end_ns"].append(int(step_ts[end]))
        out["focal_track_id"].append(focal_name)
        out["target_track_ids"].append(names)
        out["regular"].append(bool(bad_cumulative[end] - bad_cumulative[start] == 0))


@dataclass
class _Windows:
    """The windows of one log and who is observed over each.

    Attributes:
        starts: (W,) first step of each window.
        local_ids: (T,) track codes of the log's tracks (row t of the matrices below).
        focal_ids: indices into ``local_ids`` of the focal track(s).
        full: (T, W) track t has a row at every step of window w.
        targets: (T, W) ``full`` narrowed by the protocol's target rules (focal only, excluded types / ego).
    """

    starts: NDArrayInt
    local_ids: NDArrayInt
    focal_ids: NDArrayInt
    full: NDArrayBool
    targets: NDArrayBool


def _window_targets(steps: NDArrayInt, tracks: NDArrayInt, focal: np.ndarray, protocol: SampleProtocol,
                    excluded: NDArrayBool | None) -> _Windows:
    """The windows of one log (at least ``seq_len`` steps long) and its targets in each."""
    n_steps = int(steps[-1]) + 1
    seq = protocol.seq_len
    last_start = 0 if protocol.window == "first" else n_steps - seq
    window_starts = np.arange(0, last_start + 1, protocol.stride)
    local_ids, local = np.unique(tracks, return_inverse=True)
    presence = np.zeros((len(local_ids), n_steps + 1), dtype=np.int32)
    presence[local, steps + 1] = 1
    cumulative = np.cumsum(presence, axis=1)
    # full[t, w]: track t is present at all ``seq`` steps of window w.
    full = (cumulative[:, window_starts + seq] - cumulative[:, window_starts]) == seq
    focal_ids = np.unique(local[focal])
    if protocol.targets == "focal":
        target_rows = np.zeros_like(full)
        if len(focal_ids):
            target_rows[focal_ids[0]] = full[focal_ids[0]]
    else:
        target_rows = full
    if excluded is not None and excluded.any():
        target_rows = target_rows.copy()
        target_rows[np.unique(local[excluded])] = False
    return _Windows(window_starts, local_ids, focal_ids, full, target_rows)


def no_sample_reasons(tracks: pa.Table, protocol: SampleProtocol, samples: pa.Table,
                      codes: TrackCodes | None = None) -> dict[str, str]:
    """Why each log of ``tracks`` without a row in ``samples`` gives no sample: ``{log_id: reason}``.

    The reason is the first rule of the protocol the log fails, in the order the index applies them: too few
    steps for one window, no focal track (``targets="focal"``), no agent with a row at every step of any
    window, no such agent the target rules allow (``target_types``, the ego), fewer than ``min_targets``.
    Only the logs without samples are looked at again, so this costs nothing when every log gives some.

    Args:
        tracks: canonical track rows of whole logs, as given to ``build_samples``.
        protocol: the protocol ``samples`` was built with.
        samples: ``build_samples``' result for ``tracks``.
        codes: ``TrackCodes.of(tracks)`` when the caller has them already.
    """
    if tracks.num_rows == 0:
        return {}
    codes = codes or TrackCodes.of(tracks)
    sampled = set(pc.unique(samples.column("log_id")).to_pylist())
    if sampled.issuperset(codes.log_names):
        return {}
    steps = as_numpy(tracks.column("step")).astype(np.int64)
    focal = as_numpy(pc.equal(tracks.column("role"), Role.FOCAL.value))
    excluded = _excluded_rows(tracks, protocol)
    starts, ends = log_runs(codes.log_code)
    reasons: dict[str, str] = {}
    for lo, hi in zip(starts.tolist(), ends.tolist(), strict=True):
        log_id = codes.log_names[codes.log_code[lo]]
        if log_id not in sampled:
            reasons[log_id] = _no_sample_reason(steps[lo:hi], codes.track_code[lo:hi], focal[lo:hi], protocol,
                                                None if excluded is None else excluded[lo:hi])
    return reasons


def _no_sample_reason(steps: NDArrayInt, tracks: NDArrayInt, focal: np.ndarray, protocol: SampleProtocol,
                      excluded: NDArrayBool | None) -> str:
    """The first protocol rule a log without samples fails (see ``no_sample_reasons``), in words."""
    if int(steps[-1]) + 1 < protocol.seq_len:
        return f"too short for {protocol.obs_len}+{protocol.pred_len} steps"
    w = _window_targets(steps, tracks, focal, protocol, excluded)
    if protocol.targets == "focal":
        if not len(w.focal_ids):
            # AV2 sensor logs: their annotations mark no agent of interest, and the argoverse2 preset predicts
            # only the focal track.
            return "no focal track (targets=focal; --targets fully_observed predicts every agent seen throughout)"
        if not w.full[w.focal_ids[0]].any():
            return "the focal track is not observed over the whole window"
    elif not w.full.any():
        return "no agent observed over the whole window"
    if not w.targets.any():
        if protocol.target_types:
            return f"no target of the selected types ({','.join(protocol.target_types)})"
        return "no agent but the ego observed over the whole window"
    return f"fewer than {protocol.min_targets} targets in every window"


def _first_windows(  # noqa: PLR0913  all logs' parallel column arrays; a holder would only be unpacked
    log_code: NDArrayInt,
    log_names: list[str],
    track_code: NDArrayInt,
    track_names: np.ndarray,
    steps: NDArrayInt,
    ts: NDArrayInt,
    focal: np.ndarray,
    protocol: SampleProtocol,
    rate: dict[str, float],
    excluded: NDArrayBool | None = None,
) -> dict[str, list[object]]:
    """One window at step 0 of every log, for all logs at once (Argoverse: one sample per file).

    The per-log loop of the sliding case costs ~0.2 ms a log, as much as parsing the log; here every
    statistic is a reduction over contiguous runs of the batch.
    """
    seq = protocol.seq_len
    starts, ends = log_runs(log_code)
    n_logs = len(starts)
    log_of_row = np.repeat(np.arange(n_logs), ends - starts)
    n_steps = steps[ends - 1] + 1
    in_window = steps < seq
    # Rows per (log, track) inside the window; a target has one row at every one of the ``seq`` steps.
    n_tracks = int(track_code.max()) + 1
    key = log_of_row * n_tracks + track_code
    full_keys = _complete_keys(key, in_window, focal if protocol.targets == "focal" else None, n_logs * n_tracks,
                               seq)
    if excluded is not None and excluded.any():
        full_keys = np.setdiff1d(full_keys, np.unique(key[excluded]))
    target_log = full_keys // n_tracks
    target_names = track_names[full_keys % n_tracks]
    split_at = np.searchsorted(target_log, np.arange(n_logs + 1))
    focal_rows = np.flatnonzero(focal)
    first_focal = np.full(n_logs, -1)
    first_focal[log_of_row[focal_rows[::-1]]] = focal_rows[::-1]  # reversed so the first row wins
    new_step = (steps[1:] != steps[:-1]) | (log_code[1:] != log_code[:-1])
    first_of_step = np.flatnonzero(np.concatenate([[True], new_step]))
    step_start = np.searchsorted(first_of_step, starts)
    # Every per-log quantity as one array op over the logs long enough for a window; the loop below only
    # gathers the (few) target names of each log.
    eligible = np.flatnonzero(n_steps >= seq)
    step_rows = first_of_step[step_start[eligible][:, None] + np.arange(seq)]  # (logs, seq) first row per step
    step_ts = ts[step_rows]
    names_of = [log_names[c] for c in log_code[starts[eligible]].tolist()]
    period = np.array([1e9 / rate[n] if rate.get(n) else 0.0 for n in names_of], dtype=np.float64)
    off = np.abs(np.diff(step_ts, axis=1) - period[:, None]) > REGULAR_TOLERANCE * period[:, None]
    regular = (period == 0) | ~off.any(axis=1)
    out: dict[str, list[object]] = {name: [] for name in ("sample_id", "log_id", "start_step", "current_step",
                                                            "end_step", "start_ns", "current_ns", "end_ns",
                                                            "focal_track_id", "target_track_ids", "regular")}
    starts_ns, current_ns, end_ns = (step_ts[:, k].tolist() for k in (0, protocol.obs_len - 1, seq - 1))
    regular_list, focal_list = regular.tolist(), first_focal[eligible].tolist()
    for j, i in enumerate(eligible.tolist()):
        names = sorted(str(t) for t in target_names[split_at[i]:split_at[i + 1]])
        if len(names) < protocol.min_targets:
            continue
        log_id = names_of[j]
        out["sample_id"].append(f"{log_id}:0")
        out["log_id"].append(log_id)
        out["start_step"].append(0)
        out["current_step"].append(protocol.obs_len - 1)
        out["end_step"].append(seq - 1)
        out["start_ns"].append(starts_ns[j])
        out["current_ns"].append(current_ns[j])
        out["end_ns"].append(end_ns[j])
        out["focal_track_id"].append(str(track_names[track_code[focal_list[j]]]) if focal_list[j] >= 0 else None)
        out["target_track_ids"].append(names)
        out["regular"].append(bool(regular_list[j]))
    return out


# Count (log, track) pairs in a dense array when it has at most this many slots per row, else by sorting.
DENSE_KEYS_PER_ROW = 64


def _complete_keys(key: NDArrayInt, in_window: NDArrayBool, focal: NDArrayBool | None, n_keys: int,
                   seq: int) -> NDArrayInt:
    """Sorted distinct keys (in ``[0, n_keys)``) with exactly ``seq`` rows in the window and, when ``focal``
    is given, a focal row.

    A bincount over the key range is ~8x faster than ``np.unique``'s sort (~10 ms a batch of 250 Argoverse
    logs, most of the sample index's cost); the sort serves key ranges too sparse for an array.
    """
    if n_keys <= DENSE_KEYS_PER_ROW * max(len(key), 1):
        complete = np.bincount(key[in_window], minlength=n_keys) == seq
        if focal is not None:
            has_focal = np.zeros(n_keys, dtype=bool)
            has_focal[key[focal]] = True
            complete &= has_focal
        return np.flatnonzero(complete)
    keys, counts = np.unique(key[in_window], return_counts=True)
    full_keys: NDArrayInt = keys[counts == seq]
    if focal is not None:
        full_keys = np.intersect1d(full_keys, np.unique(key[focal]), assume_unique=True)
    return full_keys


def steps_from_sorted_times(ts_ns: NDArrayInt, group: NDArrayInt) -> NDArrayInt:
    """Step (rank of the distinct timestamp within its group: a file or a log) for rows sorted by time in each
    group and with each group contiguous."""
    n = len(ts_ns)
    if n == 0:
        return np.zeros(0, dtype=np.int64)
    new_group = np.ones(n, dtype=bool)
    new_group[1:] = group[1:] != group[:-1]
    new_time = new_group.copy()
    new_time[1:] |= ts_ns[1:] != ts_ns[:-1]
    counter = np.cumsum(new_time) - 1
    first_of_group = counter[np.flatnonzero(new_group)]
    group_starts = np.repeat(first_of_group, np.diff(np.append(np.flatnonzero(new_group), n)))
    result: NDArrayInt = counter - group_starts
    return result


def reason_counts(reasons: Iterable[str]) -> dict[str, int]:
    """How many logs give no sample for each reason (``no_sample_reasons``' values), the most frequent first."""
    return dict(Counter(reasons).most_common())
