"""Issue 64: the ten holes a hostile user found in round two, each reproduced through the CLI as the issue did:
one clear line (exit 2) or a quarantine, no traceback, no hang (each command run with a timeout),
nothing outside the output folder touched and nothing logpipe did not write deleted."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
DATA = REPO / "tests" / "data"
SHARED = REPO.parent / "shared" / "data"
LOGPIPE = [sys.executable, "-m", "logpipe.cli"]
HANG_SECONDS = 60
"""A hang guard, not a speed target: a FIFO blocks forever, and each command here takes 1-8 s on an idle machine
(torch's import included), so 60 s only fails a hang, not a loaded CI."""


def _cli(*args: str | Path) -> subprocess.CompletedProcess[str]:
    """One logpipe command; a hang fails the test (``TimeoutExpired``) instead of blocking the suite."""
    return subprocess.run([*LOGPIPE, "-q", *map(str, args)], capture_output=True, text=True, cwd=REPO,
                          timeout=HANG_SECONDS, check=False)


def _one_error_line(result: subprocess.CompletedProcess[str], *words: str, code: int = 2) -> str:
    lines = [ln for ln in result.stderr.splitlines() if ln.strip()]
    assert result.returncode == code, (result.returncode, result.stderr)
    assert "Traceback" not in result.stderr and len(lines) == 1, result.stderr
    assert all(w in lines[0] for w in words), lines
    return lines[0]


def _files(folder: Path) -> dict[str, bytes]:
    return {p.relative_to(folder).as_posix(): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


# ---- 1: verify --repair under a spoofed manifest ---------------------------------------------------------


@pytest.mark.parametrize("kind", ["raster_run", "dataset", "prediction_run", "score_report"])
def test_repair_under_a_spoofed_manifest_deletes_nothing(tmp_path: Path, kind: str) -> None:
    folder = tmp_path / "f"
    for rel in ("sub/d.txt", "notes.txt", "tracks/a.parquet", "mcap/b.mcap", "logs/c.parquet",
                "part-00000.parquet", "predictions/part-00000.parquet", "report.json"):
        (folder / rel).parent.mkdir(parents=True, exist_ok=True)
        (folder / rel).write_text(f"the user's {rel}")
    (folder / "manifest.json").write_text(f'{{"artifact":"{kind}","files":{{}}}}')
    before = _files(folder)
    result = _cli("verify", "--repair", folder)
    assert "Traceback" not in result.stderr, result.stderr
    assert _files(folder) == before  # not one of the user's files removed


def test_a_writer_entering_a_spoofed_dataset_deletes_nothing(tmp_path: Path) -> None:
    """The same proof guards every writer's cleanup, not only verify: an ingest into the folder."""
    folder = tmp_path / "f"
    (folder / "tracks").mkdir(parents=True)
    (folder / "tracks" / "part-00000.parquet").write_text("the user's")
    (folder / "manifest.json").write_text('{"artifact":"dataset","files":{}}')
    _cli("ingest", DATA / "driving" / "20.csv", "--out", folder, "--no-mcap")
    assert (folder / "tracks" / "part-00000.parquet").read_text() == "the user's" or \
        (folder / "tracks" / "part-00000.parquet").read_bytes().startswith(b"PAR1")  # replaced only by its own


# ---- 2: a symlinked --out ---------------------------------------------------------------------------------


def test_a_symlinked_out_is_refused_before_the_first_write(tmp_path: Path) -> None:
    target = tmp_path / "v"
    target.mkdir()
    (tmp_path / "link").symlink_to(target)
    result = _cli("ingest", DATA / "driving" / "20.csv", "--out", tmp_path / "link")
    _one_error_line(result, "link", "symbolic link")
    assert list(target.iterdir()) == []


# ---- 3: FIFOs where logpipe reads a map, a mapping file, a checkpoint's meta.json ------------------------


@pytest.fixture(scope="module")
def ethucy_dataset(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("eth") / "ds"
    subprocess.run([*LOGPIPE, "-q", "ingest", str(DATA / "ethucy"), "--out", str(out), "--no-mcap"], cwd=REPO,
                   check=True, timeout=120)
    return out


@pytest.fixture(scope="module")
def driving_dataset(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("drv") / "ds"
    subprocess.run([*LOGPIPE, "-q", "ingest", str(DATA / "driving" / "20.csv"), "--out", str(out), "--no-mcap"],
                   cwd=REPO, check=True, timeout=120)
    return out


@pytest.mark.parametrize("suffix", [".npz", ".osm"])
def test_a_fifo_as_a_map_is_refused(tmp_path: Path, driving_dataset: Path, suffix: str) -> None:
    fifo = tmp_path / f"m{suffix}"
    os.mkfifo(fifo)
    copy = tmp_path / "ds"
    shutil.copytree(driving_dataset, copy)
    _one_error_line(_cli("rasterise", copy, "--map", f"MIA={fifo}"), str(fifo), "FIFO")


@pytest.mark.parametrize("name", ["map.toml", "map.yaml"])
def test_a_fifo_as_a_mapping_file_is_refused(tmp_path: Path, name: str) -> None:
    fifo = tmp_path / name
    os.mkfifo(fifo)
    bag = DATA / "rosbags"
    result = _cli("ingest", bag, "--mapping", fifo, "--out", tmp_path / "out")
    _one_error_line(result, name, "FIFO")


def _checkpoint_copy(tmp_path: Path) -> Path:
    shipped = REPO / "model" / "checkpoints" / "ethucy" / "eth"
    copy = tmp_path / "ckpt"
    copy.mkdir()
    for name in ("meta.json", "weights.safetensors"):
        shutil.copy(shipped / name, copy / name)
    return copy


def test_a_fifo_as_a_checkpoints_meta_json_is_refused(tmp_path: Path, ethucy_dataset: Path) -> None:
    ckpt = _checkpoint_copy(tmp_path)
    (ckpt / "meta.json").unlink()
    os.mkfifo(ckpt / "meta.json")
    result = _cli("predict", ethucy_dataset, "--checkpoint", ckpt, "--out", tmp_path / "pred")
    _one_error_line(result, "meta.json", "FIFO")
    verify = _cli("verify", ckpt)  # no readable meta.json: not taken for a checkpoint folder
    assert verify.returncode == 2 and "Traceback" not in verify.stderr, verify.stderr


# ---- 4: deep nesting ---------------------------------------------------------------------------------------

DEEP = "[" * 100_000


def test_a_deeply_nested_manifest_is_one_line(tmp_path: Path, ethucy_dataset: Path) -> None:
    copy = tmp_path / "ds"
    shutil.copytree(ethucy_dataset, copy)
    (copy / "manifest.json").write_text(DEEP)
    for args in (("verify", copy), ("verify", "--repair", copy)):
        result = _cli(*args)
        assert result.returncode == 1 and "Traceback" not in result.stderr, result.stderr
        assert "nested too deeply" in result.stdout, result.stdout
    _one_error_line(_cli("ingest", DATA / "ethucy", "--out", copy), "manifest.json", "nested too deeply")


def test_a_deeply_nested_meta_json_is_one_line(tmp_path: Path, ethucy_dataset: Path) -> None:
    ckpt = _checkpoint_copy(tmp_path)
    (ckpt / "meta.json").write_text(DEEP)
    _one_error_line(_cli("predict", ethucy_dataset, "--checkpoint", ckpt, "--out", tmp_path / "p"),
                    "meta.json", "nested too deeply")


@pytest.mark.parametrize(("name", "text"), [("map.toml", "a = " + DEEP), ("map.yaml", DEEP)])
def test_a_deeply_nested_mapping_is_one_line(tmp_path: Path, name: str, text: str) -> None:
    (tmp_path / name).write_text(text)
    _one_error_line(_cli("ingest", DATA / "rosbags", "--mapping", tmp_path / name, "--out", tmp_path / "o"),
                    name, "nested too deeply")


# ---- 5: a full disk under the native MCAP writer -----------------------------------------------------------


def _tmpfs(folder: Path, size: str) -> bool:
    folder.mkdir()
    return subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(folder)],
                          capture_output=True, check=False).returncode == 0


def test_a_full_disk_under_the_native_mcap_writer_is_the_disk_full_line(tmp_path: Path) -> None:
    disk = tmp_path / "disk"
    if not _tmpfs(disk, "6m"):
        pytest.skip("cannot mount a tmpfs here (needs root with CAP_SYS_ADMIN)")
    try:
        stats = os.statvfs(disk)  # ~150 KB left: less than the ~460 KB this ingest writes
        (disk / "filler").write_bytes(b"\0" * (stats.f_bavail * stats.f_frsize - 150 * 1024))
        inputs = sorted(str(p) for p in (DATA / "argoverse1").glob("*.csv"))
        result = subprocess.run([*LOGPIPE, "-q", "ingest", *inputs, "--out", str(disk / "o")], capture_output=True,
                                text=True, cwd=REPO, timeout=60, check=False)
        line = _one_error_line(result, "disk full")
        assert ".mcap" in line or "parquet" in line, line
        assert not (disk / "o").exists() or not any((disk / "o").rglob("*.mcap"))
    finally:
        subprocess.run(["umount", str(disk)], check=False)


# ---- 6: ROS 2 zstd message compression ----------------------------------------------------------------------


def _ros2_bag(folder: Path, big_message_bytes: int) -> Path:
    from rosbags.rosbag2 import Writer
    from rosbags.rosbag2.enums import CompressionFormat, CompressionMode
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS2_HUMBLE)
    writer = Writer(folder, version=8)
    writer.set_compression(CompressionMode.MESSAGE, CompressionFormat.ZSTD)
    with writer:
        conn = writer.add_connection("/chatter", "std_msgs/msg/String", typestore=store)
        for i, size in enumerate((10, big_message_bytes, 10)):
            msg = store.types["std_msgs/msg/String"](data="a" * size)
            writer.write(conn, 1_000_000_000 + i, store.serialize_cdr(msg, "std_msgs/msg/String"))
    return folder


def test_a_ros2_zstd_message_bomb_is_refused(tmp_path: Path) -> None:
    from rosbags.highlevel import AnyReader

    from logpipe.formats.inflation import InflationError

    bomb = _ros2_bag(tmp_path / "bomb", 256 << 20)  # 256 MiB of 'a' in one message: ~8 KB of zstd
    assert sum(p.stat().st_size for p in bomb.rglob("*") if p.is_file()) < 1 << 20
    with AnyReader([bomb]) as reader, pytest.raises(InflationError, match="inflates past"):
        for _ in reader.messages():
            pass
    result = _cli("inspect", bomb)
    assert result.returncode == 2 and "Traceback" not in result.stderr
    assert "inflates past" in result.stdout + result.stderr


def test_an_ordinary_ros2_zstd_bag_reads(tmp_path: Path) -> None:
    from rosbags.highlevel import AnyReader

    bag = _ros2_bag(tmp_path / "ok", 100_000)
    with AnyReader([bag]) as reader:
        sizes = [len(raw) for _, _, raw in reader.messages()]
    assert len(sizes) == 3 and max(sizes) > 100_000


# ---- 7: a text file cut mid-number --------------------------------------------------------------------------


def _cut(source: Path, size: int, target: Path) -> Path:
    target.parent.mkdir(parents=True, exist_ok=True)
    target.write_bytes(source.read_bytes()[:size])
    return target


@pytest.mark.skipif(not (SHARED / "ethucy").is_dir(), reason="needs ../shared/data/ethucy")
def test_the_hotel_file_cut_at_1985_bytes_is_quarantined(tmp_path: Path) -> None:
    source = SHARED / "ethucy" / "hotel" / "val" / "uni_examples_val.txt"
    cut = _cut(source, 1985, tmp_path / "in" / "uni_examples_val.txt")
    assert not cut.read_bytes().endswith(b"\n") and cut.read_bytes().endswith(b"10.3")
    _one_error_line(_cli("ingest", cut, "--out", tmp_path / "a"), "uni_examples_val.txt:50", "truncated record")
    skipped = _cli("ingest", cut, "--out", tmp_path / "b", "--on-error", "skip", "--json")
    # Quarantined and named; with every input quarantined the run fails (exit 2) after committing (issue 65).
    summary = json.loads(skipped.stdout)
    assert skipped.returncode == 2 and summary["inputs_ingested"] == 0, skipped.stdout + skipped.stderr
    assert "truncated record" in json.dumps(summary["quarantined"])
    whole = _cli("ingest", source, "--out", tmp_path / "c")
    assert whole.returncode == 0, whole.stderr


def test_an_apolloscape_file_cut_mid_number_is_refused(tmp_path: Path) -> None:
    source = DATA / "apolloscape" / "result_9048_1_frame.txt"
    text = source.read_bytes()
    at = text.index(b" -0.009") + 4  # "-0." of "-0.009": parses as -0.0
    cut = _cut(source, at, tmp_path / "in" / source.name)
    _one_error_line(_cli("ingest", cut, "--out", tmp_path / "a"), source.name, "truncated record")


# ---- 8: ids that cannot round-trip -------------------------------------------------------------------------


@pytest.mark.parametrize("ped_id", ["4503599627370497.3", "2147483000.25", "5.5"])
def test_a_fractional_or_inexact_id_is_refused(tmp_path: Path, ped_id: str) -> None:
    path = tmp_path / "ids.txt"
    path.write_text(f"10.0\t{ped_id}\t1.0\t2.0\n20.0\t{ped_id}\t1.5\t2.5\n")
    _one_error_line(_cli("ingest", path, "--out", tmp_path / "o"), "ids.txt:1", "ped_id")


def test_a_large_whole_id_still_lands_exactly(tmp_path: Path) -> None:
    path = tmp_path / "ids.txt"
    path.write_text("10.0\t2147483000.0\t1.0\t2.0\n20.0\t2147483000.0\t1.5\t2.5\n")
    assert _cli("ingest", path, "--out", tmp_path / "o", "--no-mcap").returncode == 0
    import pyarrow.parquet as pq

    tracks = pq.read_table(next((tmp_path / "o" / "tracks").glob("*.parquet")), columns=["track_id"])
    assert set(tracks.column("track_id").to_pylist()) == {"2147483000"}


def test_the_native_mcap_writer_turns_a_full_disk_into_enospc(tmp_path: Path) -> None:
    """The SDK's ``RuntimeError('FoxgloveError: MCAP error: I/O error ...')`` at close is the OSError it stands for."""
    import errno

    from logpipe.mcap.native import NativeMcap

    disk = tmp_path / "disk"
    if not _tmpfs(disk, "1m"):
        pytest.skip("cannot mount a tmpfs here (needs root with CAP_SYS_ADMIN)")
    try:
        writer = NativeMcap(disk / "a.mcap")
        channel = writer.channel("/t", "json", None)
        for i in range(20_000):
            channel.log(os.urandom(200), i, None)
        with pytest.raises(OSError, match="No space left") as caught:
            writer.close()
        assert caught.value.errno == errno.ENOSPC and caught.value.filename == str(disk / "a.mcap")
    finally:
        subprocess.run(["umount", str(disk)], check=False)


# ---- 9: physically impossible motion ----------------------------------------------------------------------


def _eth_track(tmp_path: Path, name: str, xs: list[float]) -> Path:
    """One ETH/UCY file: pedestrian 1 walking at 1.2 m/s (0.48 m a 0.4 s step) along y, with ``xs`` as x."""
    path = tmp_path / "in" / name
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("".join(f"{10 * i}.0\t1.0\t{x}\t{0.48 * i}\n" for i, x in enumerate(xs)))
    return path


@pytest.mark.parametrize(("name", "xs"), [
    ("teleport.txt", [0.0] * 10 + [1000.0] * 10),  # 1 km in one 0.4 s step at observed step 10
    ("zigzag.txt", [50.0 if i % 2 else -50.0 for i in range(20)]),  # +-50 m every step
])
def test_impossible_motion_is_quarantined_at_ingest(tmp_path: Path, name: str, xs: list[float]) -> None:
    path = _eth_track(tmp_path, name, xs)
    line = _one_error_line(_cli("ingest", path, "--out", tmp_path / "a"), name, "m/s")
    assert "jumps" in line
    good = _eth_track(tmp_path, "walker.txt", [0.0] * 20)
    skipped = _cli("ingest", path.parent, "--out", tmp_path / "b", "--on-error", "skip", "--no-mcap", "--json")
    assert skipped.returncode == 0, skipped.stderr
    import json

    summary = json.loads(skipped.stdout)
    assert [q["path"] for q in summary["quarantined"]] == [name]
    assert summary["totals"]["logs"] == 1 and good.exists()


def test_a_walker_lands(tmp_path: Path) -> None:
    path = _eth_track(tmp_path, "walker.txt", [0.0] * 20)
    assert _cli("ingest", path, "--out", tmp_path / "a", "--no-mcap").returncode == 0


def _commonroad_with(tmp_path: Path, old: str, new: str) -> Path:
    source = DATA / "commonroad"
    xml = next(p for p in sorted(source.rglob("*.xml")))
    text = xml.read_text()
    assert old in text
    path = tmp_path / "in" / xml.name
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text.replace(old, new, 1))
    return path


