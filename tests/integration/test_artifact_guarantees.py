"""What the artifact layer promises every output folder: one writer at a time, disk-full errors that leave the
committed state, and ``logpipe verify`` finding a single flipped byte in any kind of committed file."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pytest

from logpipe.dataset.reader import Dataset
from logpipe.errors import ArtifactBusyError, OutputError
from logpipe.stages.ingest import IngestOptions, ingest
from logpipe.storage.artifact import MANIFEST, read_manifest
from logpipe.storage.folder_lock import LOCK_FILE, FolderLock
from logpipe.storage.io import atomic_path
from logpipe.storage.write_journal import start_journal

REPO = Path(__file__).resolve().parents[2]
DATA = REPO / "tests" / "data"
LOGPIPE = [sys.executable, "-m", "logpipe.cli"]
MAPS = ["--map", f"MIA={DATA / 'maps/MIA_lane_centerlines_crop_2645.npz'}",
        "--map", f"PIT={DATA / 'maps/PIT_lane_centerlines_crop_3861.npz'}"]


def _cli(*args: str, check: bool = True) -> subprocess.CompletedProcess[str]:
    """``logpipe ARGS`` in a subprocess; tests of error output pass ``-q`` so progress lines do not mix in."""
    result = subprocess.run([*LOGPIPE, *args], capture_output=True, text=True, cwd=REPO, timeout=300, check=False)
    if check:
        assert result.returncode == 0, result.stderr[-2000:]
    return result


def test_a_second_writer_is_refused_at_once_naming_the_holder(tmp_path: Path) -> None:
    out = tmp_path / "ds"
    ingest([DATA / "ethucy"], IngestOptions(out=out, write_mcap=False))
    before = (out / MANIFEST).read_bytes()
    holder = FolderLock(out)
    holder.acquire()
    try:
        started = time.perf_counter()
        refused = _cli("-q", "ingest", str(DATA / "apolloscape"), "--out", str(out), check=False)
        assert time.perf_counter() - started < 30  # refused, not queued
        assert refused.returncode == 2
        lines = [ln for ln in refused.stderr.splitlines() if ln.strip()]
        assert len(lines) == 1 and f"pid {os.getpid()}" in lines[0] and "another logpipe process" in lines[0]
        with pytest.raises(ArtifactBusyError, match=f"pid {os.getpid()}"):
            ingest([DATA / "ethucy"], IngestOptions(out=out))
    finally:
        holder.release()
    assert (out / MANIFEST).read_bytes() == before
    assert not (out / ".logpipe.lock").exists()


@pytest.mark.slow
def test_two_concurrent_ingests_never_corrupt_the_dataset(tmp_path: Path) -> None:
    """The user trial's race: two ingests of different inputs into one folder at once. Whatever the timing,
    each run either lands whole or is refused, and the dataset verifies with exactly the landed inputs."""
    inputs = {name: tmp_path / name for name in ("a", "b")}
    csvs = sorted((DATA / "argoverse1").glob("*.csv"))
    for i, folder in enumerate(inputs.values()):
        folder.mkdir()
        for p in csvs[i::2]:
            shutil.copy(p, folder / p.name)
    for trial in range(6):
        out = tmp_path / f"ds{trial}"
        procs = [subprocess.Popen([*LOGPIPE, "ingest", str(src), "--out", str(out), "--json", "--batch-files", "1"],
                                  cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
                 for src in inputs.values()]
        results = [(p.wait(timeout=300), p.stdout.read() if p.stdout else "", p.stderr.read() if p.stderr else "")
                   for p in procs]
        for proc in procs:
            for stream in (proc.stdout, proc.stderr):
                if stream:
                    stream.close()
        landed = [src for src, (rc, _, _) in zip(inputs.values(), results, strict=True) if rc == 0]
        for rc, _, stderr in results:
            assert rc in (0, 2), stderr
            if rc == 2:
                assert "another logpipe process is writing here" in stderr
        assert landed, results
        verified = _cli("verify", str(out), "--json")
        assert json.loads(verified.stdout)["problems"] == []
        expected = sorted(p.name for src in landed for p in src.glob("*.csv"))
        assert sorted(i["path"] for i in Dataset.open(out).manifest["inputs"]) == expected


def _tmpfs(path: Path, size: str) -> bool:
    path.mkdir()
    mounted = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(path)],
                             capture_output=True, check=False)
    return mounted.returncode == 0


def test_disk_full_is_one_line_and_keeps_the_committed_state(tmp_path: Path) -> None:
    """A real full disk: a 2 MiB tmpfs holding a dataset of one log, filled up to 16 KiB by another file."""
    disk = tmp_path / "disk"
    if not _tmpfs(disk, "2m"):
        pytest.skip("cannot mount a tmpfs here (needs root with CAP_SYS_ADMIN); the EROFS case in "
                    "tests/integration/test_predict_then_score.py covers the same path with a fault injection")
    try:
        out = disk / "ds"
        ingest([DATA / "argoverse1" / "2645.csv"], IngestOptions(out=out))
        stats = os.statvfs(disk)
        (disk / "filler").write_bytes(b"\0" * (stats.f_bavail * stats.f_frsize - 16 * 1024))
        before = {p.relative_to(out).as_posix(): p.read_bytes() for p in out.rglob("*") if p.is_file()}
        full = _cli("-q", "ingest", str(DATA / "argoverse1"), "--out", str(out), check=False)
        assert full.returncode == 2, full.stdout + full.stderr
        lines = [ln for ln in full.stderr.splitlines() if ln.strip()]
        assert len(lines) == 1 and "disk full" in lines[0] and "Traceback" not in full.stderr, full.stderr
        after = {p.relative_to(out).as_posix(): p.read_bytes() for p in out.rglob("*") if p.is_file()}
        assert after == before  # nothing committed, nothing left behind
        with pytest.raises(OutputError, match="disk full"):
            ingest([DATA / "argoverse1"], IngestOptions(out=out, workers=1))
        assert Dataset.open(out).manifest["totals"]["logs"] == 1
        (disk / "filler").unlink()  # space again: the same command now lands
        _cli("ingest", str(DATA / "argoverse1"), "--out", str(out))
        assert Dataset.open(out).manifest["totals"]["logs"] == 6
    finally:
        subprocess.run(["umount", str(disk)], check=False)


@pytest.fixture(scope="module")
def artifacts(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """One folder of each kind: dataset, raster run, prediction run, score report."""
    root = tmp_path_factory.mktemp("kinds")
    src = root / "inputs"
    src.mkdir()
    for p in sorted((DATA / "argoverse1").glob("*.csv"))[:2]:
        shutil.copy(p, src / p.name)
    _cli("ingest", str(src), "--out", str(root / "ds"))
    _cli("rasterise", str(root / "ds"), *MAPS, "--preview", "1")
    _cli("predict", str(root / "ds"), "--predictor", "cv", "--out", str(root / "pred"))
    _cli("score", str(root / "pred"), "--truth", str(root / "ds"), "--out", str(root / "score"))
    runs = sorted((root / "ds" / "rasters").iterdir())
    return {"dataset": root / "ds", "raster_run": runs[0], "prediction_run": root / "pred",
            "score_report": root / "score"}


def _kinds_of_file(folder: Path) -> dict[str, str]:
    """One committed file per file kind (by suffix and folder) of an artifact folder, plus its manifest."""
    manifest = read_manifest(folder)
    assert manifest is not None
    picked: dict[str, str] = {MANIFEST: MANIFEST}
    for rel in sorted(manifest["files"]):
        kind = f"{rel.split('/')[0] if '/' in rel else ''}*{Path(rel).suffix}"
        picked.setdefault(kind, rel)
    return picked


@pytest.mark.parametrize("kind", ["dataset", "raster_run", "prediction_run", "score_report"])
def test_verify_finds_one_flipped_byte_in_every_kind_of_file(kind: str, artifacts: dict[str, Path],
                                                             tmp_path: Path) -> None:
    source = artifacts[kind]
    assert read_manifest(source)["artifact"] == kind  # type: ignore[index]
    clean = _cli("verify", str(source), "--json")
    assert json.loads(clean.stdout)["problems"] == [] and json.loads(clean.stdout)["leftovers"] == []
    files = _kinds_of_file(source)
    assert len(files) >= 3, files
    for label, rel in files.items():
        copy = tmp_path / label.replace("*", "_").replace("/", "_")
        shutil.copytree(source, copy)
        path = copy / rel
        data = bytearray(path.read_bytes())
        data[len(data) // 2] ^= 0x01
        path.write_bytes(bytes(data))
        found = _cli("verify", str(copy), check=False)
        assert found.returncode == 1, (label, found.stdout, found.stderr)
        problem_lines = [ln for ln in found.stdout.splitlines() if ln.strip()]
        assert len(problem_lines) == 1 and str(path) in problem_lines[0], (label, found.stdout)
        shutil.rmtree(copy)


def test_verify_repair_removes_leftovers_only(artifacts: dict[str, Path], tmp_path: Path) -> None:
    copy = tmp_path / "ds"
    shutil.copytree(artifacts["dataset"], copy)
    (copy / ".staging-0123456789ab").mkdir()
    (copy / ".staging-0123456789ab" / "part-00009.parquet").write_bytes(b"half")
    (copy / LOCK_FILE).write_text("{}")  # a writer killed while writing: its file is in the folder's journal
    start_journal(copy)  # the copy's journal (copied from the dataset) proves nothing here: new inodes
    with atomic_path(copy / "tracks" / "part-00009.parquet") as tmp:
        tmp.write_bytes(b"uncommitted")
    (copy / LOCK_FILE).unlink()
    (copy / "notes.txt").write_text("the user's own file")
    (copy / "tracks" / "part-00010.parquet").write_bytes(b"put there by hand: logpipe cannot prove it wrote it")
    found = _cli("verify", str(copy), check=False)
    assert found.returncode == 0 and found.stdout.count("uncommitted leftover") == 2
    _cli("verify", str(copy), "--repair")
    assert not (copy / ".staging-0123456789ab").exists() and not (copy / "tracks" / "part-00009.parquet").exists()
    assert (copy / "notes.txt").read_text() == "the user's own file"
    assert (copy / "tracks" / "part-00010.parquet").exists()
    assert json.loads(_cli("verify", str(copy), "--json").stdout)["leftovers"] == []


def test_verify_finds_a_flipped_byte_in_a_checkpoint(tmp_path: Path) -> None:
    copy = tmp_path / "eth"
    shipped = REPO / "model" / "checkpoints" / "ethucy" / "eth"
    copy.mkdir()
    for name in ("meta.json", "weights.safetensors"):
        shutil.copy(shipped / name, copy / name)
    assert _cli("verify", str(copy)).returncode == 0
    data = bytearray((copy / "weights.safetensors").read_bytes())
    data[len(data) // 2] ^= 0x01
    (copy / "weights.safetensors").write_bytes(bytes(data))
    found = _cli("verify", str(copy), check=False)
    assert found.returncode == 1 and found.stdout.strip() == (
        f"{copy / 'weights.safetensors'}: sha256 differs from meta.json (content changed)")


def test_a_flipped_bit_in_a_shard_is_an_error_on_read_not_other_values(artifacts: dict[str, Path],
                                                                       tmp_path: Path) -> None:
    """Readers do not recompute sha256 on open (too slow for big shards), but every Parquet page carries a
    CRC they check: the damage is one error line naming the file, never silently other positions."""
    copy = tmp_path / "ds"
    shutil.copytree(artifacts["dataset"], copy)
    shard = copy / Dataset.open(copy).manifest["shards"][0]["file"]
    data = bytearray(shard.read_bytes())
    data[len(data) // 3] ^= 0x01
    shard.write_bytes(bytes(data))
    failed = _cli("-q", "predict", str(copy), "--predictor", "cv", "--out", str(tmp_path / "pred"), check=False)
    lines = [ln for ln in failed.stderr.splitlines() if ln.strip()]
    assert failed.returncode == 2 and len(lines) == 1 and str(shard) in lines[0] and "CRC" in lines[0], failed.stderr


def test_a_new_output_folder_keeps_the_users_own_files(artifacts: dict[str, Path], tmp_path: Path) -> None:
    """--out pointed at a folder that already holds files of the names a report owns (PNGs), never written by
    logpipe: they are not leftovers, so they stay."""
    out = tmp_path / "pictures"
    out.mkdir()
    (out / "holiday.png").write_bytes(b"not ours")
    _cli("score", str(artifacts["prediction_run"]), "--truth", str(artifacts["dataset"]), "--out", str(out),
         "--no-plots")
    assert (out / "holiday.png").read_bytes() == b"not ours"
    assert (out / "report.json").is_file()
    _cli("score", str(artifacts["prediction_run"]), "--truth", str(artifacts["dataset"]), "--out", str(out))
    assert (out / "holiday.png").read_bytes() == b"not ours"  # still not a leftover once the folder is ours


def test_a_changed_raster_shard_is_an_error_when_a_run_reads_it(artifacts: dict[str, Path], tmp_path: Path) -> None:
    """Issue 56 item 8: predict used raster .npy files without a check (a flipped byte is a silently other raster;
    .npy has no CRC of its own). Each shard's sha256 is checked against the manifest when a reader first opens it."""
    from logpipe.errors import DatasetError
    from logpipe.raster.runs import find_raster_run

    copy = tmp_path / "ds"
    shutil.copytree(artifacts["dataset"], copy)
    rasters = find_raster_run(copy, None, None)
    assert rasters is not None
    first = rasters.index.column("sample_id")[0].as_py()
    assert rasters.get(first)[0].dtype.name == "uint8"  # intact: reads
    shard = rasters.run_dir / rasters.index.column("shard")[0].as_py()
    data = bytearray(shard.read_bytes())
    data[-1] ^= 0x01
    shard.write_bytes(bytes(data))
    damaged = find_raster_run(copy, None, None)
    assert damaged is not None
    with pytest.raises(DatasetError, match=f"{shard}: unreadable raster shard \\(sha256 differs"):
        damaged.get(first)
