"""logpipe: an offline pipeline for multi-agent trajectory forecasting (ingest, rasterise, train, predict, score)."""

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("logpipe")
except PackageNotFoundError:  # running from a source tree without an install
    __version__ = "0.0.0+local"

__all__ = ["__version__"]