@pytest.mark.parametrize("field", ["x", "velocity"])
def test_a_commonroad_obstacle_far_away_or_too_fast_is_refused(tmp_path: Path, field: str) -> None:
    from lxml import etree

    xml = next(p for p in sorted((DATA / "commonroad").rglob("*.xml")))
    root = etree.parse(str(xml)).getroot()
    element = next(el for el in root.iter(field) if el.getparent().tag in ("position", "state")
                   or el.getparent().getparent().tag == "state") if field == "velocity" else \
        next(el for el in root.iter("x") if el.getparent().tag == "point" and
             el.getparent().getparent().tag == "position")
    target = element.find("exact") if element.find("exact") is not None else element
    target.text = "1000000.0"
    path = tmp_path / "in" / xml.name
    path.parent.mkdir(parents=True)
    etree.ElementTree(root).write(str(path))
    _one_error_line(_cli("ingest", path, "--out", tmp_path / "o"), xml.name)


# ---- 10: large CommonRoad files ---------------------------------------------------------------------------


def test_a_commonroad_file_over_the_limit_is_refused_at_once(tmp_path: Path) -> None:
    from logpipe.maps.commonroad import MAX_FILE_BYTES

    xml = next(p for p in sorted((DATA / "commonroad").rglob("*.xml")))
    text = xml.read_bytes()
    big = tmp_path / "in" / xml.name
    big.parent.mkdir()
    # Padding in an XML comment after the root element: a well-formed file, only too large.
    big.write_bytes(text + b"<!--" + b" " * (MAX_FILE_BYTES + 1 - len(text)) + b"-->\n")
    line = _one_error_line(_cli("ingest", big, "--out", tmp_path / "o"), xml.name, "16 MiB")
    assert "refused before parsing" in line
    help_text = _cli("ingest", "--help").stdout
    assert "CommonRoad files 16 MiB" in " ".join(help_text.split())


