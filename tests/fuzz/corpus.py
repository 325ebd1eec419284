"""The damaged-input corpus: real samples (``tests/data``, and ``../shared/data`` when present) broken in
every way a user trial found, for every input format and the map files.

A ``Case`` builds its damaged input into a folder beside a good input of the same format (``build``), and
says whether the damage must be refused (``must_refuse``: absurd values that would otherwise land silently
changed) or may be harmless (a flipped byte inside a number that stays a valid number). Nothing here is
random: the positions are fractions of the sample's size, so the corpus is the same on every run.

``python -m tests.fuzz.corpus`` lists the cases (id, format, whether it needs ../shared).
"""

from __future__ import annotations

import os
import shutil
import struct
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
from pyarrow import feather

REPO = Path(__file__).resolve().parents[2]
BUNDLED = REPO / "tests" / "data"
SHARED = (REPO.parent / "shared" / "data").resolve()

Build = Callable[[Path], Path]
"""Writes the damaged input into the given folder; returns its path (a file, a folder or a special file)."""


@dataclass(frozen=True)
class Sample:
    """A real input of one format: ``good`` lands beside every damaged copy of ``victim``.

    Attributes:
        fmt: adapter name (``maps`` for map files).
        good: the clean input placed beside the damaged one (a file or a folder), None for maps.
        victim: the input that is damaged (a file; for folder inputs the file inside ``victim_dir``).
        victim_dir: for folder inputs (bags, sensor logs): the folder holding ``victim``.
        shared: needs ../shared/data.
        name: short label used in case ids.
    """

    fmt: str
    good: Path | None
    victim: Path
    name: str
    victim_dir: Path | None = None
    shared: bool = False


@dataclass(frozen=True)
class Case:
    """One damaged input.

    Attributes:
        id: stable, readable id (``<format>-<sample>-<damage>``).
        sample: what it was made from.
        damage: the kind of damage (for the summary).
        build: writes the damaged input into a folder; returns its path.
        must_refuse: the damage makes the input wrong (quarantine required; landing = silently wrong).
        fast: part of the quick subset run by ``make test``.
    """

    id: str
    sample: Sample
    damage: str
    build: Build
    must_refuse: bool
    fast: bool = False


# --- byte-level damage (any format)


def truncate(fraction: float) -> Callable[[bytes], bytes]:
    return lambda b: b[: int(len(b) * fraction)]


def flip(fraction: float) -> Callable[[bytes], bytes]:
    def apply(b: bytes) -> bytes:
        if not b:
            return b
        i = min(int(len(b) * fraction), len(b) - 1)
        return b[:i] + bytes([b[i] ^ 0xFF]) + b[i + 1:]

    return apply


def bom(b: bytes) -> bytes:
    return b"\xef\xbb\xbf" + b


def cr_only(b: bytes) -> bytes:
    return b.replace(b"\r\n", b"\n").replace(b"\n", b"\r")


def empty(_: bytes) -> bytes:
    return b""


def nul_inside(b: bytes) -> bytes:
    i = len(b) // 2
    return b[:i] + b"\x00" + b[i:]


def bad_utf8(b: bytes) -> bytes:
    i = len(b) // 3
    return b[:i] + b"\xc3\x28" + b[i:]


TRUNCATIONS = (0.0005, 0.01, 0.1, 0.33, 0.5, 0.9, 0.999)
FLIPS = (0.0, 0.001, 0.003, 0.01, 0.05, 0.2, 0.4, 0.6, 0.8, 0.95, 0.999)


def mcap_huge_length(b: bytes) -> bytes:
    """The first record after the magic claims 2^40 bytes (the length is a uint64 after its opcode)."""
    return b[:9] + struct.pack("<Q", 1 << 40) + b[17:]


def mcap_huge_chunk(b: bytes) -> bytes:
    """The first chunk (opcode 0x06) claims 2^40 bytes decompressed (a uint64 after start/end times)."""
    pos = 8
    while pos + 9 <= len(b):
        opcode, length = b[pos], struct.unpack_from("<Q", b, pos + 1)[0]
        if opcode == 0x06:
            at = pos + 9 + 16
            return b[:at] + struct.pack("<Q", 1 << 40) + b[at + 8:]
        pos += 9 + length
    return mcap_huge_length(b)


