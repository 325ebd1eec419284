"""Why ``predict`` without ``--checkpoint`` / ``--predictor`` uses what it uses, in one phrase for its summary.

Every dataset kind gets a default that runs: the shipped model of its kind (the driving model for the Argoverse
formats and CommonRoad, whose tracks are vehicles on lane maps; one of the ETH/UCY or ApolloScape models), and for
a kind no shipped model serves (ROS bags, MCAP) the best kinematic baseline (``model.registry.DEFAULT_BASELINE``).
The phrase says what the dataset's tracks are, so a user sees why the driving model was not the one.
"""

from __future__ import annotations

from pathlib import Path

import pyarrow.compute as pc

from logpipe.dataset.reader import Dataset
from logpipe.storage.io import read_table

ROAD_VEHICLES = frozenset({"vehicle", "bus_truck", "motorcyclist"})
"""Object types the driving model is trained on."""


def track_types(dataset: Dataset) -> list[str]:
    """The object types of the dataset's tracks, sorted (one column read per shard)."""
    seen: set[str] = set()
    for path in dataset.shard_paths:
        column = read_table(path, columns=["object_type"]).column(0)
        seen |= {str(t) for t in pc.unique(column).to_pylist() if t is not None}
    return sorted(seen)


def kinematic_reason(dataset: Dataset) -> str:
    """Why a dataset of a kind without a shipped model gets the default kinematic baseline: its kind, its tracks'
    types, whether its logs name a map."""
    types = track_types(dataset)
    vehicles = bool(types) and set(types) <= ROAD_VEHICLES
    mapped = any(m for m in dataset.logs().column("map_id").to_pylist())
    kinds = "road vehicles" if vehicles else f"{' and '.join(types)} agents" if types else "none"
    what = f"{kinds}, {'on a map' if mapped else 'no map'}"
    return (f"the kinematic baseline with the lowest K=1 FDE in docs/results, as no shipped model serves dataset "
            f"kind {dataset.kind!r} (its tracks: {what}; the driving model reads Argoverse and CommonRoad datasets)")


def checkpoint_reason(dataset: Dataset, checkpoint: Path, driving: bool) -> str:
    """Why a dataset gets the shipped checkpoint ``checkpoint`` of its kind."""
    if driving:
        return (f"the driving model, shipped for dataset kind {dataset.kind!r} (its tracks are vehicles on lane "
                "maps)")
    return f"the shipped model for dataset kind {dataset.kind!r} ({checkpoint.parent.name}/{checkpoint.name})"
