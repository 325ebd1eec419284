"""Issue 56 item 10: error lines keep the errno and the file, never claim that nothing was committed, and a dying
Ray system process is one line (exit 2), not Ray's traceback."""

from __future__ import annotations

import errno

import pytest
import typer

from logpipe.cli.app import user_errors
from logpipe.storage.artifact import os_error_message


def test_an_os_error_keeps_its_errno_name_and_file() -> None:
    line = os_error_message(OSError(errno.EIO, "Input/output error", "/data/ds/tracks/part-00003.parquet"))
    assert line.startswith("/data/ds/tracks/part-00003.parquet: Input/output error (EIO);")
    assert "nothing was committed" not in line and "previous state (its last commit)" in line
    full = os_error_message(OSError(errno.ENOSPC, "No space left on device", "/d/x.tmp"))
    assert "disk full (ENOSPC)" in full
    moved = os_error_message(OSError(errno.EXDEV, "Invalid cross-device link", "/a", None, "/b"))
    assert moved.startswith("/a -> /b: Invalid cross-device link (EXDEV)")


def test_an_os_error_without_a_file_says_so_instead_of_output() -> None:
    line = os_error_message(OSError(errno.EIO, "Input/output error"))
    assert not line.startswith("output:") and "did not name" in line and "(EIO)" in line


def test_a_ray_system_error_is_one_line_with_exit_2(capsys: pytest.CaptureFixture[str]) -> None:
    died = type("LocalRayletDiedError", (Exception,), {"__module__": "ray.exceptions"})
    with pytest.raises(typer.Exit) as exit_info, user_errors():
        raise died("The task's local raylet died. Check raylet.out for more information.\nmore detail")
    assert exit_info.value.exit_code == 2
    lines = [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()]
    assert len(lines) == 1 and "LocalRayletDiedError" in lines[0] and "committed work is kept" in lines[0]


def test_other_exceptions_still_propagate() -> None:
    with pytest.raises(KeyError), user_errors():
        raise KeyError("a bug stays a bug")
