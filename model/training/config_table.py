"""A family's settings as a frozen dataclass read from a TOML table: the table of a config file, merged over a
preset, every key known and every value of its field's type (an int where a float is expected is accepted)."""

from __future__ import annotations

import dataclasses
import tomllib
from pathlib import Path
from typing import Any, TypeVar

from logpipe.errors import LogpipeError

T = TypeVar("T")


@dataclasses.dataclass(frozen=True)
class WindowSchedule:
    """The schedule every window-trained family shares (subclasses add their network's settings and may give
    ``batch_size`` another default): steps, validation every ``val_every`` steps on ``val_windows`` windows, early
    stop after ``patience`` validations without progress or after ``time_budget_s`` seconds (0: none), the seed and
    the protocol's observed and predicted steps."""

    batch_size: int = 64
    steps: int = 20000
    val_every: int = 250
    val_windows: int = 400
    patience: int = 8
    time_budget_s: float = 0.0
    seed: int = 0
    obs_len: int = 8
    pred_len: int = 12

    def to_dict(self) -> dict[str, Any]:
        """The ``config`` block of ``meta.json`` (and the TOML table's keys)."""
        return dataclasses.asdict(self)


def read_table(config_path: Path | None, table: str) -> dict[str, Any]:
    """The ``[table]`` of a TOML file (empty without a file or without the table)."""
    if config_path is None:
        return {}
    try:
        data = tomllib.loads(config_path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError) as exc:
        raise LogpipeError(f"{config_path}: unreadable config: {exc}") from None
    found = data.get(table, {})
    if not isinstance(found, dict):
        raise LogpipeError(f"{config_path}: [{table}] is not a table")
    return found


def typed_config(cls: type[T], data: dict[str, Any], where: str, label: str) -> T:
    """``cls(**data)`` with each value checked against its field's default's type.

    Raises:
        LogpipeError: an unknown key or a value of the wrong type, naming ``where`` and the key.
    """
    defaults = cls()
    names = {f.name for f in dataclasses.fields(defaults)}  # type: ignore[arg-type]
    unknown = sorted(set(data) - names)
    if unknown:
        raise LogpipeError(f"{where}: unknown {label} setting(s) {unknown}")
    values: dict[str, Any] = {}
    for name, raw in data.items():
        kind = type(getattr(defaults, name))
        number = kind is float and isinstance(raw, int) and not isinstance(raw, bool)
        given = float(raw) if number else raw  # TOML writes 1 for 1.0
        if not isinstance(given, kind) or (kind is not bool and isinstance(given, bool)):
            raise LogpipeError(f"{where}: {label} setting {name} must be {kind.__name__}, got {given!r}")
        values[name] = given
    return cls(**values)