# ---- files without chunk CRCs ------------------------------------------------------------------------------


def _pose_mcap(path: Path, *, crcs: bool) -> Path:
    import json

    from mcap.writer import Writer

    with path.open("wb") as fh:
        writer = Writer(fh, enable_crcs=crcs)
        writer.start()
        schema = writer.register_schema(name="foxglove.PoseInFrame", encoding="jsonschema", data=b"{}")
        channel = writer.register_channel(topic="/pose", message_encoding="json", schema_id=schema)
        for i in range(50):
            pose = {"timestamp": {"sec": i // 10, "nsec": (i % 10) * 100_000_000}, "frame_id": "map",
                    "pose": {"position": {"x": i * 0.5, "y": 0.0, "z": 0.0},
                             "orientation": {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0}}}
            t = (i + 1) * 100_000_000
            writer.add_message(channel, log_time=t, publish_time=t, data=json.dumps(pose).encode())
        writer.finish()
    return path


def test_an_mcap_without_chunk_crcs_lands_with_a_warning(tmp_path: Path) -> None:
    import json

    (tmp_path / "in").mkdir()
    bare = _pose_mcap(tmp_path / "in" / "bare.mcap", crcs=False)
    checked = _pose_mcap(tmp_path / "in" / "checked.mcap", crcs=True)
    result = _cli("ingest", bare, checked, "--out", tmp_path / "o", "--set", "ego=/pose", "--json")
    assert result.returncode == 0, result.stderr
    warnings = json.loads(result.stdout)["warnings"]
    assert warnings == ["bare.mcap: 1 chunks carry no CRC: corruption inside them cannot be detected"]
    human = subprocess.run([*LOGPIPE, "ingest", str(bare), "--out", str(tmp_path / "h"), "--set", "ego=/pose"],
                           capture_output=True, text=True, cwd=REPO, timeout=HANG_SECONDS, check=False)
    assert "warning: bare.mcap: 1 chunks carry no CRC" in human.stdout + human.stderr


def test_a_ros1_bag_lands_with_a_warning(tmp_path: Path) -> None:
    import json

    bag = next(p for p in sorted((DATA / "rosbags").rglob("*.bag")))
    result = _cli("ingest", bag, "--out", tmp_path / "o", "--json", "--on-error", "skip")
    assert result.returncode == 0, result.stderr
    summary = json.loads(result.stdout)
    assert summary["inputs_ingested"] == 1, summary["quarantined"]
    assert [w.split(": ", 1)[1] for w in summary["warnings"]] == [
        "a ROS 1 bag carries no checksums: corruption inside it cannot be detected"]
