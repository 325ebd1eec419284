"""The ``logpipe`` command: a thin Typer layer over the stage functions (``logpipe.api``).

Every command prints a human summary, or with ``--json`` one JSON object on stdout (for CI). Errors that
concern the user's input print one line naming file, line/record and field, and exit with code 2.

``main`` is the console-script entry point (``python -m logpipe.cli`` runs it too): it spares the command
pyarrow's probe for pandas, then runs ``app``. ``app`` holds the Typer app, the global options and what every
command shares; the commands are in ``data`` (ingest, index, rasterise), ``models`` (train, predict) and ``checks``
(score, verify, inspect, export), registered below in the order ``logpipe --help`` lists them.
"""

from __future__ import annotations

from logpipe.cli.app import app
from logpipe.cli.checks import export, inspect, score, verify
from logpipe.cli.data import index, ingest, rasterise
from logpipe.cli.models import predict, train
from logpipe.executor import skip_pyarrow_pandas_probe

__all__ = ["app", "main"]

for _command in (ingest, index, rasterise, train, predict, score, verify, inspect, export):
    app.command()(_command)


def main() -> None:
    """The ``logpipe`` command."""
    skip_pyarrow_pandas_probe()
    app()
