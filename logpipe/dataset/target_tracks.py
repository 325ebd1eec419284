"""Columnar windowing for predictors that read only their targets' own observed tracks (constant velocity):
the targets of many samples cut at once from a shard's track rows, with no ``SceneSample`` per sample.

It gives the targets, order and values that ``LogWindows.sample`` and ``SampleCutter.cut`` give sample by
sample, and it is tested against them: a sample's targets are those of its ``target_track_ids`` seen in its
window, in order of first appearance there; a track's class is that of its last row in the window; where a
(track, step) has several rows, the last one counts.

Frames and units: x/y are metres in the log's world frame; times are ns on the log's clock; steps are the log's
integer time steps.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc

from logpipe.contracts import decode_dictionaries
from logpipe.storage.io import as_numpy
from logpipe.types import OBJECT_TYPES, NDArrayBool, NDArrayFloat, NDArrayInt

SAMPLE_COLUMNS = ("log_id", "sample_id", "start_step", "end_step", "target_track_ids")
"""The sample-index columns ``ShardTracks.targets`` reads."""


@dataclass(frozen=True)
class TargetTracks:
    """The targets of consecutive samples, in sample order and, within a sample, in window order.

    Attributes:
        per_sample: (S,) targets kept of each sample (0: a sample without targets).
        sample_of: (N,) index of each target's sample.
        track_ids: (N,) the targets' track ids (str objects).
        object_types: (N,) integer codes into ``OBJECT_TYPES``.
        observed: (N, T_obs, 2) world metres at the observed steps, NaN where unobserved.
        step_ns: (S, T_pred) times of each sample's future steps: the window's own where it has them, else the
            current time + k x the log's median step.
        truth: (N, T_fut, 2) world metres at the window's steps after the observed ones, NaN where unobserved
            (T_fut: the longest such part among the samples); None unless asked for.
    """

    per_sample: NDArrayInt
    sample_of: NDArrayInt
    track_ids: np.ndarray
    object_types: NDArrayInt
    observed: NDArrayFloat
    step_ns: NDArrayInt
    truth: NDArrayFloat | None = None


class ShardTracks:
    """A shard's track rows sorted once by (log, track, step), for cutting the targets of many samples.

    Args:
        tracks: the shard's rows, grouped by log and sorted by step within a log (as shards store them).

    Raises:
        ValueError: a log's rows are not contiguous or not sorted by step.
    """

    COLUMNS = ("log_id", "step", "track_id", "x", "y", "timestamp_ns", "object_type")
    """The tracks columns it reads: a caller reading a shard for it need read no others."""

    def __init__(self, tracks: pa.Table) -> None:
        tracks = decode_dictionaries(tracks.select(list(self.COLUMNS)))
        logs = pc.dictionary_encode(tracks.column("log_id").combine_chunks())
        names = pc.dictionary_encode(tracks.column("track_id").combine_chunks())
        self._log_names, self._track_names = logs.dictionary, names.dictionary
        log_code = logs.indices.to_numpy().astype(np.int64)
        step = as_numpy(tracks.column("step")).astype(np.int64)
        self._step0 = int(step.min()) - 1 if len(step) else 0
        rel = step - self._step0  # >= 1, so 0 and -1 are free for "before the first step"
        self._span = int(rel.max()) + 2 if len(rel) else 2
        by_log_step = log_code * self._span + rel
        if len(rel) > 1 and bool((np.diff(by_log_step) < 0).any()):
            raise ValueError("ShardTracks needs each log's rows together and sorted by step (as shards store them)")
        self._by_log_step = by_log_step  # non-decreasing: log codes number logs in row order
        self._ts = as_numpy(tracks.column("timestamp_ns")).astype(np.int64)
        key = log_code * len(names.dictionary) + names.indices.to_numpy().astype(np.int64)
        self._order = np.lexsort((rel, key))  # stable: rows of one (track, step) keep their stored order
        self._sorted = key[self._order] * self._span + rel[self._order]
        self._x = as_numpy(tracks.column("x")).astype(np.float64)
        self._y = as_numpy(tracks.column("y")).astype(np.float64)
        type_code = {t: i for i, t in enumerate(OBJECT_TYPES)}
        types = pc.dictionary_encode(tracks.column("object_type").combine_chunks())
        lookup = np.array([type_code[t] for t in types.dictionary.to_pylist()], np.int64)
        self._types = lookup[types.indices.to_numpy()] if len(lookup) else np.zeros(0, np.int64)

    def targets(self, samples: pa.Table, obs_len: int, pred_len: int, dt_ns: NDArrayInt,
                object_types: tuple[str, ...] = (), with_truth: bool = False) -> TargetTracks:
        """The targets of ``samples`` (sample-index rows of this shard's logs, ``SAMPLE_COLUMNS``).

        Args:
            obs_len, pred_len: the protocol's observed and predicted steps.
            dt_ns: (S,) each sample's log median step, for future steps past the window.
            object_types: keep only targets of these classes (empty: all).
            with_truth: also cut each target's positions after the observed steps (``TargetTracks.truth``).
        """
        samples = decode_dictionaries(samples.select(list(SAMPLE_COLUMNS)))
        n_samples = samples.num_rows
        # Relative steps clipped into [0, span - 1]: no row has 0 or span - 1, so a window past either end of the
        # shard's steps finds only its own rows, never another track's.
        start = np.clip(as_numpy(samples.column("start_step")).astype(np.int64) - self._step0, 0, self._span - 1)
        end = np.clip(as_numpy(samples.column("end_step")).astype(np.int64) - self._step0, 0, self._span - 1)
        log_code = _codes(samples.column("log_id"), self._log_names)
        lists = samples.column("target_track_ids").combine_chunks()
        sample_of = np.repeat(np.arange(n_samples), pc.list_value_length(lists).fill_null(0).to_numpy())
        track_code = _codes(pc.list_flatten(lists), self._track_names)
        known = (track_code >= 0) & (log_code[sample_of] >= 0)
        sample_of, track_code = sample_of[known], track_code[known]
        key = (log_code[sample_of] * len(self._track_names) + track_code) * self._span
        first = np.searchsorted(self._sorted, key + start[sample_of])
        last = np.searchsorted(self._sorted, key + end[sample_of], side="right") - 1
        seen = last >= first  # the track has rows in the window
        sample_of, key, first, last = sample_of[seen], key[seen], first[seen], last[seen]
        # Window order: by the row number of each target's first row in the window; a repeated id once.
        first_row = self._order[first]
        arrange = np.lexsort((first_row, sample_of))
        sample_of, key, first, last, first_row = (a[arrange] for a in (sample_of, key, first, last, first_row))
        fresh = np.ones(len(key), bool)
        fresh[1:] = (sample_of[1:] != sample_of[:-1]) | (key[1:] != key[:-1])
        sample_of, key, first, last = sample_of[fresh], key[fresh], first[fresh], last[fresh]
        types = self._types[self._order[last]]
        if object_types:
            keep = np.isin(np.asarray(OBJECT_TYPES)[types], object_types)
            sample_of, key, types = sample_of[keep], key[keep], types[keep]
        window_start = start[sample_of]
        # Observed steps clipped into the shard's steps: a key plus a step past them would be another track's.
        observed = self._positions(key, window_start, np.minimum(window_start + obs_len - 1, self._span - 1), obs_len)
        truth = None
        if with_truth:
            future_start = np.minimum(window_start + obs_len, self._span - 1)
            length = max(int((end - start + 1 - obs_len).max(initial=0)), 0)
            truth = self._positions(key, future_start, end[sample_of], length)
        names = self._track_names.to_numpy(zero_copy_only=False)
        return TargetTracks(
            per_sample=np.bincount(sample_of, minlength=n_samples).astype(np.int64),
            sample_of=sample_of.astype(np.int64),
            track_ids=names[key // self._span % len(self._track_names)] if len(key) else np.zeros(0, object),
            object_types=types,
            observed=observed,
            step_ns=self._future_times(log_code, start, end, obs_len, pred_len, np.asarray(dt_ns, np.int64)),
            truth=truth,
        )

    def _positions(self, key: NDArrayInt, lo: NDArrayInt, hi: NDArrayInt, length: int) -> NDArrayFloat:
        """(N, length, 2) positions of each target (its ``key``) at its relative steps ``lo`` .. ``hi`` (both in the
        shard's steps), step ``lo`` first; NaN where it has no row."""
        n = len(key)
        positions = np.full((n, length, 2), np.nan)
        first = np.searchsorted(self._sorted, key + lo)
        stop = np.searchsorted(self._sorted, key + hi, side="right")
        counts = np.maximum(stop - first, 0)
        target = np.repeat(np.arange(n), counts)
        at = np.arange(int(counts.sum())) - np.repeat(np.cumsum(counts) - counts, counts) + np.repeat(first, counts)
        rows = self._order[at]
        offset = self._sorted[at] % self._span - lo[target]
        positions[target, offset, 0] = self._x[rows]  # in row order, so the last of duplicate rows wins
        positions[target, offset, 1] = self._y[rows]
        return positions

    def _future_times(self, log_code: NDArrayInt, start: NDArrayInt, end: NDArrayInt, obs_len: int,
                      pred_len: int, dt_ns: NDArrayInt) -> NDArrayInt:
        """(S, pred_len) future step times (``logpipe.prediction.output.future_times`` column-wise)."""
        steps = start[:, None] + np.arange(obs_len - 1, obs_len + pred_len)[None, :]  # current, then the future
        inside = steps <= end[:, None]  # end is clipped to the shard's steps, so the lookup stays in the log
        found = self._time_at(log_code[:, None] * self._span + np.minimum(steps, self._span - 1)) * inside
        current, future = found[:, :1], found[:, 1:]
        fallback = current + dt_ns[:, None] * np.arange(1, pred_len + 1, dtype=np.int64)[None, :]
        result: NDArrayInt = np.where(future > 0, future, fallback)
        return result

    def _time_at(self, log_steps: NDArrayInt) -> NDArrayInt:
        """The time of the last row at each (log code x span + relative step), 0 where the log has none."""
        at = np.searchsorted(self._by_log_step, log_steps, side="right") - 1
        hit: NDArrayBool = (at >= 0) & (self._by_log_step[np.maximum(at, 0)] == log_steps)
        times: NDArrayInt = np.where(hit, self._ts[np.maximum(at, 0)], 0)
        return times


def _codes(values: pa.Array | pa.ChunkedArray, dictionary: pa.Array) -> NDArrayInt:
    """Each value's index in ``dictionary``, -1 where absent."""
    found = pc.index_in(values, value_set=dictionary)
    codes: NDArrayInt = as_numpy(found.fill_null(-1)).astype(np.int64)
    return codes
