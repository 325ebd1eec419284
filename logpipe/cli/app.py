"""The Typer app of the ``logpipe`` command and what every command shares: the global ``-q`` / ``-v`` options,
logging and progress on stderr, user errors as one line with exit code 2, ``--json`` output, and the option
types several commands take. The commands themselves are in the sibling modules (``logpipe.cli``)."""

from __future__ import annotations

import json
import logging
import os
import sys
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any, TextIO

import typer
from rich.console import Console
from rich.markup import escape

from logpipe import __version__
from logpipe.errors import LogpipeError
from logpipe.progress import Mode, ProgressReporter
from logpipe.types import PROTOCOLS

app = typer.Typer(
    name="logpipe",
    help="Offline pipeline for multi-agent trajectory forecasting: ingest → rasterise → train → predict → score.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
    # Rich help panels only on a terminal: piped (CI logs, `| less`) rich cuts option names to fit 80
    # columns (`--constant-velo…`); click's plain help wraps the text and never cuts a name.
    rich_markup_mode="rich" if sys.stdout.isatty() else None,
)
err = Console(stderr=True)


@dataclass
class _Output:
    """What the global ``-q`` / ``-v`` options chose (set by the app callback before every command)."""

    quiet: bool = False
    verbose: int = 0


output = _Output()


def _version(value: bool) -> None:
    if value:
        typer.echo(f"logpipe {__version__}")
        raise typer.Exit


@app.callback()
def main(
    version: Annotated[bool, typer.Option("--version", callback=_version, is_eager=True,
                                          help="Print the version and exit.")] = False,
    quiet: Annotated[bool, typer.Option(
        "--quiet", "-q", help="No progress and no human summary; errors and warnings are still shown.")] = False,
    verbose: Annotated[int, typer.Option(
        "--verbose", "-v", count=True, help="Also log details (per-batch timings); -vv for debug logging.")] = 0,
) -> None:
    """Offline pipeline for multi-agent trajectory forecasting.

    Progress goes to stderr: a bar on a terminal, elsewhere a time heartbeat, one line every 5 s
    (LOGPIPE_PROGRESS_INTERVAL seconds), and nothing with -q. stdout carries only --json output.
    """
    if quiet and verbose:
        raise typer.BadParameter("--quiet and --verbose exclude each other")
    output.quiet, output.verbose = quiet, verbose
    _configure_logging(logging.DEBUG if verbose > 1 else logging.INFO if verbose else logging.WARNING)


class _StderrHandler(logging.StreamHandler[TextIO]):
    """Writes to the current ``sys.stderr``: a progress bar redirects it to print above the bar."""

    def emit(self, record: logging.LogRecord) -> None:
        # Assigned, not ``setStream``: that flushes the previous stream, which may be closed by now (a test
        # runner's captured stderr from an earlier command in this process).
        self.stream = sys.stderr
        super().emit(record)


def _configure_logging(level: int) -> None:
    """logpipe's own loggers at ``level`` on stderr, one plain line per record (never wrapped)."""
    logger = logging.getLogger("logpipe")
    for handler in [h for h in logger.handlers if isinstance(h, _StderrHandler)]:
        logger.removeHandler(handler)  # one handler, however often the app runs in this process (tests)
    handler = _StderrHandler()
    handler.setFormatter(logging.Formatter("%(levelname)s %(name)s: %(message)s"))
    logger.addHandler(handler)
    logger.setLevel(level)


def progress_mode() -> Mode:
    """``off`` with -q; a bar when stderr is a terminal that can redraw; else plain lines (CI, pipes)."""
    if output.quiet:
        return "off"
    return "bar" if sys.stderr.isatty() and os.environ.get("TERM") != "dumb" else "lines"


@contextmanager
def user_errors(as_json: bool = False) -> Iterator[None]:
    """Turn logpipe's own errors into one clear line and exit code 2 (no traceback); with ``--json`` the error
    is also the one JSON object on stdout (``{"error": ..., "exit_code": 2}``), so a parser never meets text."""
    try:
        yield
    except LogpipeError as exc:
        _fail(str(exc), as_json)
    except OSError as exc:
        # Disk full, read-only or forbidden outputs: the writers commit only by the manifest swap, so the
        # folder still holds its previous state; one line, not a traceback.
        from logpipe.storage.artifact import os_error_message

        _fail(os_error_message(exc), as_json)
    except Exception as exc:
        if not type(exc).__module__.startswith("ray."):
            raise
        # A Ray system process killed or lost (LocalRayletDiedError, RaySystemError...): the run's committed
        # shards stay; one line saying so, not Ray's traceback.
        first = (str(exc).strip().splitlines() or [""])[0][:200]
        _fail(f"the Ray backend failed ({type(exc).__name__}: {first}); committed work is kept, run the "
              "command again (or use --backend local)", as_json)


