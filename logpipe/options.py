"""Command options as ``logpipe.api`` takes them (CLI strings or Python values) → the values the stages take:
paths, choices, comma-separated names, ``KEY=VALUE`` pairs, the sample protocol of the protocol flags and the
input adapters' options. Each raises ``LogpipeError`` naming the CLI option, as the command reports it.

Importing this module is cheap (``logpipe.api``'s promise): what it needs beyond the errors is imported lazily.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Mapping, Sequence
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

from logpipe.errors import LogpipeError

if TYPE_CHECKING:
    from logpipe.types import SampleProtocol

StrPath = str | os.PathLike[str]
"""A path given as ``str`` or ``pathlib.Path``."""


def as_path(value: StrPath) -> Path:
    """``value`` as a ``Path``."""
    return Path(os.fspath(value))


def optional_path(value: StrPath | None) -> Path | None:
    """``value`` as a ``Path``; None when not given."""
    return as_path(value) if value is not None else None


def as_paths(values: StrPath | Sequence[StrPath] | None) -> list[Path]:
    """One path or several (a lone ``str`` is one path, not a sequence of characters)."""
    if values is None:
        return []
    if isinstance(values, str | os.PathLike):
        return [as_path(values)]
    return [as_path(v) for v in values]


def check_choice(option: str, value: str, allowed: Sequence[str]) -> None:
    """Refuse a ``value`` of ``option`` that is not one of ``allowed``."""
    if value not in allowed:
        raise LogpipeError(f"{option} must be {' or '.join(allowed)}, got {value!r}")


def names(value: str | Sequence[str] | None) -> tuple[str, ...] | None:
    """Comma-separated names (``"vehicle,bus_truck"``) or a sequence of them; None when not given."""
    if value is None:
        return None
    parts = value.split(",") if isinstance(value, str) else list(value)
    return tuple(p.strip() for p in parts if p.strip())


def _key_values(items: Sequence[str] | None, error: Callable[[str], str]) -> list[tuple[str, str]]:
    """``KEY=VALUE`` option strings split at the first ``=``; ``error(item)`` is the message for one without."""
    pairs = []
    for item in items or ():
        key, sep, value = item.partition("=")
        if not sep:
            raise LogpipeError(error(item))
        pairs.append((key, value))
    return pairs


def map_files(map_file: Sequence[str] | Mapping[str, StrPath] | None) -> dict[str, Path]:
    """``rasterise``'s ``--map``: ``MAP_ID=FILE`` strings or ``{map_id: file}`` → map id → file."""
    if isinstance(map_file, Mapping):
        return {str(k): as_path(v) for k, v in map_file.items()}
    return {key: Path(value) for key, value in _key_values(map_file, _map_error)}


def gates(fail_above: Sequence[str] | Mapping[str, float] | None) -> dict[str, float]:
    """``score``'s ``--fail-above``: ``kN.METRIC=VALUE`` strings or ``{"k1.ade": 0.6}`` → metric → threshold."""
    if isinstance(fail_above, Mapping):
        return {str(key): float(value) for key, value in fail_above.items()}
    thresholds: dict[str, float] = {}
    for key, value in _key_values(fail_above, _gate_error):
        try:
            thresholds[key.strip()] = float(value)
        except ValueError:
            raise LogpipeError(_gate_error(f"{key}={value}")) from None
    return thresholds


def _map_error(item: str) -> str:
    return f"--map expects MAP_ID=FILE, got {item!r}"


def _gate_error(item: str) -> str:
    return f"--fail-above {item!r}: expected kN.METRIC=NUMBER"


def sample_protocol(  # noqa: PLR0913  keyword options mirror the CLI's protocol flags one to one
    preset: str | None = None, *, obs: int | None = None, pred: int | None = None,
    stride: int | None = None, min_targets: int | None = None, targets: str | None = None,
    target_types: str | Sequence[str] | None = None, window: str | None = None,
    default: SampleProtocol | None = None,
) -> SampleProtocol | None:
    """The protocol the ``--protocol/--obs/--pred/...`` options describe: ``preset`` (or ``default``) with the
    overrides; None when nothing is given. Overrides of a preset are named ``<preset>-custom``.

    Raises:
        LogpipeError: an unknown preset or ``window`` (``sliding`` or ``first``).
    """
    from logpipe.types import PROTOCOLS, WINDOWS, SampleProtocol

    types = names(target_types)
    if window is not None:
        check_choice("--window", window, WINDOWS)
    if preset is None and all(v is None for v in (obs, pred, stride, min_targets, targets, types, window)):
        return None
    if preset is not None and preset not in PROTOCOLS:
        raise LogpipeError(f"unknown protocol {preset!r}; presets: {', '.join(PROTOCOLS)}")
    base = PROTOCOLS[preset] if preset else default
    if base is None:
        base = SampleProtocol("custom", obs_len=obs or 8, pred_len=pred or 12)
    changes: dict[str, Any] = {}
    for key, value in (("obs_len", obs), ("pred_len", pred), ("stride", stride), ("min_targets", min_targets),
                       ("targets", targets), ("target_types", types), ("window", window)):
        if value is not None:
            changes[key] = value
    if changes and base.name != "custom":
        changes["name"] = f"{base.name.removesuffix('-custom')}-custom"
    return replace(base, **changes)


def adapter_options(mapping: StrPath | None, overrides: Sequence[str], hz: float | None,
                    allow_empty: bool) -> dict[str, Any]:
    """``ingest``'s options for the input adapters (bags/MCAP/AV2): only the options the user gave, so formats
    that do not take them are not handed them."""
    options: dict[str, Any] = {}
    if mapping is not None:
        options["mapping"] = os.fspath(mapping)
    if overrides:
        options["mapping_overrides"] = tuple(overrides)
    if hz is not None:
        options["hz"] = hz
    if allow_empty:
        options["allow_empty"] = True
    return options
