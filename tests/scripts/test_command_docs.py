"""docs/commands/*.md are what the commands' ``--help`` prints now (one page per command, none missing)."""

from __future__ import annotations

from pathlib import Path

from scripts.command_docs import DOCS, main, pages


def test_every_command_has_a_current_page() -> None:
    assert main(["--check"]) == 0, "run python -m scripts.command_docs"
    names = set(pages())
    assert {"ingest", "index", "rasterise", "train", "predict", "score", "verify", "inspect", "export"} <= names
    assert {p.stem for p in Path(DOCS).glob("*.md")} == names


def test_a_stale_page_is_named(tmp_path: Path) -> None:
    assert main(["--out", str(tmp_path)]) == 0
    (tmp_path / "score.md").write_text("old help\n")
    assert main(["--check", "--out", str(tmp_path)]) == 1