def rosbag1_huge_length(b: bytes) -> bytes:
    """The first record after the ROS1 magic (13 bytes) claims a header of 2^31 - 1 bytes."""
    return b[:13] + struct.pack("<i", 2**31 - 1) + b[17:]


def rosbag1_huge_data(b: bytes) -> bytes:
    """The bag-header record's data length (after its header) claims 2^31 - 1 bytes."""
    header_len = struct.unpack_from("<i", b, 13)[0]
    at = 17 + header_len
    return b[:at] + struct.pack("<i", 2**31 - 1) + b[at + 4:]


BYTES_DAMAGE: dict[str, Callable[[bytes], bytes]] = {
    **{f"trunc{f:g}": truncate(f) for f in TRUNCATIONS},
    **{f"flip{f:g}": flip(f) for f in FLIPS},
    "empty": empty,
}
TEXT_BYTES_DAMAGE: dict[str, Callable[[bytes], bytes]] = {
    "bom": bom, "cr-only": cr_only, "nul": nul_inside, "bad-utf8": bad_utf8,
}
HARMLESS_OK = {"flip", "trunc"}  # may land when what is left is valid


# --- special files (any format)


def special_builds(target_name: str) -> dict[str, Build]:
    def dangling(folder: Path) -> Path:
        path = folder / target_name
        path.symlink_to(folder / "does-not-exist")
        return path

    def dev_zero(folder: Path) -> Path:
        path = folder / target_name
        path.symlink_to("/dev/zero")
        return path

    def fifo(folder: Path) -> Path:
        path = folder / target_name
        os.mkfifo(path)
        return path

    def directory(folder: Path) -> Path:
        path = folder / target_name
        path.mkdir()
        (path / "README").write_text("a folder named like an input\n")
        return path

    return {"dangling-link": dangling, "dev-zero-link": dev_zero, "fifo": fifo, "dir-named-like-input": directory}


# --- text formats: lines edited in place

Lines = list[list[str]]


@dataclass(frozen=True)
class TextLayout:
    header: int
    sep: str
    eol: str
    time: int
    track: int
    x: int
    y: int


LAYOUTS = {
    "argoverse1": TextLayout(header=1, sep=",", eol="\n", time=0, track=1, x=3, y=4),
    "ethucy": TextLayout(header=0, sep="\t", eol="\n", time=0, track=1, x=2, y=3),
    "apolloscape": TextLayout(header=0, sep=" ", eol="\r\n", time=0, track=1, x=3, y=4),
}


def _edit_text(layout: TextLayout, edit: Callable[[Lines, TextLayout], Lines]) -> Callable[[bytes], bytes]:
    def apply(b: bytes) -> bytes:
        text = b.decode()
        raw = [line for line in text.splitlines()]
        head, body = raw[: layout.header], raw[layout.header:]
        split = [line.split(layout.sep) for line in body if line.strip()]
        out = edit(split, layout)
        return (layout.eol.join(head + [layout.sep.join(f) for f in out]) + layout.eol).encode()

    return apply


def _set(field: str, value: Callable[[str], str], where: float) -> Callable[[Lines, TextLayout], Lines]:
    def edit(lines: Lines, layout: TextLayout) -> Lines:
        col = getattr(layout, field)
        k = min(int(len(lines) * where), len(lines) - 1)
        lines = [list(f) for f in lines]
        lines[k][col] = value(lines[k][col])
        return lines

    return edit


def _all(field: str, value: Callable[[str], str]) -> Callable[[Lines, TextLayout], Lines]:
    def edit(lines: Lines, layout: TextLayout) -> Lines:
        col = getattr(layout, field)
        return [[value(v) if i == col else v for i, v in enumerate(f)] for f in lines]

    return edit


def _duplicate(where: float) -> Callable[[Lines, TextLayout], Lines]:
    def edit(lines: Lines, layout: TextLayout) -> Lines:
        k = min(int(len(lines) * where), len(lines) - 1)
        return [*lines[:k + 1], list(lines[k]), *lines[k + 1:]]

    return edit


def _backwards(lines: Lines, layout: TextLayout) -> Lines:
    return [lines[-1], *lines[1:-1], lines[0]]


def _plus(amount: float) -> Callable[[str], str]:
    return lambda v: repr(float(v) + amount)


