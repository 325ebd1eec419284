"""Inputs that are copies of one kept input are found again for the summary (``logpipe.formats.input_copies``)."""

from __future__ import annotations

import shutil
from pathlib import Path

from logpipe.formats.input_copies import duplicate_inputs
from logpipe.formats.inputs import fingerprint_inputs


def test_each_copy_names_the_input_it_equals(bundled: Path, tmp_path: Path) -> None:
    eth = sorted((bundled / "ethucy").rglob("*.txt"))
    a, b = eth[0], eth[1]
    assert a.read_bytes() != b.read_bytes() and a.stat().st_size != b.stat().st_size
    layout = {"x/train/a.txt": a, "y/train/a.txt": a, "z/train/a.txt": a, "x/train/b.txt": b}
    for rel, source in layout.items():
        (tmp_path / rel).parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(source, tmp_path / rel)
    found = [(tmp_path / rel, rel) for rel in sorted(layout)]
    sources = fingerprint_inputs(found, known_sizes=set(), threads=2)
    assert sorted(s.relpath for s in sources) == ["x/train/a.txt", "x/train/b.txt"]
    assert duplicate_inputs(found, sources) == [{"path": "y/train/a.txt", "same_as": "x/train/a.txt"},
                                                {"path": "z/train/a.txt", "same_as": "x/train/a.txt"}]
    assert duplicate_inputs(found[:1], sources[:1]) == []


def test_a_copied_bag_folder_is_matched_by_its_digest(tmp_path: Path) -> None:
    for name in ("one", "two"):
        bag = tmp_path / name / "bag"
        bag.mkdir(parents=True)
        (bag / "metadata.yaml").write_text("rosbag2_bagfile_information: {}\n")
        (bag / "bag_0.db3").write_bytes(b"\x00" * 64)
    found = [(tmp_path / "one" / "bag", "one/bag"), (tmp_path / "two" / "bag", "two/bag")]
    sources = fingerprint_inputs(found, known_sizes=set(), threads=2)
    assert [s.relpath for s in sources] == ["one/bag"]
    assert duplicate_inputs(found, sources) == [{"path": "two/bag", "same_as": "one/bag"}]
