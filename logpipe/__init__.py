"""logpipe: an offline pipeline for multi-agent trajectory forecasting (ingest, rasterise, train, predict, score)."""

# The one place the version is written (pyproject.toml reads it from here): importlib.metadata would cost
# ~60 ms of start-up in every process, pool workers' server included.
__version__ = "0.1.0"

__all__ = ["__version__"]
