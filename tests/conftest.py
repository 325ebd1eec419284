"""Shared fixtures: where the bundled samples and the real data of ../shared/data are."""

from __future__ import annotations

import hashlib
import os
from collections.abc import Callable
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


@pytest.fixture(scope="session")
def driving_rasterised(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The two bundled AV1 sequences (``driving/20.csv``, ``32.csv``) ingested and rasterised (ego-rotated) from
    their bundled lane crops: a dataset the shipped driving model predicts over rasters. Read-only for tests."""
    from logpipe.maps import MapSource
    from logpipe.stages.ingest import IngestOptions, ingest
    from logpipe.stages.rasterise import rasterise_dataset

    data = tmp_path_factory.mktemp("driving") / "av1"
    driving = BUNDLED / "driving"
    ingest([driving / "20.csv", driving / "32.csv"], IngestOptions(out=data))
    maps = MapSource(files={"MIA": driving / "MIA_lane_centerlines_crop_20.npz",
                            "PIT": driving / "PIT_lane_centerlines_crop_32.npz"})
    rasterise_dataset(data, maps, rotate=True)
    return data


def _folder_digests(out: Path) -> dict[str, str]:
    return {p.relative_to(out).as_posix(): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(out.rglob("*")) if p.is_file() and p.name != ".lock"}


@pytest.fixture(scope="session")
def folder_digests() -> Callable[[Path], dict[str, str]]:
    """sha256 of every file of an output folder, by relative POSIX path (the manifest included, the lock file
    not): two runs wrote the same bytes when these are equal."""
    return _folder_digests


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """Start the README run (``tests/test_readme.py``) in the background when its test is selected: it takes
    about 1.5 minutes of one mostly idle core, which then overlaps the rest of the suite.

    Under pytest-xdist (``make test``) every worker collects every test but only one runs it: there the test goes
    first instead and starts the run itself, so one worker waits on it while the others work."""
    from tests.test_readme import RUN_TEST, start_readme_run

    if os.environ.get("PYTEST_XDIST_WORKER"):
        items.sort(key=lambda item: item.name != RUN_TEST)  # stable: the rest keep their order
    elif any(item.name == RUN_TEST for item in items):
        config.readme_run = start_readme_run()  # type: ignore[attr-defined]


def pytest_unconfigure(config: pytest.Config) -> None:
    run = getattr(config, "readme_run", None)
    if run is not None:
        run.stop()  # killed if a selection or an interrupt left it running; its folder removed
