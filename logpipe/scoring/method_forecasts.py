"""One method's forecasts as ``logpipe score`` reads them: a ``logpipe predict`` output folder or a predictions
file as dense arrays (``MethodForecasts``, positions in metres in the world frame), the label each method gets
in a report (``name_methods``), and the check that it was predicted under the dataset's protocol
(``check_protocol``).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from logpipe.dataset.reader import Dataset
from logpipe.errors import ScoreError
from logpipe.prediction.runs import PredictionMeta, PredictionRun
from logpipe.types import NDArrayFloat


@dataclass
class MethodForecasts:
    """One method's forecasts (one prediction run folder or predictions file), as dense arrays.

    Attributes:
        name: label in reports (the predictor unless relabelled or colliding).
        predictor: the metadata's predictor.
        checkpoint_ids: distinct ``checkpoint_id`` values.
        source: the folder or file.
        run_name: the folder's name or the file's stem (the label when predictor names collide).
        meta: what the forecasts were made with (protocol, K, horizon, seed, ...).
        sample_ids: (N,) sample of each agent row.
        track_ids: (N,) track of each agent row.
        object_types: (N,) normalised class of each agent row.
        pred: (N, K, T, 2) metres, world frame; mode 0 the most likely.
    """

    name: str
    predictor: str
    checkpoint_ids: list[str]
    source: str
    run_name: str
    meta: PredictionMeta
    sample_ids: Any
    track_ids: Any
    object_types: Any
    pred: NDArrayFloat

    @property
    def num_modes(self) -> int:
        """K."""
        return int(self.pred.shape[1])


def load_method(path: Path) -> MethodForecasts:
    """Read one method: a ``logpipe predict`` output folder (its committed predictions) or a predictions file.

    Raises:
        PredictionsError: missing, damaged, not a prediction run, or not one row per (agent, mode) with the
            metadata's K and lists of its T steps (version 1 tables: one row per (agent, mode, step)).
    """
    run = PredictionRun.open(Path(path))
    dense = run.dense()
    return MethodForecasts(
        name=run.meta.predictor, predictor=run.meta.predictor, checkpoint_ids=dense.checkpoint_ids,
        source=str(path), run_name=run.name, meta=run.meta, sample_ids=dense.sample_ids, track_ids=dense.track_ids,
        object_types=dense.object_types, pred=dense.pred,
    )


def name_methods(methods: list[MethodForecasts], labels: Sequence[str] | None) -> None:
    """Labels given, else the predictor; methods whose predictors collide (two checkpoints of one method) are
    named by their folder or file, and ``#N`` is added where even those collide."""
    if labels:
        if len(labels) != len(methods):
            raise ScoreError(f"{len(labels)} labels for {len(methods)} methods (one per predictions folder or "
                             f"file: {', '.join(m.source for m in methods)})")
        for m, label in zip(methods, labels, strict=True):
            m.name = label
    else:
        counts: dict[str, int] = {}
        for m in methods:
            counts[m.name] = counts.get(m.name, 0) + 1
        for m in methods:
            if counts[m.name] > 1:
                m.name = m.run_name
    seen: dict[str, int] = {}
    for m in methods:
        if m.name in seen:
            seen[m.name] += 1
            m.name = f"{m.name}#{seen[m.name]}"
        else:
            seen[m.name] = 1


def check_protocol(methods: Sequence[MethodForecasts], ds: Dataset) -> None:
    """Every method was predicted under the dataset's protocol (name, observed and predicted steps)."""
    p = ds.protocol
    for m in methods:
        meta = m.meta
        wrong = []
        if meta.protocol is not None and meta.protocol != p.name:
            wrong.append(f"protocol {meta.protocol!r}, the dataset's is {p.name!r}")
        if meta.obs_len and meta.obs_len != p.obs_len:
            wrong.append(f"{meta.obs_len} observed steps, the dataset's protocol {p.obs_len}")
        if meta.pred_len != p.pred_len:
            wrong.append(f"horizon {meta.pred_len} steps, the dataset's protocol {p.pred_len}")
        if wrong:
            raise ScoreError(f"{m.source}: predicted with " + "; ".join(wrong) + f" ({ds.root})")