def text_edits(fmt: str) -> dict[str, tuple[Callable[[Lines, TextLayout], Lines], bool]]:
    """Structured damage of a text format: name -> (edit, must_refuse)."""
    edits: dict[str, tuple[Callable[[Lines, TextLayout], Lines], bool]] = {}
    for where in (0.0, 0.5, 0.999):
        w = f"@{where:g}"
        edits |= {
            f"time-1e20{w}": (_set("time", lambda v: "1e20", where), True),
            f"x-nan{w}": (_set("x", lambda v: "nan", where), True),
            f"y-inf{w}": (_set("y", lambda v: "inf", where), True),
            f"x-neg-inf{w}": (_set("x", lambda v: "-inf", where), True),
            f"duplicate-row{w}": (_duplicate(where), True),
            f"x-not-a-number{w}": (_set("x", lambda v: "abc", where), True),
        }
        # Issue 56's hostile values: physically absurd, each one input's refusal (never stored as given).
        edits |= {
            f"x-1e12{w}": (_set("x", lambda v: "1e12", where), True),
            f"y-neg-4e9{w}": (_set("y", lambda v: "-4e9", where), True),
            f"x-1e300{w}": (_set("x", lambda v: "1e300", where), True),
            f"y-1e400{w}": (_set("y", lambda v: "1e400", where), True),
        }
        if fmt == "argoverse1":
            edits[f"track-control{w}"] = (_set("track", lambda v: v[:4] + "\x01" + v[4:], where), True)
        else:
            edits[f"frame-negative{w}"] = (_set("time", lambda v: "-400", where), True)
    edits["time-backwards"] = (_backwards, True)
    edits["extra-column"] = (_set("y", lambda v: v + ("," if fmt == "argoverse1" else "\t" if fmt == "ethucy"
                                                      else " ") + "1", 0.5), True)
    if fmt == "argoverse1":
        edits |= {
            "time-1e10s": (_set("time", lambda v: "10000000000.5", 0.5), True),
            "time-21-digits": (_set("time", lambda v: "100000000000000000000.5", 0.5), True),
            "time-all-plus-1e12": (_all("time", lambda v: str(int(float(v)) + 10**12) + ".5"), True),
            "time-negative": (_set("time", lambda v: "-" + v, 0.5), True),
            "track-empty": (_set("track", lambda v: "", 0.5), False),
        }
    else:
        edits |= {
            "frame-all-plus-1e12": (_all("time", _plus(1e12)), True),
            "frame-1e19": (_set("time", lambda v: "1e19", 0.5), True),
            "id-1e19": (_set("track", lambda v: "1e19", 0.5), True),
            "id-all-1e19": (_all("track", lambda v: repr(float(v) + 1e19)), True),
            "frame-fraction": (_set("time", lambda v: v + ".5" if "." not in v else v + "5", 0.5), True),
        }
    return edits


# --- AV2: tables edited with pyarrow


def _parquet_edit(edit: Callable[[pa.Table], pa.Table]) -> Callable[[Path, Path], None]:
    def apply(src: Path, dst: Path) -> None:
        pq.write_table(edit(pq.read_table(src)), dst)

    return apply


def _feather_edit(edit: Callable[[pa.Table], pa.Table]) -> Callable[[Path, Path], None]:
    def apply(src: Path, dst: Path) -> None:
        feather.write_feather(edit(feather.read_table(src)), dst)

    return apply


def _set_rows(table: pa.Table, column: str, rows: slice | list[int], value: object) -> pa.Table:
    values = table.column(column).to_numpy(zero_copy_only=False).copy()
    values[rows] = value
    i = table.schema.get_field_index(column)
    return table.set_column(i, column, pa.array(values, table.schema.field(column).type))


def _dup_rows(table: pa.Table, row: int) -> pa.Table:
    return pa.concat_tables([table.slice(0, row + 1), table.slice(row, 1), table.slice(row + 1)])


def _swap_rows(table: pa.Table, a: int, b: int) -> pa.Table:
    order = list(range(table.num_rows))
    order[a], order[b] = order[b], order[a]
    return table.take(pa.array(order))


