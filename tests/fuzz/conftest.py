"""The full damaged-input corpus (marker ``fuzz``) runs only when asked for (``make fuzz``: ``-m fuzz``)."""

from __future__ import annotations

import pytest


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """Deselect ``fuzz``-marked items unless the ``-m`` expression names the marker (the fast subset stays)."""
    if "fuzz" in (config.option.markexpr or ""):
        return
    kept = [item for item in items if item.get_closest_marker("fuzz") is None]
    if len(kept) < len(items):
        config.hook.pytest_deselected(items=[i for i in items if i.get_closest_marker("fuzz") is not None])
        items[:] = kept
