"""``docs/results/README.md`` lists every results file: each file and folder of ``docs/results/`` is named there
(a ``.json`` beside a listed ``.md`` of the same name counts as listed, as the index writes them "(+ `.json`)")."""

from __future__ import annotations

from pathlib import Path

RESULTS = Path(__file__).resolve().parents[1] / "docs" / "results"


def test_the_results_index_names_every_results_file() -> None:
    index = (RESULTS / "README.md").read_text()
    unlisted = [entry.name for entry in sorted(RESULTS.iterdir()) if entry.name != "README.md"
                and f"`{entry.name}" not in index and f"{entry.name}/" not in index
                and not (entry.suffix == ".json" and f"`{entry.with_suffix('.md').name}`" in index)]
    assert unlisted == []
