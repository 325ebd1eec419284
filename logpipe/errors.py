"""Errors that name where the bad input is: file, line/record and field."""

from __future__ import annotations

from typing import Any


class LogpipeError(Exception):
    """Base class of every error logpipe reports to a user (the CLI prints these without a traceback)."""


class SourceError(LogpipeError):
    """An input file is unreadable or violates its format.

    Attributes:
        file: the file (relative to the ingest root where known).
        reason: what is wrong, in words.
        line: 1-based line number (text formats) or record/message index, when known.
        field: the column, topic or field concerned, when known.
    """

    def __init__(self, file: str, reason: str, *, line: int | None = None, field: str | None = None) -> None:
        self.file = file
        self.reason = reason
        self.line = line
        self.field = field
        super().__init__(self.describe())

    def __reduce__(self) -> tuple[object, ...]:
        # Keyword-only fields: rebuild explicitly so the error survives pickling across worker processes.
        return (_rebuild_source_error, (self.file, self.reason, self.line, self.field))

    def describe(self) -> str:
        """``file:line: field 'f': reason`` with the parts that are known."""
        where = self.file
        if self.line is not None:
            where += f":{self.line}"
        what = f"field '{self.field}': " if self.field else ""
        return f"{where}: {what}{self.reason}"

    def to_dict(self) -> dict[str, object]:
        """Plain dict for manifests and ``--json`` summaries."""
        return {"file": self.file, "line": self.line, "field": self.field, "reason": self.reason}


def _rebuild_source_error(file: str, reason: str, line: int | None, field: str | None) -> SourceError:
    return SourceError(file, reason, line=line, field=field)


class DatasetError(LogpipeError):
    """A dataset folder is missing, incomplete or was written with incompatible settings."""


class QuarantineLimitError(LogpipeError):
    """An ``--on-error skip`` ingest committed, but quarantined every new input or more than
    ``--max-quarantined``: a job that relies on its dataset must not pass. ``summary`` is the run's summary."""

    def __init__(self, message: str, summary: dict[str, Any]) -> None:
        super().__init__(message)
        self.summary = summary


class ArtifactBusyError(LogpipeError):
    """Another process holds the write lock of an output folder."""


class OutputError(LogpipeError):
    """Writing an output failed at the operating-system level (disk full, read-only, permissions); the folder
    keeps its last committed state."""


class ScoreError(LogpipeError):
    """Predictions and truth cannot be scored together (bad table, missing agents, unknown metric)."""