def scenario_edits() -> dict[str, tuple[Callable[[pa.Table], pa.Table], bool]]:
    mid = 500
    return {
        "start-1e20": (lambda t: _set_rows(t, "start_timestamp", slice(None), 1e20), True),
        "end-nan": (lambda t: _set_rows(t, "end_timestamp", slice(None), float("nan")), True),
        "start-negative": (lambda t: _set_rows(t, "start_timestamp", slice(None), -1e18), True),
        "steps-1e12": (lambda t: _set_rows(t, "num_timestamps", slice(None), 10**12), True),
        "x-nan": (lambda t: _set_rows(t, "position_x", [mid], float("nan")), True),
        "heading-inf": (lambda t: _set_rows(t, "heading", [mid], float("inf")), True),
        "vx-nan-all": (lambda t: _set_rows(t, "velocity_x", slice(None), float("nan")), True),
        "duplicate-row": (lambda t: _dup_rows(t, mid), True),
        "timestep-backwards": (lambda t: _swap_rows(t, mid, mid + 1), True),
        "timestep-huge": (lambda t: _set_rows(t, "timestep", [mid], 2**62), True),
        "id-traversal": (lambda t: _set_rows(t, "scenario_id", slice(None), "../../../x"), True),
        "id-empty": (lambda t: _set_rows(t, "scenario_id", slice(None), ""), True),
        "id-nul": (lambda t: _set_rows(t, "scenario_id", slice(None), "a\x00b"), True),
        "id-slash": (lambda t: _set_rows(t, "scenario_id", slice(None), "a/b"), True),
        "id-long": (lambda t: _set_rows(t, "scenario_id", slice(None), "x" * 300), True),
        "no-rows": (lambda t: t.slice(0, 0), True),
        "column-dropped": (lambda t: t.drop_columns(["heading"]), True),
    }


def sensor_edits() -> dict[str, tuple[str, Callable[[pa.Table], pa.Table], bool]]:
    """name -> (which file: ego/ann, edit, must_refuse)."""
    zero_q = {c: 0.0 for c in ("qw", "qx", "qy", "qz")}

    def zero_quaternion(rows: slice | list[int]) -> Callable[[pa.Table], pa.Table]:
        def edit(t: pa.Table) -> pa.Table:
            for c, v in zero_q.items():
                t = _set_rows(t, c, rows, v)
            return t

        return edit

    return {
        "ego-zero-quaternion-one": ("ego", zero_quaternion([100]), True),
        "ego-zero-quaternion-all": ("ego", zero_quaternion(slice(None)), True),
        "ann-zero-quaternion": ("ann", zero_quaternion([100]), True),
        "ego-tx-nan": ("ego", lambda t: _set_rows(t, "tx_m", [50], float("nan")), True),
        "ann-ty-inf": ("ann", lambda t: _set_rows(t, "ty_m", [50], float("inf")), True),
        "ann-length-nan": ("ann", lambda t: _set_rows(t, "length_m", [50], float("nan")), True),
        "ego-time-duplicate": ("ego", lambda t: _dup_rows(t, 100), True),
        "ego-time-backwards": ("ego", lambda t: _swap_rows(t, 100, 101), True),
        "ann-time-huge": ("ann", lambda t: _set_rows(t, "timestamp_ns", [50], 2**63 - 1), True),
        "ann-duplicate-row": ("ann", lambda t: _dup_rows(t, 50), True),
        "ego-time-negative": ("ego", lambda t: _set_rows(t, "timestamp_ns", slice(None), -1), True),
    }


# --- samples


