"""README.md runs as written: every code block, in order, as one bash script in a fresh folder that holds the
repository's files (linked, as a clone would have them) but none of its outputs, with the bundled data only.

How each block is treated: ``bash`` blocks run verbatim, except that ``make test`` (this suite itself) runs as
``make -n test`` (the target exists and what it would run is valid) instead of recursing; ``python`` blocks run
with the venv's python (after the README's own ``source .venv/bin/activate``). A block in any other language fails
the test: the README shows only what runs."""

from __future__ import annotations

import os
import re
import subprocess
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
README = REPO / "README.md"
FENCE = re.compile(r"^```(\w*)\n(.*?)^```$", re.S | re.M)
NOT_LINKED = {".git", "out", ".pytest_cache", ".mypy_cache", ".ruff_cache"}
"""What a fresh clone lacks (outputs, caches) or what must not be shared with the working tree (git)."""


def readme_blocks() -> list[tuple[str, str]]:
    """(language, code) of every fenced block of README.md, in order."""
    return FENCE.findall(README.read_text())


def readme_script(blocks: list[tuple[str, str]]) -> str:
    """The blocks as one bash script (see the module docstring for how each is treated)."""
    parts = ["set -euo pipefail"]
    for language, code in blocks:
        if language == "bash":
            parts.append(re.sub(r"^make test\b", "make -n test > /dev/null", code, flags=re.M))
        elif language == "python":
            parts.append(f"python - <<'README_PYTHON'\n{code}README_PYTHON")
        else:
            raise AssertionError(f"README.md has a ```{language} block, which no test runs")
    return "\n".join(parts) + "\n"


def test_the_front_page_is_short_and_shows_a_forecast() -> None:
    lines = README.read_text().splitlines()
    assert len(lines) <= 125
    assert "![" in lines[5] or any(line.startswith("![") for line in lines[:10])
    assert (REPO / "docs" / "images" / "forecast.png").stat().st_size > 10_000
    assert [lang for lang, _ in readme_blocks()].count("bash") >= 3


def test_make_test_is_the_only_command_the_readme_test_does_not_run_as_written() -> None:
    script = readme_script(readme_blocks())
    assert script.count("make -n test") == 1
    assert "make demo" in script and "logpipe score" in script and "logpipe export" in script


@pytest.mark.slow
def test_every_readme_block_runs_in_order_in_a_fresh_folder(tmp_path: Path) -> None:
    work = tmp_path / "clone"
    work.mkdir()
    for entry in REPO.iterdir():
        if entry.name not in NOT_LINKED:
            (work / entry.name).symlink_to(entry)
    (work / "readme.sh").write_text(readme_script(readme_blocks()))
    env = {k: v for k, v in os.environ.items() if k not in ("VIRTUAL_ENV", "MAKEFLAGS", "MAKELEVEL")}
    result = subprocess.run(["bash", "readme.sh"], cwd=work, capture_output=True, text=True, timeout=900, env=env,
                            check=False)
    output = result.stdout + result.stderr
    assert result.returncode == 0, output[-4000:]
    out = work / "out"
    # make demo ends by naming what to open, and it is there
    assert "demo done" in output and (out / "demo" / "forecast.png").is_file()
    assert (out / "demo" / "predict-argoverse1" / "mcap" / "part-00000" / "20.mcap").is_file()
    # the quickstart: a scored forecast, an MCAP and a Rerun recording; each summary named the next step
    assert (out / "av1-score" / "report.md").is_file() and (out / "av1-rrd" / "20.rrd").is_file()
    assert "next: logpipe predict out/av1 --out out/av1-pred" in output
    # your own data, the Python API and the queries
    assert (out / "mine-score" / "report.md").is_file() and (out / "api-cv-score" / "report.md").is_file()
    assert "constant velocity ADE (m):" in output and "fde_m" in output and "MIA" in output
