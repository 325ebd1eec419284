"""Issue 56, storage safety: output folders that are shared or prepared by someone else. No write through a
link, no cleanup of what logpipe did not write, no cleanup that races another writer or a worker."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from logpipe.dataset.reader import Dataset
from logpipe.errors import ArtifactBusyError, DatasetError, OutputError
from logpipe.stages.ingest import IngestOptions, ingest
from logpipe.storage import folder_lock
from logpipe.storage.artifact import MANIFEST, ArtifactWriter, Ownership, file_entry, manifest_checksum, read_manifest
from logpipe.storage.folder_lock import LOCK_FILE, FolderLock
from logpipe.storage.io import atomic_path
from logpipe.storage.write_journal import start_journal
from logpipe.verify import verify_tree

REPO = Path(__file__).resolve().parents[2]
DATA = REPO / "tests" / "data"
ONE_LOG = DATA / "argoverse1" / "2645.csv"
LOGPIPE = [sys.executable, "-m", "logpipe.cli"]


def _cli(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([*LOGPIPE, "-q", *args], capture_output=True, text=True, cwd=REPO, timeout=300, check=False)


def _one_error_line(result: subprocess.CompletedProcess[str], *words: str) -> None:
    lines = [ln for ln in result.stderr.splitlines() if ln.strip()]
    assert result.returncode == 2, result.stderr
    assert len(lines) == 1 and "Traceback" not in result.stderr, result.stderr
    assert all(w in lines[0] for w in words), lines


def test_a_symlinked_lock_file_is_refused_and_its_target_untouched(tmp_path: Path) -> None:
    """Red-team item 1: ``ln -s ~/victim DS/.logpipe.lock; logpipe index DS`` wrote the lock JSON into victim."""
    out = tmp_path / "ds"
    ingest([ONE_LOG], IngestOptions(out=out, write_mcap=False))
    victim = tmp_path / "victim"
    victim.write_text("precious\n")
    (out / LOCK_FILE).symlink_to(victim)
    before = (out / MANIFEST).read_bytes()
    result = _cli("index", str(out), "--stride", "5")
    _one_error_line(result, str(out / LOCK_FILE), "symbolic link")
    assert victim.read_text() == "precious\n"
    assert (out / MANIFEST).read_bytes() == before
    assert (out / LOCK_FILE).is_symlink()  # the user's link is theirs to remove


def test_a_hard_linked_stale_lock_file_is_replaced_not_written_into(tmp_path: Path) -> None:
    out = tmp_path / "ds"
    out.mkdir()
    victim = tmp_path / "victim"
    victim.write_text("precious\n")
    os.link(victim, out / LOCK_FILE)
    lock = FolderLock(out)
    lock.acquire()
    try:
        assert lock.found_stale
        assert str(os.getpid()) in (out / LOCK_FILE).read_text()
    finally:
        lock.release()
    assert victim.read_text() == "precious\n"
    assert not (out / LOCK_FILE).exists()


def test_a_fifo_lock_file_is_refused_without_blocking(tmp_path: Path) -> None:
    out = tmp_path / "ds"
    out.mkdir()
    os.mkfifo(out / LOCK_FILE)
    with pytest.raises(OutputError, match="special file"):
        FolderLock(out).acquire()


def test_a_symlinked_owned_subfolder_receives_nothing(tmp_path: Path) -> None:
    """Red-team item 1: a symlinked ``mcap/`` received the MCAPs outside ``--out``."""
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    out = tmp_path / "ds"
    out.mkdir()
    (out / "mcap").symlink_to(elsewhere, target_is_directory=True)
    with pytest.raises(OutputError, match="mcap: is a symbolic link"):
        ingest([ONE_LOG], IngestOptions(out=out))
    assert list(elsewhere.iterdir()) == []
    assert sorted(p.name for p in out.iterdir()) == ["mcap"]
    # And the CLI says it in one line.
    _one_error_line(_cli("ingest", str(ONE_LOG), "--out", str(out)), "mcap: is a symbolic link")
    assert list(elsewhere.iterdir()) == []


def test_a_symlinked_subfolder_made_after_the_check_is_still_refused(tmp_path: Path) -> None:
    """The commit moves shards into owned folders part by part; each part is checked again there."""
    from logpipe.storage.safe_paths import real_folder

    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    (tmp_path / "ds").mkdir()
    (tmp_path / "ds" / "tracks").symlink_to(elsewhere, target_is_directory=True)
    with pytest.raises(OutputError, match="tracks: is a symbolic link"):
        real_folder(tmp_path / "ds", "tracks")
    assert real_folder(tmp_path / "ds", "mcap/part-00000").is_dir()


def test_verify_repair_never_touches_a_folder_logpipe_did_not_write(tmp_path: Path) -> None:
    """Red-team item 2: in any folder whose manifest.json is {"files": {}}, --repair removed every other file."""
    folder = tmp_path / "someone"
    folder.mkdir()
    (folder / MANIFEST).write_text('{"files": {}}')
    (folder / "thesis.tex").write_text("years of work")
    (folder / "tracks").mkdir()
    (folder / "tracks" / "data.parquet").write_bytes(b"PAR1")
    report = verify_tree([folder], repair=True)
    assert sorted(p.relative_to(folder).as_posix() for p in folder.rglob("*")) == [
        "manifest.json", "thesis.tex", "tracks", "tracks/data.parquet"]
    assert report["leftovers"] == [] and len(report["problems"]) == 1
    assert "not written by logpipe" in report["problems"][0]
    # A writer does not adopt it either.
    with pytest.raises(DatasetError, match="logpipe did not write"):
        ingest([ONE_LOG], IngestOptions(out=folder))
    assert (folder / "thesis.tex").read_text() == "years of work"


@pytest.mark.parametrize("files", [
    {"../outside": {"bytes": 1, "sha256": "x"}},
    {"/etc/hostname": {"bytes": 1, "sha256": "x"}},
    {"a": 5},
    {"a": {"bytes": "many", "sha256": "x"}},
    {"a\x00b": {"bytes": 1, "sha256": "x"}},
])
def test_a_foreign_manifest_is_one_problem_line_not_a_traceback(tmp_path: Path, files: dict[str, object]) -> None:
    """Red-team item 2: a foreign manifest made ``verify`` print a traceback; one naming a path outside the
    folder would have steered reads and removals outside it."""
    folder = tmp_path / "run"
    folder.mkdir()
    manifest: dict[str, object] = {"artifact": "score_report", "owns": ["report.json"], "files": files}
    manifest["checksum"] = manifest_checksum(manifest)
    (folder / MANIFEST).write_text(json.dumps(manifest))
    with pytest.raises(DatasetError, match="damaged or foreign manifest"):
        read_manifest(folder)
    result = _cli("verify", str(folder), "--repair")
    assert result.returncode != 0 and "Traceback" not in result.stderr, result.stderr
    assert "damaged or foreign manifest" in result.stdout + result.stderr


def test_verify_repair_removes_only_what_the_kinds_writer_owns(tmp_path: Path) -> None:
    """A manifest may claim to own everything; --repair trusts the writer's code, not the claim."""
    folder = tmp_path / "report"
    folder.mkdir()
    manifest: dict[str, object] = {"artifact": "score_report", "owns": ["*", "*/"], "files": {}}
    manifest["checksum"] = manifest_checksum(manifest)
    (folder / MANIFEST).write_text(json.dumps(manifest))
    (folder / "notes.txt").write_text("mine")
    (folder / LOCK_FILE).write_text("{}")  # a killed writer's stale lock: it was writing when it died
    start_journal(folder)  # as that writer did on entering
    with atomic_path(folder / "horizon.png") as tmp:  # as the killed run wrote it: recorded in its journal
        tmp.write_bytes(b"stale leftover of a killed run")
    (folder / LOCK_FILE).unlink()
    report = verify_tree([folder], repair=True)
    assert report["leftovers"] == [str(folder / "horizon.png")]
    assert (folder / "notes.txt").read_text() == "mine"
    assert not (folder / "horizon.png").exists()