def fail_after_summary(message: str) -> None:
    """Exit 2 with ``message`` as the error line, after ``emit`` printed the run's summary (with ``--json`` the
    summary's own ``error`` and ``exit_code`` say it: stdout keeps one JSON object)."""
    err.print(f"[bold red]error:[/] {escape(message)}", highlight=False, soft_wrap=True)
    raise typer.Exit(code=2)


def _fail(message: str, as_json: bool) -> None:
    err.print(f"[bold red]error:[/] {escape(message)}", highlight=False, soft_wrap=True)
    if as_json:
        typer.echo(json.dumps({"error": message, "exit_code": 2}))
    raise typer.Exit(code=2) from None


class WarningCount(logging.Handler):
    """Collects the warnings logpipe logs while a command runs, so its summary can count them."""

    def __init__(self) -> None:
        super().__init__(logging.WARNING)
        self.messages: list[str] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.messages.append(record.getMessage())


@contextmanager
def counting_warnings() -> Iterator[WarningCount]:
    """A ``WarningCount`` on logpipe's logger for the duration of the block."""
    handler = WarningCount()
    logger = logging.getLogger("logpipe")
    logger.addHandler(handler)
    try:
        yield handler
    finally:
        logger.removeHandler(handler)


def stage_progress(label: str, unit: str) -> ProgressReporter:
    """The progress callback of one stage run (the stage reports the total once it knows it). On stderr, so
    it runs with --json too: a CI job that parses stdout still shows progress in its log. The bar is redrawn
    by the reporter, not by rich's refresh thread: with no thread running, the stage's worker pool can fork
    from this process (see ``logpipe.executor``), ~0.4 s of a core less per run."""
    return ProgressReporter(label, unit, progress_mode(), console=err)


def emit(summary: dict[str, Any], as_json: bool, human: Callable[[dict[str, Any]], list[str]],
         logged: WarningCount | None = None) -> None:
    """Print a command's summary: ``--json``, one object on stdout; else (unless ``-q``) the few human lines
    ``human`` gives on stderr (what it did, where the outputs are, the command to run next), closed by the count of
    warnings (the summary's own ``warnings`` and those logged while it ran, also added to the JSON)."""
    warnings = list(summary.get("warnings") or [])
    warnings += [w for w in (logged.messages if logged else []) if w not in warnings]
    if warnings or "warnings" in summary:
        summary = {**summary, "warnings": warnings}
    if as_json:
        typer.echo(json.dumps(summary, indent=2, sort_keys=True, default=str))
        return
    if output.quiet:
        return
    lines = human(summary)
    if warnings:
        lines.append(f"{len(warnings)} warning{'s' if len(warnings) != 1 else ''} (shown above)")
    say(lines)


def say(lines: list[str]) -> None:
    """Human lines on stderr, never wrapped or cut (a path must stay one piece to be copied)."""
    for line in lines:
        typer.echo(line, err=True)


ProtocolOpt = Annotated[str | None, typer.Option("--protocol", help=f"Sample preset: {', '.join(PROTOCOLS)} "
                                                 "(default: the format's own).")]
ObsOpt = Annotated[int | None, typer.Option("--obs", help="Observed steps per sample (overrides the preset).")]
PredOpt = Annotated[int | None, typer.Option("--pred", help="Predicted steps per sample.")]
StrideOpt = Annotated[int | None, typer.Option("--stride", help="Steps between sliding windows.")]
MinTargetsOpt = Annotated[int | None, typer.Option(
    "--min-targets", help="Keep windows with at least this many fully observed agents (Social-GAN: 2).")]
TargetsOpt = Annotated[str | None, typer.Option(
    "--targets", help="fully_observed | fully_observed_no_ego (the ego's future is an input) | focal")]
TargetTypesOpt = Annotated[str | None, typer.Option(
    "--target-types", help="Only agents of these types are targets, comma-separated (vehicle,bus_truck).")]
WindowOpt = Annotated[str | None, typer.Option(
    "--window", help="sliding (a window every --stride steps) | first (one window at step 0, Argoverse).")]
JsonOpt = Annotated[bool, typer.Option("--json", help="Print a JSON summary on stdout (for CI).")]
DatasetArg = Annotated[Path, typer.Argument(help="Dataset folder written by `logpipe ingest`.")]


def next_step(command: str, why: str = "") -> str:
    """The summary's last line: the command to run next (quoted so it can be copied)."""
    return f"next: {command}" + (f"   ({why})" if why else "")