def samples() -> list[Sample]:
    out = [
        Sample("argoverse1", BUNDLED / "argoverse1" / "2645.csv", BUNDLED / "argoverse1" / "3861.csv", "av1"),
        Sample("ethucy", BUNDLED / "ethucy" / "hotel" / "test" / "biwi_hotel.txt",
               BUNDLED / "ethucy" / "eth" / "test" / "biwi_eth.txt", "eth"),
        Sample("apolloscape", BUNDLED / "apolloscape" / "result_9048_1_frame.txt",
               BUNDLED / "apolloscape" / "result_9049_4_frame.txt", "apollo"),
        Sample("rosbag", BUNDLED / "rosbags" / "datmo" / "intersection.bag",
               BUNDLED / "rosbags" / "datmo" / "intersection.bag", "datmo"),
        Sample("maps", None, BUNDLED / "maps" / "PIT_lane_centerlines_crop_3861.npz", "npz"),
        Sample("maps", None, BUNDLED / "maps" / "log_map_archive_0a1e6f0a-1817-4a98-b02e-db8c9327d151.json",
               "av2json"),
        Sample("maps", None, BUNDLED / "maps" / "lanelet2_fixture.osm", "osm"),
        # More real files of the text formats (issue 56 grew the corpus past 1,000 damaged inputs).
        Sample("argoverse1", BUNDLED / "argoverse1" / "2645.csv", BUNDLED / "argoverse1" / "3700.csv", "av1b"),
        Sample("argoverse1", BUNDLED / "argoverse1" / "2645.csv", BUNDLED / "argoverse1" / "4791.csv", "av1c"),
        Sample("ethucy", BUNDLED / "ethucy" / "eth" / "test" / "biwi_eth.txt",
               BUNDLED / "ethucy" / "hotel" / "test" / "biwi_hotel.txt", "hotel"),
        Sample("apolloscape", BUNDLED / "apolloscape" / "result_9049_4_frame.txt",
               BUNDLED / "apolloscape" / "result_9048_1_frame.txt", "apollo2"),
    ]
    s = SHARED
    av2 = s / "av2"
    sensor = av2 / "sensor_logs"
    out += [
        Sample("argoverse1", None, s / "argoverse1" / "data" / "1.csv", "av1s", shared=True),
        Sample("argoverse1", BUNDLED / "argoverse1" / "2645.csv", s / "argoverse1" / "data" / "10.csv", "av1s10",
               shared=True),
        Sample("ethucy", BUNDLED / "ethucy" / "hotel" / "test" / "biwi_hotel.txt",
               s / "ethucy" / "zara1" / "val" / "uni_examples_val.txt", "univval", shared=True),
        Sample("ethucy", BUNDLED / "ethucy" / "hotel" / "test" / "biwi_hotel.txt",
               s / "ethucy" / "zara1" / "val" / "crowds_zara03_val.txt", "zara3val", shared=True),
        Sample("apolloscape", BUNDLED / "apolloscape" / "result_9048_1_frame.txt",
               s / "apolloscape" / "prediction_train" / "result_9050_2_frame.txt", "apollos", shared=True),
        Sample("rosbag", None, s / "rosbags" / "evo" / "tf_example.bag", "ros1tf", shared=True),
        Sample("rosbag", None, s / "rosbags" / "webviz" / "example-bz2.bag", "ros1bz2", shared=True),
        Sample("rosbag", None, s / "rosbags" / "evo" / "tf_example" / "tf_example.db3", "ros2db3",
               victim_dir=s / "rosbags" / "evo" / "tf_example", shared=True),
        # No ROS2 MCAP bag here has topics logpipe tracks: a ROS2 sqlite3 bag is the good input beside it.
        Sample("rosbag", s / "rosbags" / "evo" / "tf_example", s / "rosbags" / "rosbag2" / "rosbag2_tests"
               / "resources" / "mcap" / "cdr_test"
               / "cdr_test_0.mcap", "ros2mcap",
               victim_dir=s / "rosbags" / "rosbag2" / "rosbag2_tests" / "resources" / "mcap" / "cdr_test",
               shared=True),
        Sample("mcap", s / "mcap" / "evo" / "nav2_turtlebot.mcap", s / "mcap" / "evo" / "nav2_turtlebot.mcap",
               "nav2", shared=True),
        Sample("mcap", s / "mcap" / "evo" / "nav2_turtlebot.mcap", s / "mcap" / "coscene" / "example.mcap",
               "coscene", shared=True),
        Sample("argoverse2", None, next(iter(sorted(av2.glob("scenario_*.parquet"))), av2 / "missing.parquet"),
               "scenario", shared=True),
        Sample("argoverse2", sensor / "adcf7d18-0510-35b0-a2fa-b4cea13a6d76",
               sensor / "7fab2350-7eaf-3b7e-a39d-6937a4c1bede" / "city_SE3_egovehicle.feather", "sensor",
               victim_dir=sensor / "7fab2350-7eaf-3b7e-a39d-6937a4c1bede", shared=True),
        Sample("maps", None, s / "argoverse1" / "maps" / "lane_centerlines" / "derived"
               / "MIA_lane_centerlines.npz", "npzcity", shared=True),
    ]
    return out


SUFFIX = {"argoverse1": ".csv", "ethucy": ".txt", "apolloscape": ".txt"}


def _good_name(sample: Sample) -> str:
    assert sample.good is not None
    return sample.good.name if sample.fmt != "rosbag" else "a_good" + sample.good.suffix


