"""The ``logpipe`` command: a thin Typer layer over the stage functions (``logpipe.api``).

Every command prints a human summary, or with ``--json`` one JSON object on stdout (for CI). Errors that
concern the user's input print one line naming file, line/record and field, and exit with code 2.

``app`` holds the Typer app, the global options and what every command shares; the commands are in ``data``
(ingest, index, rasterise), ``models`` (train, predict) and ``checks`` (score, verify, inspect, export), registered
below in the order ``logpipe --help`` lists them. ``logpipe.cli:app`` is the console-script entry point and
``python -m logpipe.cli`` runs it too.
"""

from __future__ import annotations

from logpipe.cli.app import app
from logpipe.cli.checks import export, inspect, score, verify
from logpipe.cli.data import index, ingest, rasterise
from logpipe.cli.models import predict, train

__all__ = ["app"]

for _command in (ingest, index, rasterise, train, predict, score, verify, inspect, export):
    app.command()(_command)
