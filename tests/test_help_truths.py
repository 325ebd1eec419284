"""What the help and the README say is true: the top-level ``--help`` never cuts a command's first sentence at an
abbreviation ("Train the Zhu et al."), examples use paths a fresh clone has (not ``../shared/data``) and run, the
mapping file is documented where ``ingest --help`` says, and the extra the README names installs what its query
examples import."""

from __future__ import annotations

import re
import shlex
import tomllib
from pathlib import Path
from typing import Any

import pytest
import typer
from typer.testing import CliRunner

from logpipe.cli import app

REPO = Path(__file__).resolve().parents[1]
runner = CliRunner()


def _commands() -> dict[str, Any]:
    return dict(typer.main.get_command(app).commands)  # type: ignore[attr-defined]


def test_top_level_help_keeps_each_first_sentence_whole_or_marks_the_cut() -> None:
    """A short help that does not end in "..." must be the command's whole first paragraph."""
    for name, command in _commands().items():
        short = command.get_short_help_str(45)
        first = " ".join((command.help or "").partition("\n\n")[0].split())
        assert short.endswith("...") or short == first, f"{name}: {short!r} cuts {first!r}"
    train = _commands()["train"].get_short_help_str(200)
    assert "Zhu et al., IJCAI 2020" in train


def _examples() -> list[str]:
    return [line.split("Example:", 1)[1].strip() for c in _commands().values()
            for line in (c.help or "").splitlines() if "Example:" in line]


def test_help_examples_point_at_the_clone_not_at_shared_data() -> None:
    examples = _examples()
    assert len(examples) >= 8
    assert not [e for e in examples if "../shared" in e]
    paths = [w for e in examples for w in shlex.split(e) if w.startswith("tests/data")]
    assert paths and all((REPO / p).exists() for p in paths)


@pytest.mark.parametrize("example", [e for e in _examples() if e.startswith(("logpipe ingest tests/data",
                                                                              "logpipe inspect tests/data"))])
def test_help_examples_on_bundled_data_run(example: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(tmp_path)
    (tmp_path / "tests").symlink_to(REPO / "tests")
    result = runner.invoke(app, shlex.split(example)[1:])
    assert result.exit_code == 0, result.output


def test_the_mapping_file_is_documented_where_ingest_help_says() -> None:
    option = next(p for p in _commands()["ingest"].params if p.name == "mapping")
    assert "docs/guide.md, 'Bags and MCAP: the mapping'" in (option.help or "").replace("\n", " ")
    guide = (REPO / "docs" / "guide.md").read_text()
    section = guide.split("### Bags and MCAP: the mapping", 1)[1].split("\n## ", 1)[0]
    assert "--mapping" in section and "TOML or YAML" in section


def test_the_readme_names_an_extra_that_installs_what_its_query_examples_import() -> None:
    readme = (REPO / "README.md").read_text()
    blocks = re.findall(r"```python\n(.*?)```", readme, re.S)
    imported = {m for b in blocks for m in re.findall(r"^import (\w+)", b, re.M)} - {"logpipe"}
    assert imported >= {"duckdb", "polars"}
    assert "pip install -e '.[query]'" in readme
    extras = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]["optional-dependencies"]
    assert {re.split(r"[<>=\[]", r)[0] for r in extras["query"]} == imported
    assert {re.split(r"[<>=\[]", r)[0] for r in extras["dev"]} >= imported
