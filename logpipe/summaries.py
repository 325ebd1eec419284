"""The summaries the API returns and ``--json`` prints, as typed records: ``logpipe.api`` functions return
them; the keys are the JSON's."""

from __future__ import annotations

from typing import Any, NotRequired, TypedDict


class IngestSummary(TypedDict):
    """What ``ingest`` returns (``logpipe ingest --json``). Counts are of this run unless under ``totals``.

    ``inputs_found`` counts distinct inputs: ``duplicates`` more files were identical copies of one of them
    (listed in ``duplicate_inputs`` as ``{"path", "same_as"}``, relative paths) and were ingested once, as
    that input (their folders are added to its memberships). ``logs_without_samples`` counts the logs that
    give no prediction sample, by reason (e.g. ``"too short for 8+12 steps"``).
    """

    dataset: str
    format: str
    protocol: dict[str, Any]
    inputs_found: int
    inputs_skipped_already_ingested: int
    inputs_ingested: int
    duplicates: int
    duplicate_inputs: list[dict[str, str]]
    quarantined: list[dict[str, Any]]
    logs: int
    rows: int
    samples: int
    logs_without_samples: dict[str, int]
    shards_written: list[str]
    mcap_messages: NotRequired[int]
    seconds: float
    totals: dict[str, int]


class IndexSummary(TypedDict):
    """What ``index`` returns (``logpipe index --json``); ``unchanged`` when the protocol was the dataset's
    already (then nothing was recounted, and ``logs_without_samples`` is absent)."""

    dataset: str
    protocol: dict[str, Any]
    samples: int
    logs_without_samples: NotRequired[dict[str, int]]
    unchanged: NotRequired[bool]


class VerifyReport(TypedDict):
    """What ``verify`` returns: the folders checked, how many files, one line per problem, leftover paths."""

    folders: list[str]
    files_checked: int
    problems: list[str]
    leftovers: list[str]
