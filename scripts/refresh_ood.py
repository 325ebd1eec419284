"""Bring a residual checkpoint's ``ood`` record up to the current code without retraining: recompute, on the very
training targets it was trained on, what the record gained since (the training windows per location and the kinematic
baselines chosen on those targets: ``baselines``, ``fallback_k1``, ``fallback_kalman``); every other field and the
weights stay as they are. The datasets must hold exactly the recordings the checkpoint names as its training data
(checked by sha256), so the record cannot describe other data::

    python -m scripts.refresh_ood model/checkpoints/argoverse/residual out/driving_lolo/data/av1 \\
        out/driving_lolo/data/av2 out/driving_lolo/data/ngsim --train-split hash/train

(``python -m scripts.driving_lolo`` and ``make train-driving`` build those datasets alike.)
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import replace
from pathlib import Path
from typing import Any

from logpipe.dataset.locations import window_locations
from logpipe.dataset.reader import Dataset
from logpipe.model.checkpoint.format import TrainingData
from logpipe.model.residual.checkpoint import load_residual
from logpipe.model.residual.fit import collect
from logpipe.model.residual.meta import META
from logpipe.model.residual.ood import tune_baselines
from logpipe.model.training.splits import logs_filter, split_logs
from logpipe.storage.io import atomic_open


def refresh(checkpoint: Path, datasets: list[Dataset], train_split: str) -> dict[str, Any]:
    """Rewrite ``checkpoint``'s ``meta.json`` with the record's new fields; returns them."""
    _, meta = load_residual(checkpoint)
    logs = split_logs(datasets, train_split)
    found = TrainingData.of_logs([(ds, ids, []) for ds, ids in zip(datasets, logs, strict=True)], train_split, None)
    if meta.training_data is None or set(found.train_sources) != set(meta.training_data.train_sources):
        raise SystemExit(f"{checkpoint}: these datasets' {train_split} is not the checkpoint's training data")
    samples = [s for ds, ids in zip(datasets, logs, strict=True) if ids
               for s in ds.iter_scene_samples(logs_filter(ids))]
    inputs, _ = collect(samples, replace(meta.config, environment=False))  # the record reads no map crop
    if len(inputs) != meta.ood.get("targets"):
        raise SystemExit(f"{checkpoint}: {len(inputs)} training targets here, {meta.ood.get('targets')} recorded")
    added: dict[str, Any] = tune_baselines(inputs, seed=meta.config.seed) | {
        "locations": window_locations([ds.logs() for ds in datasets], [s.log_id for s in samples])}
    fresh = replace(meta, ood=meta.ood | added)  # the weights, their sha256, version and date as they were
    with atomic_open(checkpoint / META, "w") as out:
        out.write(json.dumps(fresh.to_dict(), indent=2, sort_keys=True) + "\n")
    load_residual(checkpoint)  # the checksum and weights still agree
    return added


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("checkpoint", type=Path)
    ap.add_argument("datasets", type=Path, nargs="+")
    ap.add_argument("--train-split", default="hash/train")
    args = ap.parse_args(argv)
    added = refresh(args.checkpoint, [Dataset.open(p) for p in args.datasets], args.train_split)
    print(added, file=sys.stderr)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
