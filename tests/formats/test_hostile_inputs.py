"""Issue 56, inputs: a negative frame, a FIFO inside an input folder and a symlink out of it are each one input's
error (quarantined with ``--on-error skip``), never a crash, a hang or a leak of another file into the manifest."""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import pytest

from logpipe.dataset.reader import Dataset
from logpipe.errors import SourceError
from logpipe.stages.ingest import IngestOptions, ingest

REPO = Path(__file__).resolve().parents[2]
DATA = REPO / "tests" / "data"
AV2 = REPO.parent / "shared" / "data" / "av2"


def _with_negative_frame(source: Path, target: Path, sep: str) -> None:
    lines = source.read_text().splitlines()
    first = lines[0].split(sep)
    lines.append(sep.join(["-400", *first[1:]]))  # a late row at frame -400
    target.write_text("\n".join(lines) + "\n")


@pytest.mark.parametrize(("fmt", "good", "sep"), [
    ("ethucy", DATA / "ethucy" / "eth" / "test" / "biwi_eth.txt", "\t"),
    ("apolloscape", DATA / "apolloscape" / "result_9048_1_frame.txt", " "),
])
def test_a_negative_frame_is_quarantined_and_the_good_files_land(tmp_path: Path, fmt: str, good: Path,
                                                                 sep: str) -> None:
    """Red-team item 4: frame -400 raised struct.error in the MCAP writer even in skip mode (exit 1, nothing
    ingested, the good files lost)."""
    inputs = tmp_path / "in"
    inputs.mkdir()
    shutil.copy(good, inputs / good.name)
    bad = inputs / ("bad_" + good.name)
    _with_negative_frame(good, bad, sep)
    out = tmp_path / "ds"
    ingest([inputs], IngestOptions(out=out, on_error="skip", format=fmt))
    manifest = Dataset.open(out).manifest
    assert [i["path"] for i in manifest["inputs"]] == [good.name]
    [quarantined] = manifest["quarantined"]
    assert quarantined["path"] == bad.name and quarantined["error"]["field"] == "frame_id"
    assert "-400" in str(quarantined["error"]["reason"])
    with pytest.raises(SourceError, match="frame_id"):
        ingest([inputs], IngestOptions(out=tmp_path / "ds2", format=fmt))
    assert not (tmp_path / "ds2").exists()


def test_a_symlink_out_of_the_input_folder_leaks_nothing_into_the_manifest(tmp_path: Path) -> None:
    """Red-team item 9: in skip mode a symlinked input's parse error quoted its first line into the manifest."""
    secret = tmp_path / "secret.txt"
    secret.write_text("hunter2-password-line\n")
    inputs = tmp_path / "in"
    inputs.mkdir()
    good = DATA / "ethucy" / "eth" / "test" / "biwi_eth.txt"
    shutil.copy(good, inputs / good.name)
    (inputs / "zz_link.txt").symlink_to(secret)
    out = tmp_path / "ds"
    ingest([inputs], IngestOptions(out=out, on_error="skip", format="ethucy"))
    text = (out / "manifest.json").read_text()
    assert "hunter2" not in text
    [quarantined] = Dataset.open(out).manifest["quarantined"]
    assert quarantined["path"] == "zz_link.txt" and "outside its input folder" in str(quarantined["error"]["reason"])
    # A link that stays inside the input folder is an input like any other.
    inside = tmp_path / "in2"
    inside.mkdir()
    shutil.copy(good, inside / "real.txt")
    (inside / "sub").mkdir()
    (inside / "sub" / "link.txt").symlink_to(inside / "real.txt")
    ingest([inside], IngestOptions(out=tmp_path / "ds2", on_error="skip", format="ethucy"))
    assert Dataset.open(tmp_path / "ds2").manifest["quarantined"] == []


@pytest.mark.shared
@pytest.mark.skipif(not AV2.is_dir(), reason="needs ../shared/data/av2")
@pytest.mark.timeout(120)
def test_a_fifo_inside_an_av2_sensor_log_is_that_logs_error_not_a_hang(tmp_path: Path) -> None:
    """Red-team item 6: a FIFO inside an AV2 sensor log hung ingest forever and left the lock and a staging
    folder behind."""
    logs = sorted((AV2 / "sensor_logs").iterdir())[:2]
    inputs = tmp_path / "sensor_logs"
    inputs.mkdir()
    for log in logs:
        shutil.copytree(log, inputs / log.name)
        (inputs / log.name).chmod(0o755)  # the shared data is read-only
    hostile = inputs / logs[0].name
    annotations = next(hostile.glob("annotations*.feather"))
    annotations.unlink()
    os.mkfifo(annotations)
    out = tmp_path / "ds"
    ingest([inputs], IngestOptions(out=out, on_error="skip", format="argoverse2", write_mcap=False))
    manifest = Dataset.open(out).manifest
    assert [i["path"] for i in manifest["inputs"]] == [logs[1].name]
    [quarantined] = manifest["quarantined"]
    assert "FIFO" in str(quarantined["error"]["reason"]) and annotations.name in str(quarantined["error"]["file"])
    # no lock, no staging left; the write journal stays (the proof that logpipe wrote what a later commit removes)
    assert sorted(p.name for p in out.iterdir() if p.name.startswith(".")) == [".logpipe-written"]


