"""Measure CommonRoad readers side by side: logpipe's own (lxml) and the official ``commonroad-io``.

Why a script: the issue asked which reader to use, measured (install size, parse time per file, what each
rejects). ``commonroad-io`` cannot live in logpipe's environment (it pins ``protobuf==3.20.2``; logpipe and
``mcap-protobuf-support`` need protobuf >= 4.25), so it runs in a venv of its own, given by
``--commonroad-io-python``, through ``scripts/commonroad_io_probe.py``. Both readers parse the same files in the
same run, in interleaved rounds; medians are reported. Damaged variants are made from one real file in a temporary
folder and each reader's outcome is recorded (an error, or a silent read).

Usage::

    python -m venv /tmp/crio && /tmp/crio/bin/pip install commonroad-io
    python -m scripts.commonroad_readers --data ../shared/data/commonroad/ngsim \
        --commonroad-io-python /tmp/crio/bin/python
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from logpipe.errors import SourceError
from logpipe.formats.commonroad import CommonRoadAdapter
from logpipe.types import SourceFile

PROBE = Path(__file__).with_name("commonroad_io_probe.py")
DAMAGE: dict[str, tuple[str, str]] = {
    "unknown obstacle type": ("<type>car</type>", "<type>spaceship</type>"),
    "time step gap": ("<exact>1</exact>", "<exact>2</exact>"),
    "time going backwards": ("<exact>1</exact>", "<exact>0</exact>"),
    "NaN position": ("<x>-14.1891</x>", "<x>nan</x>"),
    "infinite position": ("<y>10.7437</y>", "<y>inf</y>"),
    "position 1e400": ("<x>-14.1891</x>", "<x>1e400</x>"),
    "text in a number": ("<x>-14.1891</x>", "<x>west</x>"),
    "NaN orientation": ("<exact>-1.5783</exact>", "<exact>NaN</exact>"),
    "negative length": ("<length>4.7244</length>", "<length>-4.7</length>"),
    "duplicate obstacle id": ('<obstacle id="405">', '<obstacle id="407">'),
    "negative time step size": ('timeStepSize="0.1"', 'timeStepSize="-1"'),
    "lanelet bound at infinity": ("<x>-15.1963</x>", "<x>inf</x>"),
    "entity declaration": ('<?xml version="1.0" encoding="utf-8"?>',
                           '<?xml version="1.0" encoding="utf-8"?><!DOCTYPE c [<!ENTITY a "x">]>'),
    "truncated file": ("</commonRoad>", ""),
}


def ours(paths: list[Path]) -> dict[str, dict[str, Any]]:
    """Parse each file with logpipe's adapter: seconds, ok, rows or the error."""
    adapter = CommonRoadAdapter()
    out: dict[str, dict[str, Any]] = {}
    for path in paths:
        started = time.perf_counter()
        try:
            parsed = adapter.read([SourceFile(str(path), path.name, "", path.stat().st_size)], keep_going=False)
            result: dict[str, Any] = {"ok": True, "states": parsed.tracks.num_rows}
        except SourceError as err:
            result = {"ok": False, "error": err.describe()[:200]}
        result["seconds"] = time.perf_counter() - started
        out[str(path)] = result
    return out


def theirs(python: str, paths: list[Path]) -> dict[str, dict[str, Any]]:
    """The same through commonroad-io in its own interpreter."""
    done = subprocess.run([python, str(PROBE), *map(str, paths)], capture_output=True, text=True, check=True)
    result: dict[str, dict[str, Any]] = json.loads(done.stdout.strip().splitlines()[-1])
    return result


_SIZES = ("import importlib.metadata as m, json\n"
          "print(json.dumps({d.metadata['Name'].lower().replace('_', '-'): sum(f.size or 0 for f in d.files or ())"
          " for d in m.distributions()}))")


def distribution_mb(python: str) -> dict[str, float]:
    """Installed size of each distribution of an interpreter (from its RECORD files), MB by normalised name."""
    done = subprocess.run([python, "-c", _SIZES], capture_output=True, text=True, check=True)
    return {name: size / 1e6 for name, size in json.loads(done.stdout).items()}


def install_cost(python: str) -> dict[str, Any]:
    """What each reader adds to logpipe's environment: commonroad-io and what it pulls in that logpipe lacks;
    for logpipe's reader, lxml."""
    theirs, mine = distribution_mb(python), distribution_mb(sys.executable)
    added = {k: round(v, 1) for k, v in sorted(theirs.items()) if k not in mine and k not in ("pip", "setuptools")}
    return {"commonroad-io adds (MB)": round(sum(added.values()), 1), "commonroad-io adds": added,
            "commonroad-io pins": "protobuf==3.20.2 (logpipe and mcap-protobuf-support need >= 4.25)",
            "logpipe reader adds (MB)": round(mine.get("lxml", 0.0), 1)}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, required=True, help="folder of CommonRoad XML files")
    ap.add_argument("--commonroad-io-python", required=True, help="python of a venv with commonroad-io installed")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--out", type=Path, default=Path("out/commonroad_readers.json"))
    args = ap.parse_args(argv)
    files = sorted(args.data.rglob("*.xml"))
    per_file: dict[str, list[list[float]]] = {"logpipe": [], "commonroad-io": []}
    for _ in range(args.rounds):
        mine, other = ours(files), theirs(args.commonroad_io_python, files)
        per_file["logpipe"].append([mine[str(p)]["seconds"] for p in files])
        per_file["commonroad-io"].append([other[str(p)]["seconds"] for p in files])
    medians = {k: statistics.median(statistics.median(r) for r in zip(*v, strict=True)) for k, v in per_file.items()}
    totals = {k: statistics.median(sum(r) for r in v) for k, v in per_file.items()}
    base = next(p for p in files if p.name == "USA_Peach-3_1_T-1.xml")
    outcomes: dict[str, dict[str, str]] = {}
    with tempfile.TemporaryDirectory() as tmp:
        damaged = []
        for name, (old, new) in DAMAGE.items():
            path = Path(tmp) / f"{name.replace(' ', '_')}.xml"
            path.write_text(base.read_text().replace(old, new, 1))
            damaged.append(path)
        mine, other = ours(damaged), theirs(args.commonroad_io_python, damaged)
        for name, path in zip(DAMAGE, damaged, strict=True):
            outcomes[name] = {k: ("refused: " + r["error"][:120]) if not r["ok"] else "read without an error"
                              for k, r in (("logpipe", mine[str(path)]), ("commonroad-io", other[str(path)]))}
    report = {"files": len(files), "rounds": args.rounds, "median_seconds_per_file": medians,
              "median_seconds_all_files": totals, "ratio_commonroad_io_to_logpipe": totals["commonroad-io"]
              / totals["logpipe"], "install": install_cost(args.commonroad_io_python), "damaged": outcomes}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(report, indent=1))
    print(json.dumps(report, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
