"""logpipe: an offline pipeline for multi-agent trajectory forecasting (ingest, rasterise, train, predict, score).

The commands are also Python functions (``logpipe.api``): ``logpipe.ingest(...)``, ``logpipe.index``,
``logpipe.rasterise``, ``logpipe.train``, ``logpipe.predict``, ``logpipe.score``.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

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