@pytest.mark.parametrize(("column", "value", "field", "words"), [
    ("X", "1e12", "x", "beyond the plausible"),
    ("Y", "-3.5e9", "y", "beyond the plausible"),
    ("TRACK_ID", "evil\x01id", "track_id", "NUL or control characters"),
])
def test_absurd_values_are_quarantined_with_their_field(tmp_path: Path, column: str, value: str, field: str,
                                                        words: str) -> None:
    """Red-team item 9: coordinates of 1e12 m and control characters in ids were stored as given."""
    inputs = tmp_path / "in"
    inputs.mkdir()
    good = DATA / "argoverse1" / "2645.csv"
    shutil.copy(good, inputs / good.name)
    lines = (DATA / "argoverse1" / "3861.csv").read_text().splitlines()
    header = lines[0].split(",")
    row = lines[5].split(",")
    row[header.index(column)] = value
    lines[5] = ",".join(row)
    (inputs / "3861.csv").write_text("\n".join(lines) + "\n")
    out = tmp_path / "ds"
    ingest([inputs], IngestOptions(out=out, on_error="skip", format="argoverse1", write_mcap=False))
    manifest = Dataset.open(out).manifest
    assert [i["path"] for i in manifest["inputs"]] == [good.name]
    [quarantined] = manifest["quarantined"]
    assert quarantined["error"]["field"] == field and words in str(quarantined["error"]["reason"])


@pytest.mark.shared
@pytest.mark.skipif(not AV2.is_dir(), reason="needs ../shared/data/av2")
def test_a_scaled_quaternion_in_an_av2_sensor_log_is_refused(tmp_path: Path) -> None:
    """Red-team item 9: quaternions scaled by 1e-3 turned headings silently."""
    import pyarrow as pa
    from pyarrow import feather

    from logpipe.formats.av2 import Av2Adapter
    from logpipe.types import SourceFile

    log = sorted((AV2 / "sensor_logs").iterdir())[0]
    copy = tmp_path / log.name
    shutil.copytree(log, copy)
    copy.chmod(0o755)
    annotations = next(copy.glob("annotations*.feather"))
    table = feather.read_table(annotations)
    for name in ("qw", "qx", "qy", "qz"):
        scaled = pa.array(table.column(name).to_numpy() * 1e-3)
        table = table.set_column(table.schema.get_field_index(name), name, scaled)
    feather.write_feather(table, annotations)
    with pytest.raises(SourceError, match="not unit length") as info:
        Av2Adapter().read([SourceFile(str(copy), log.name, "0" * 64, 0)], keep_going=False)
    assert info.value.field == "qw"
    Av2Adapter().read([SourceFile(str(log), log.name, "0" * 64, 0)], keep_going=False)  # the real one passes


ROS2_BAG = REPO.parent / "shared" / "data" / "rosbags" / "evo" / "tf_example"


@pytest.mark.shared
@pytest.mark.skipif(not ROS2_BAG.is_dir(), reason="needs ../shared/data/rosbags")
@pytest.mark.timeout(120)
def test_a_fifo_inside_a_bag_folder_is_refused_not_read(tmp_path: Path) -> None:
    """The same hang as item 6 for any folder input: a ROS 2 bag whose storage file is a FIFO."""
    from logpipe.formats.rosbag import RosbagAdapter
    from logpipe.types import SourceFile

    bag = tmp_path / "tf_example"
    shutil.copytree(ROS2_BAG, bag)
    bag.chmod(0o755)  # the shared data is read-only
    storage = next(bag.glob("*.db3"))
    storage.unlink()
    os.mkfifo(storage)
    with pytest.raises(SourceError, match=f"tf_example/{storage.name}: not a regular file: a FIFO"):
        RosbagAdapter().read([SourceFile(str(bag), "tf_example", "0" * 64, 0)], keep_going=False)