def _fail_in_first_run(root: Path, rel: str, *, staged: bool = False) -> None:
    """A writer that creates ``root``, writes ``rel`` (and a staging file) and fails before committing."""
    with ArtifactWriter(root, Ownership(["tracks/"]), "dataset") as writer:
        (root / rel).parent.mkdir(parents=True, exist_ok=True)
        (root / rel).write_bytes(b"uncommitted")
        if staged:
            (writer.staging() / "x").write_bytes(b"staged")
        raise RuntimeError("A failed")


def test_a_failed_first_run_never_removes_a_concurrent_committed_one(tmp_path: Path,
                                                                   monkeypatch: pytest.MonkeyPatch) -> None:
    """Red-team item 3: writer A failed its first run, released the lock, then removed the folder; writer B
    that took the lock in that gap lost its committed dataset. B runs here exactly in that gap."""
    root = tmp_path / "ds"
    original = FolderLock.release
    b_ran: list[bool] = []

    def release_then_b(self: FolderLock, *, remove_folder: bool = False) -> None:
        original(self, remove_folder=remove_folder)
        if not b_ran:
            b_ran.append(True)
            ingest([ONE_LOG], IngestOptions(out=root, write_mcap=False))  # B lands in the gap

    monkeypatch.setattr(folder_lock.FolderLock, "release", release_then_b)
    with pytest.raises(RuntimeError, match="A failed"):
        _fail_in_first_run(root, "tracks/part-00000.parquet")
    assert b_ran
    monkeypatch.setattr(folder_lock.FolderLock, "release", original)
    assert Dataset.open(root).manifest["totals"]["logs"] == 1
    assert verify_tree([root])["problems"] == []


