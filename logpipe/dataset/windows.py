"""Cutting windows out of one log's track rows: the one windowing implementation.

``LogWindows`` converts a log's columns to NumPy once; each window is then two binary searches over the step
column and a scatter, instead of an Arrow filter per window. ``SceneSample``s (``dataset.reader.scene_sample``, the
predict stage) and the rasteriser's per-track lookups all cut their windows here. The one column-wise counterpart,
``dataset.target_tracks`` (only the targets' own tracks, for constant velocity), is tested against it.

Frames and units: x/y are metres in the log's world frame; ``timestamp_ns`` is ns on the log's clock; steps are
the log's integer time steps.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc

from logpipe.contracts import decode_dictionaries
from logpipe.dataset.shards import log_slices
from logpipe.storage.io import as_numpy
from logpipe.types import OBJECT_TYPES, NDArrayInt, Role, SceneSample


class LogWindows:
    """One log's rows as NumPy arrays, for cutting many windows quickly.

    Args:
        tracks: one log's rows, sorted by step (as shards store them; binary searches rely on it).

    Raises:
        ValueError: the rows are not sorted by step.

    Attributes:
        steps: (R,) int64 step of each row.
        names: track ids; ``codes`` (R,) indexes it per row.
        x, y: (R,) float64 world metres; ``ts``: (R,) int64 ns.
        types: (R,) int64 index into ``OBJECT_TYPES``; ``ego``: (R,) bool, the row's role is ``ego``.
    """

    def __init__(self, tracks: pa.Table) -> None:
        self._view(_Columns(tracks), 0, tracks.num_rows)

    @classmethod
    def of_logs(cls, tracks: pa.Table) -> dict[str, LogWindows]:
        """``{log_id: LogWindows}`` of every log in ``tracks`` (several logs' rows grouped by log, each sorted by
        step, as shards store them), in row order: the columns are converted once for all of them (per log, the
        fixed cost of the conversion was most of an Argoverse sample's cut)."""
        columns = _Columns(tracks)
        windows = {}
        for log_id, (lo, hi) in log_slices(tracks).items():
            windows[log_id] = cls.__new__(cls)
            windows[log_id]._view(columns, lo, hi)
        return windows

    def _view(self, columns: _Columns, lo: int, hi: int) -> None:
        """Take rows [lo, hi) of ``columns`` (views, no copies); track names stay those of all ``columns``."""
        self.steps = columns.steps[lo:hi]
        if len(self.steps) > 1 and bool((np.diff(self.steps) < 0).any()):
            raise ValueError("LogWindows needs a log's rows sorted by step (as dataset shards store them)")
        self.names, self._code_of = columns.names, columns.code_of
        self.codes, self.x, self.y = columns.codes[lo:hi], columns.x[lo:hi], columns.y[lo:hi]
        self.ts, self.types, self.ego = columns.ts[lo:hi], columns.types[lo:hi], columns.ego[lo:hi]

    def span(self, first: int, last: int) -> tuple[int, int]:
        """Row range [lo, hi) of the steps ``first..last`` (inclusive)."""
        lo, hi = np.searchsorted(self.steps, [first, last + 1])
        return int(lo), int(hi)

    def track_rows(self, track_id: str, first: int, last: int) -> NDArrayInt:
        """Indices of the rows of ``track_id`` with ``first <= step <= last``, in step order."""
        code = self._code_of.get(track_id)
        if code is None:
            return np.zeros(0, np.int64)
        lo, hi = self.span(first, last)
        rows: NDArrayInt = lo + np.flatnonzero(self.codes[lo:hi] == code)
        return rows

    def track_ids(self) -> list[str]:
        """The ids of the tracks that have rows, sorted."""
        return sorted(self.names[c] for c in np.unique(self.codes).tolist())

    def sample(self, row: dict[str, Any], obs_len: int) -> SceneSample:
        """The window of one sample-index row: every agent seen in it (in order of first appearance), NaN
        where unobserved; ``obs_len`` is the protocol's observed steps."""
        start, end = int(row["start_step"]), int(row["end_step"])
        lo, hi = self.span(start, end)
        codes = self.codes[lo:hi]
        # Window-local agent numbering in order of first appearance (as dictionary_encode numbers them).
        uniq, first = np.unique(codes, return_index=True)
        order = uniq[np.argsort(first)]
        local = np.empty(len(self.names), np.int64)  # uninitialised: only the window's codes are set and read
        local[order] = np.arange(len(order))
        agent = local[codes]
        steps = self.steps[lo:hi] - start
        seq = end - start + 1
        positions = np.full((len(order), seq, 2), np.nan)
        positions[agent, steps, 0] = self.x[lo:hi]
        positions[agent, steps, 1] = self.y[lo:hi]
        timestamps = np.zeros(seq, np.int64)
        timestamps[steps] = self.ts[lo:hi]
        object_types = np.zeros(len(order), np.int64)
        object_types[agent] = self.types[lo:hi]
        ego_rows = agent[self.ego[lo:hi]]
        names = [self.names[c] for c in order.tolist()]
        targets = set(row["target_track_ids"])
        return SceneSample(
            sample_id=str(row["sample_id"]),
            positions=positions,
            timestamps_ns=timestamps,
            track_ids=names,
            object_types=object_types,
            target_mask=np.array([n in targets for n in names], dtype=bool),
            ego_index=int(ego_rows.min()) if len(ego_rows) else -1,
            obs_len=obs_len,
        )


class _Columns:
    """The columns ``LogWindows`` cuts from, as NumPy arrays over all rows of a table (one log or a shard)."""

    def __init__(self, tracks: pa.Table) -> None:
        # Plain strings: a column read with its file's dictionary would number every track of the row group.
        tracks = decode_dictionaries(tracks.select(["step", "track_id", "x", "y", "timestamp_ns", "object_type",
                                                    "role"]))
        self.steps = as_numpy(tracks.column("step")).astype(np.int64)
        encoded = pc.dictionary_encode(tracks.column("track_id")).combine_chunks()
        self.names: list[str] = [str(n) for n in encoded.dictionary.to_pylist()]
        self.code_of = {n: i for i, n in enumerate(self.names)}
        self.codes = encoded.indices.to_numpy().astype(np.int64)
        self.x = as_numpy(tracks.column("x")).astype(np.float64)
        self.y = as_numpy(tracks.column("y")).astype(np.float64)
        self.ts = as_numpy(tracks.column("timestamp_ns")).astype(np.int64)
        type_code = {t: i for i, t in enumerate(OBJECT_TYPES)}
        types = pc.dictionary_encode(tracks.column("object_type")).combine_chunks()
        lookup = np.array([type_code[t] for t in types.dictionary.to_pylist()], np.int64)
        self.types = lookup[types.indices.to_numpy()] if len(lookup) else np.zeros(0, np.int64)
        self.ego = as_numpy(pc.equal(tracks.column("role"), Role.EGO.value)).astype(bool)
