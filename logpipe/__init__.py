"""logpipe: an offline pipeline for multi-agent trajectory forecasting (ingest, rasterise, train, predict, score).

The commands are also Python functions (``logpipe.api``): ``logpipe.ingest(...)``, ``logpipe.index``,
``logpipe.rasterise``, ``logpipe.train``, ``logpipe.predict``, ``logpipe.score``.
"""

from __future__ import annotations

import os
from typing import TYPE_CHECKING, Any

# OpenMP threads that sleep at a barrier instead of spinning, set before torch loads its OpenMP (read once, at
# load; a value the user set wins). With spinning threads, training on 2 threads while another job shared the 2
# cores ran 6-20x slower than with sleeping ones (0.5-0.8 against 6-15 samples/s, benchmarks/bench_train.py).
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

# The one place the version is written (pyproject.toml reads it from here): importlib.metadata would cost
# ~60 ms of start-up in every process, pool workers' server included.
__version__ = "0.1.0"

if TYPE_CHECKING:
    from logpipe.api import index, ingest, predict, rasterise, score, train

# Loaded on first use: ``import logpipe`` (every pool worker does) must not import the API, which the stages
# follow. ``verify`` and ``inspect`` stay in ``logpipe.api``: modules of this package have those names.
_API = ("ingest", "index", "rasterise", "train", "predict", "score")

__all__ = ["__version__", "index", "ingest", "predict", "rasterise", "score", "train"]


def __getattr__(name: str) -> Any:
    if name in _API:
        from logpipe import api

        return getattr(api, name)
    raise AttributeError(f"module 'logpipe' has no attribute {name!r}")
