"""README.md runs as written: every code block, in order, as one bash script in a fresh folder that holds the
repository's files (linked, as a clone would have them) but none of its outputs, with the bundled data only.

How each block is treated: ``bash`` blocks run verbatim, except that ``make test`` (this suite itself) runs as
``make -n test`` (the target exists and what it would run is valid) instead of recursing; ``python`` blocks run
with the venv's python (after the README's own ``source .venv/bin/activate``). A block in any other language fails
the test: the README shows only what runs.

The run takes about 1.5 minutes of one core, mostly single-threaded, so ``conftest.py`` starts it in the background
as soon as this test is collected (``start_readme_run``) and the test waits for it: it overlaps the rest of the
suite instead of adding to its wall time. Nothing else changes: same script, same fresh folder, same checks."""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import tempfile
from dataclasses import dataclass
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
README = REPO / "README.md"
FENCE = re.compile(r"^```(\w*)\n(.*?)^```$", re.S | re.M)
NOT_LINKED = {".git", "out", ".pytest_cache", ".mypy_cache", ".mypy-tree", ".ruff_cache"}
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


RUN_TEST = "test_every_readme_block_runs_in_order_in_a_fresh_folder"


@dataclass
class ReadmeRun:
    """The README script running in ``root/clone`` (its output in ``root/output.txt``)."""

    root: Path
    process: subprocess.Popen[bytes]

    @property
    def work(self) -> Path:
        return self.root / "clone"

    def wait(self, timeout: float) -> tuple[int, str]:
        """Its exit code and output, once it ends (killed after ``timeout`` seconds: -9)."""
        try:
            code = self.process.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            self.stop()
            code = -9
        return code, (self.root / "output.txt").read_text(errors="replace")

    def stop(self) -> None:
        """Kill it if it still runs (its whole process group: make, logpipe and their workers) and remove its
        folder."""
        if self.process.poll() is None:
            os.killpg(self.process.pid, 9)
            self.process.wait()
        shutil.rmtree(self.root, ignore_errors=True)


def start_readme_run() -> ReadmeRun:
    """Start the README script in a new folder linking the repository's files (as a clone has them)."""
    root = Path(tempfile.mkdtemp(prefix="logpipe-readme-"))
    work = root / "clone"
    work.mkdir()
    for entry in REPO.iterdir():
        if entry.name not in NOT_LINKED:
            (work / entry.name).symlink_to(entry)
    (work / "readme.sh").write_text(readme_script(readme_blocks()))
    env = {k: v for k, v in os.environ.items() if k not in ("VIRTUAL_ENV", "MAKEFLAGS", "MAKELEVEL")}
    with (root / "output.txt").open("wb") as log:
        process = subprocess.Popen(["bash", "readme.sh"], cwd=work, stdout=log, stderr=subprocess.STDOUT, env=env,
                                   stdin=subprocess.DEVNULL, start_new_session=True)
    return ReadmeRun(root, process)


@pytest.mark.slow
def test_every_readme_block_runs_in_order_in_a_fresh_folder(request: pytest.FixtureRequest) -> None:
    run: ReadmeRun | None = getattr(request.config, "readme_run", None)
    if run is None:  # not started at collection (the conftest hook): run it now
        run = start_readme_run()
        request.config.readme_run = run  # type: ignore[attr-defined]
    code, output = run.wait(timeout=900)
    work = run.work
    assert code == 0, output[-4000:]
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