def test_a_failed_first_run_leaves_no_folder_but_keeps_foreign_files(tmp_path: Path) -> None:
    root = tmp_path / "new"
    with pytest.raises(RuntimeError):
        _fail_in_first_run(root, "tracks/part-00000.parquet", staged=True)
    assert not root.exists()
    with pytest.raises(RuntimeError):
        _fail_in_first_run(root, "users_note.txt")  # not owned: put there by someone during the run
    assert sorted(p.name for p in root.iterdir()) == ["users_note.txt"]


def test_a_commit_never_removes_a_workers_new_empty_folder(tmp_path: Path) -> None:
    """Red-team item 7: after a commit the writer removed every empty owned folder, among them a worker's
    ``mcap/part-N/`` made an instant before its first file: that predict failed (~1 in 40 runs)."""
    root = tmp_path / "run"
    with ArtifactWriter(root, Ownership(["predictions/", "mcap/"]), "prediction_run") as writer:
        old = root / "mcap" / "part-00000" / "a.mcap"
        with atomic_path(old) as tmp:  # as logpipe writes: recorded, so the next commit may remove it
            tmp.write_bytes(b"old")
        writer.commit({"files": {"mcap/part-00000/a.mcap": file_entry(old)}})
        fresh = root / "mcap" / "part-00001"
        fresh.mkdir()  # a worker's, about to hold its first file
        new = root / "predictions" / "part-00000.parquet"
        new.parent.mkdir()
        new.write_bytes(b"new")
        writer.commit({"files": {"predictions/part-00000.parquet": file_entry(new)}})
        assert fresh.is_dir()
        assert not (root / "mcap" / "part-00000").exists()  # emptied by this commit: removed


def test_a_symlinked_training_log_receives_nothing(tmp_path: Path) -> None:
    """A training run folder is locked but not a committed artifact: its append-only log is opened O_NOFOLLOW."""
    from logpipe.model.zhu2020.fit import _Log
    from logpipe.storage.io import open_nofollow

    victim = tmp_path / "victim"
    victim.write_text("precious\n")
    (tmp_path / "train_log.jsonl").symlink_to(victim)
    with pytest.raises(OutputError, match=r"train_log\.jsonl: is a symbolic link"):
        _Log(tmp_path / "train_log.jsonl").write("start", step=0)
    with pytest.raises(OutputError, match="symbolic link"):
        open_nofollow(tmp_path / "train_log.jsonl", "w")
    assert victim.read_text() == "precious\n"
    with open_nofollow(tmp_path / "own.jsonl", "a") as fh:
        fh.write("x\n")
    assert (tmp_path / "own.jsonl").read_text() == "x\n"


def test_a_lock_taken_on_a_folder_removed_meanwhile_is_taken_again(tmp_path: Path,
                                                                    monkeypatch: pytest.MonkeyPatch) -> None:
    """Item 3's other side: a writer that opened the folder just before a failed first run removed it (under its
    lock) would hold a lock on a deleted folder; the lock checks the path still leads to what it locked."""
    root = tmp_path / "ds"
    root.mkdir()
    real_open = os.open
    replaced: list[bool] = []

    def open_then_replace(path: object, flags: int, *args: object, **kwargs: object) -> int:
        fd = real_open(path, flags, *args, **kwargs)  # type: ignore[arg-type]
        if path == root and not replaced:
            replaced.append(True)
            root.rmdir()  # the other run's cleanup, in the instant after this open
            root.mkdir()
        return fd

    monkeypatch.setattr(folder_lock.os, "open", open_then_replace)
    lock = FolderLock(root)
    lock.acquire()
    try:
        assert replaced and (root / LOCK_FILE).is_file()  # the lock file is in the folder the path names now
        monkeypatch.setattr(folder_lock.os, "open", real_open)
        with pytest.raises(ArtifactBusyError):  # and the lock is on it: a second writer is refused
            FolderLock(root).acquire()
    finally:
        lock.release()
    assert not (root / LOCK_FILE).exists()


def test_a_symlinked_rasters_folder_of_a_dataset_receives_no_run(tmp_path: Path) -> None:
    """A raster run is an artifact nested in its dataset's ``rasters/``: a link there is refused like ``mcap/``."""
    from logpipe.raster.runs import RasterRunWriter

    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    (tmp_path / "ds").mkdir()
    (tmp_path / "ds" / "rasters").symlink_to(elsewhere, target_is_directory=True)
    writer = RasterRunWriter(tmp_path / "ds" / "rasters" / "r1")
    with pytest.raises(OutputError, match="rasters: is a symbolic link"):
        writer.__enter__()
    assert list(elsewhere.iterdir()) == []