def place_good(sample: Sample, folder: Path) -> Path | None:
    """Copy the good input of ``sample`` into ``folder`` (a scenario/mcap good copy gets its own log id)."""
    if sample.fmt == "argoverse2" and sample.good is None:  # one real scenario: a copy with another id is the good one
        t = pq.read_table(sample.victim)
        t = _set_rows(t, "scenario_id", slice(None), "good-" + str(t.column("scenario_id")[0].as_py()))
        path = folder / "scenario_good.parquet"
        pq.write_table(t, path)
        return path
    if sample.fmt == "maps":
        return None
    if sample.good is None and sample.victim_dir is not None:  # a folder input: an intact copy is the good one
        target = folder / "a_good"
        shutil.copytree(sample.victim_dir, target)
        return target
    good = sample.good if sample.good is not None else sample.victim
    if good.is_dir():
        target = folder / good.name
        shutil.copytree(good, target)
        return target
    name = _good_name(sample) if sample.good is not None else "a_good" + good.suffix
    target = folder / name
    shutil.copyfile(good, target)
    return target


def _victim_name(sample: Sample, tag: str) -> str:
    if sample.fmt == "maps":  # map files are found by name (city, log id)
        return sample.victim.name
    if sample.fmt == "argoverse1":
        return f"z_{tag}.csv"
    if sample.fmt == "argoverse2" and sample.victim_dir is None:
        return "scenario_" + sample.victim.stem.removeprefix("scenario_") + ".parquet"
    return f"z_{tag}{sample.victim.suffix}"


def _write_damaged(sample: Sample, folder: Path, tag: str, blob: bytes) -> Path:
    """The damaged bytes as the victim input: a file, or the victim file inside a copy of its folder."""
    if sample.victim_dir is not None:
        target = folder / f"z_{tag}"
        shutil.copytree(sample.victim_dir, target)
        (target / sample.victim.name).chmod(0o644)
        (target / sample.victim.name).write_bytes(blob)
        return target
    path = folder / _victim_name(sample, tag)
    path.write_bytes(blob)
    return path


def _bytes_case(sample: Sample, name: str, damage: Callable[[bytes], bytes], refuse: bool) -> Build:
    def build(folder: Path) -> Path:
        return _write_damaged(sample, folder, name.replace(".", "_"), damage(sample.victim.read_bytes()))

    return build


def _special_case(sample: Sample, kind: str) -> Build:
    def build(folder: Path) -> Path:
        name = _victim_name(sample, kind) if sample.victim_dir is None else f"z_{kind}.bag"
        if sample.fmt == "argoverse2":
            name = "scenario_z.parquet"
        if sample.fmt == "maps":
            name = sample.victim.name
        return special_builds(name)[kind](folder)

    return build


def _table_case(sample: Sample, name: str, apply: Callable[[Path, Path], None], which: str | None) -> Build:
    def build(folder: Path) -> Path:
        if sample.victim_dir is None:
            path = folder / _victim_name(sample, name)
            apply(sample.victim, path)
            return path
        target = folder / f"z_{name}"
        shutil.copytree(sample.victim_dir, target)
        file = "city_SE3_egovehicle.feather" if which == "ego" else next(
            p.name for p in sorted(target.glob("annotations*.feather")))
        (target / file).chmod(0o644)
        apply(sample.victim_dir / file, target / file)
        return target

    return build


FAST = {
    "argoverse1-av1-trunc0.5", "argoverse1-av1-flip0.4", "argoverse1-av1-bom", "argoverse1-av1-cr-only",
    "argoverse1-av1-time-1e10s", "argoverse1-av1-x-nan@0.5", "argoverse1-av1-duplicate-row@0.5",
    "argoverse1-av1-time-backwards", "argoverse1-av1-dangling-link", "argoverse1-av1-fifo",
    "argoverse1-av1-dev-zero-link", "argoverse1-av1-empty", "argoverse1-av1-bad-utf8",
    "ethucy-eth-bom", "ethucy-eth-cr-only", "ethucy-eth-frame-1e19", "ethucy-eth-id-1e19",
    "ethucy-eth-frame-all-plus-1e12", "ethucy-eth-y-inf@0", "ethucy-eth-duplicate-row@0.999",
    "ethucy-eth-trunc0.33", "ethucy-eth-flip0.01", "ethucy-eth-nul", "ethucy-eth-dir-named-like-input",
    "apolloscape-apollo-frame-all-plus-1e12", "apolloscape-apollo-id-all-1e19", "apolloscape-apollo-bom",
    "apolloscape-apollo-cr-only", "apolloscape-apollo-x-neg-inf@0.999", "apolloscape-apollo-time-backwards",
    "apolloscape-apollo-flip0.6", "apolloscape-apollo-fifo",
    "rosbag-datmo-trunc0.5", "rosbag-datmo-flip0.001", "rosbag-datmo-huge-header", "rosbag-datmo-empty",
    "rosbag-datmo-dangling-link",
    "maps-npz-flip0.5", "maps-npz-trunc0.5", "maps-av2json-trunc0.5", "maps-osm-trunc0.5",
    "argoverse1-av1-x-1e12@0.5", "argoverse1-av1-track-control@0.5", "ethucy-eth-frame-negative@0.5",
    "apolloscape-apollo-frame-negative@0", "ethucy-hotel-y-1e400@0.999", "argoverse1-av1b-x-1e300@0",
}


