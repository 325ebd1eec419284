"""Issue 56 item 5: ROS 1 bag chunks are checked against the decompression limits before ``rosbags`` inflates
them without a bound (an 8 KB bz2 bag took ingest to 677 MB and inspect to 1.1 GB)."""

from __future__ import annotations

import struct
import subprocess
import sys
from pathlib import Path

import pytest
from rosbags.rosbag1 import Writer
from rosbags.typesys import Stores, get_typestore

from logpipe.errors import SourceError
from logpipe.formats.inflation import InflationError, check_ros1_bag
from logpipe.formats.rosbag import RosbagAdapter
from logpipe.inspect import inspect_paths
from logpipe.types import SourceFile

REPO = Path(__file__).resolve().parents[2]


def _bag(path: Path, text_bytes: int, compression: Writer.CompressionFormat) -> Path:
    store = get_typestore(Stores.ROS1_NOETIC)
    msg = store.types["std_msgs/msg/String"](data="a" * text_bytes)
    writer = Writer(path)
    writer.set_compression(compression)
    with writer:
        conn = writer.add_connection("/chatter", "std_msgs/msg/String", typestore=store)
        writer.write(conn, 1_000_000_000, store.serialize_ros1(msg, "std_msgs/msg/String"))
    return path


def test_a_bag_bomb_is_refused_before_it_is_inflated(tmp_path: Path) -> None:
    bomb = _bag(tmp_path / "bomb.bag", 64 << 20, Writer.CompressionFormat.BZ2)  # 64 MiB of 'a': ~100 bytes of bz2
    assert bomb.stat().st_size < 64 << 10
    with pytest.raises(InflationError, match="declares"):
        check_ros1_bag(bomb)
    with pytest.raises(SourceError, match="refused: chunk at byte"):
        RosbagAdapter().read([SourceFile(str(bomb), "bomb.bag", "0" * 64, 0)], keep_going=False)
    [report] = inspect_paths([bomb])
    assert "declares" in str(report.get("error")), report


def test_an_lz4_chunk_that_understates_its_size_is_refused(tmp_path: Path) -> None:
    """lz4 inflates at most ~255x, so a lie about the size is the danger: a chunk declaring 1 KiB."""
    bag = _bag(tmp_path / "lie.bag", 8 << 20, Writer.CompressionFormat.LZ4)
    check_ros1_bag(bag)  # honest: 8 MiB from ~33 KB passes
    data = bytearray(bag.read_bytes())
    at = data.index(struct.pack("<I", 9) + b"size=") + 9
    struct.pack_into("<I", data, at, 1024)
    bag.write_bytes(bytes(data))
    with pytest.raises(InflationError, match=r"lz4 chunk at byte \d+ inflates past the 1024 bytes it declares"):
        check_ros1_bag(bag)


def test_an_ordinary_compressed_bag_passes(tmp_path: Path) -> None:
    bag = _bag(tmp_path / "ok.bag", 200_000, Writer.CompressionFormat.BZ2)
    check_ros1_bag(bag)
    for real in sorted((REPO / "tests" / "data" / "rosbags").rglob("*.bag")):
        check_ros1_bag(real)


@pytest.mark.skipif(not Path("/proc/self/status").is_file(), reason="reads VmHWM from /proc (Linux)")
def test_inspect_of_a_bomb_stays_small(tmp_path: Path) -> None:
    """Peak memory of ``logpipe inspect`` on a 4.9 KB bz2 bag of 256 MiB, in a fresh process (ru_maxrss of the
    child): ~110 MB refused, 1.17 GB and 19 s when the limits are lifted (LOGPIPE_MAX_INFLATION=1e9)."""
    bomb = tmp_path / "bomb.bag"
    # Made in a child: a child's peak counts what it had when forked, so this process must stay small.
    subprocess.run([sys.executable, "-c", "import sys; from pathlib import Path; sys.path.insert(0, sys.argv[1]); "
                    "from test_decompression_bombs import Writer, _bag; "
                    "_bag(Path(sys.argv[2]), 256 << 20, Writer.CompressionFormat.BZ2)",
                    str(Path(__file__).parent), str(bomb)], check=True, timeout=300, cwd=REPO)
    # The child reports its own peak, VmHWM of its address space (ru_maxrss would count what this process held
    # when it forked the child).
    report_peak = ("import re, runpy, sys\n"
                   "sys.argv = ['logpipe', '-q', 'inspect', sys.argv[1]]\n"
                   "try:\n    runpy.run_module('logpipe.cli', run_name='__main__', alter_sys=True)\n"
                   "finally:\n    status = open('/proc/self/status').read()\n"
                   "    print('PEAK', re.search(r'VmHWM:\\s+(\\d+)', status).group(1), file=sys.stderr)\n")
    done = subprocess.run([sys.executable, "-c", report_peak, str(bomb)], capture_output=True, text=True,
                          timeout=120, check=False, cwd=REPO)
    assert "Traceback" not in done.stderr, done.stderr
    assert "declares" in done.stdout + done.stderr
    peak_kib = int(done.stderr.rsplit("PEAK ", 1)[1].split()[0])
    assert peak_kib < 400 * 1024  # the interpreter and its imports; no 256 MiB string, no copies
