"""Shared fixtures: where the bundled samples and the real data of ../shared/data are."""

from __future__ import annotations

from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
BUNDLED = REPO / "tests" / "data"
SHARED = (REPO.parent / "shared" / "data").resolve()


@pytest.fixture(scope="session")
def bundled() -> Path:
    """``tests/data``: small real samples shipped with the repo."""
    return BUNDLED


@pytest.fixture(scope="session")
def shared() -> Path:
    """``../shared/data``: the full real data (present on developer machines and in CI)."""
    if not SHARED.is_dir():
        pytest.skip(f"real data folder {SHARED} is absent (CI and developer machines have it)")
    return SHARED