def cases() -> list[Case]:  # noqa: PLR0912  one flat branch per damage family
    out: list[Case] = []

    def add(sample: Sample, damage: str, build: Build, refuse: bool) -> None:
        case_id = f"{sample.fmt}-{sample.name}-{damage}"
        out.append(Case(case_id, sample, damage, build, refuse, fast=case_id in FAST and not sample.shared))

    for sample in samples():
        for name, fn in BYTES_DAMAGE.items():
            refuse = name == "empty" or not any(name.startswith(h) for h in HARMLESS_OK)
            add(sample, name, _bytes_case(sample, name, fn, refuse), refuse)
        if sample.fmt in LAYOUTS:
            for name, fn in TEXT_BYTES_DAMAGE.items():
                add(sample, name, _bytes_case(sample, name, fn, True), True)
            for name, (edit, refuse) in text_edits(sample.fmt).items():
                add(sample, name, _bytes_case(sample, name, _edit_text(LAYOUTS[sample.fmt], edit), refuse), refuse)
        if sample.fmt == "mcap" or sample.victim.suffix == ".mcap":
            add(sample, "huge-record", _bytes_case(sample, "huge-record", mcap_huge_length, True), True)
            add(sample, "huge-chunk", _bytes_case(sample, "huge-chunk", mcap_huge_chunk, True), True)
        if sample.victim.suffix == ".bag":
            add(sample, "huge-header", _bytes_case(sample, "huge-header", rosbag1_huge_length, True), True)
            # The bag-header record's data is padding and readers seek by the header's index position: a huge
            # claimed padding length may be harmless.
            add(sample, "huge-data", _bytes_case(sample, "huge-data", rosbag1_huge_data, False), False)
        if sample.fmt == "argoverse2" and sample.victim_dir is None:
            for name, (edit, refuse) in scenario_edits().items():
                add(sample, name, _table_case(sample, name, _parquet_edit(edit), None), refuse)
        if sample.fmt == "argoverse2" and sample.victim_dir is not None:
            for name, (which, edit, refuse) in sensor_edits().items():
                add(sample, name, _table_case(sample, name, _feather_edit(edit), which), refuse)
        if sample.fmt != "maps" or sample.name == "npz":
            for kind in special_builds("x"):
                if sample.victim_dir is not None and kind == "dir-named-like-input":
                    continue  # a folder is what these inputs are
                add(sample, kind, _special_case(sample, kind), kind != "dir-named-like-input")
        if sample.fmt == "maps" and sample.name in ("npz", "npzcity"):
            add(sample, "npz-nan-points", _npz_nan(sample), True)
    return out


def _npz_nan(sample: Sample) -> Build:
    def build(folder: Path) -> Path:
        with np.load(sample.victim, allow_pickle=False) as z:
            arrays = {k: z[k] for k in z.files}
        arrays["points"] = arrays["points"].astype(np.float64)
        arrays["points"][3] = np.nan
        path = folder / sample.victim.name
        np.savez(path, **arrays)
        return path

    return build


def available(case: Case) -> bool:
    """Whether the case's sample files exist here (../shared may be absent)."""
    paths = [case.sample.victim] + ([case.sample.good] if case.sample.good is not None else [])
    return all(p.exists() for p in paths)


if __name__ == "__main__":  # pragma: no cover
    all_cases = cases()
    for c in all_cases:
        print(c.id, "shared" if c.sample.shared else "", "fast" if c.fast else "")
    print(len(all_cases), "cases,", sum(c.fast for c in all_cases), "fast")
