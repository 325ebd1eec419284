"""Ingest throughput on Argoverse 1 CSVs replicated to >= 10,000 files, against the devkit's way.

Baseline (same run): ``pandas.read_csv`` per file and one ``pandas.concat`` — what argoverse-api's loader
does. Ours: ``logpipe ingest`` end to end (hash, parse, validate, Parquet shards, sample index, manifest),
without and with MCAP output. Each measurement runs in a fresh subprocess so its peak RSS (including worker
processes) is its own; ours is measured at two corpus sizes to show memory does not grow with file count.
Replicas differ in the AV's track id (same length), so content hashing does not merge them.
"""

from __future__ import annotations

import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[1]
SOURCE = REPO.parent / "shared" / "data" / "argoverse1" / "data"
FALLBACK = REPO / "tests" / "data" / "argoverse1"
AV_ID = b"00000000-0000-0000-0000-000000000000"

_CHILD = r"""
import json, os, resource, sys, time
from pathlib import Path


def tree_cpu():
    # CPU s of this process, its reaped children, and its live children: the worker server (still running
    # at exit) holds the CPU time of the pool workers it reaped.
    total = sum(getattr(resource.getrusage(who), f) for who in (resource.RUSAGE_SELF, resource.RUSAGE_CHILDREN)
                for f in ("ru_utime", "ru_stime"))
    for entry in os.listdir("/proc"):
        if entry.isdigit():
            try:
                with open(f"/proc/{entry}/stat") as fh:
                    fields = fh.read().rsplit(")", 1)[1].split()
            except OSError:
                continue
            if int(fields[1]) == os.getpid():
                total += sum(int(x) for x in fields[11:15]) / os.sysconf("SC_CLK_TCK")
    return total


mode, src, out = sys.argv[1], Path(sys.argv[2]), Path(sys.argv[3])
files = sorted(src.glob("*.csv"))
t0 = time.perf_counter()
if mode == "pandas":
    import pandas as pd
    frame = pd.concat([pd.read_csv(f) for f in files], ignore_index=True)
    rows = len(frame)
else:
    from logpipe.stages.ingest import IngestOptions, ingest
    summary = ingest([src], IngestOptions(out=out, write_mcap=mode.startswith("logpipe+mcap"),
                                          workers=1 if mode.endswith("@1") else 0))
    rows = summary["rows"]
seconds = time.perf_counter() - t0
usage = (resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN))
peak_kb = max(u.ru_maxrss for u in usage)
print(json.dumps({"files": len(files), "rows": rows, "seconds": seconds, "peak_rss_mb": peak_kb / 1024,
                  "cpu_seconds": tree_cpu()}))
"""


def make_corpus(folder: Path, n_files: int) -> int:
    """Write ``n_files`` distinct replicas of the real CSVs into ``folder``; returns the bytes written."""
    source = SOURCE if SOURCE.is_dir() else FALLBACK
    originals = [(p.stem, p.read_bytes()) for p in sorted(source.glob("*.csv"))]
    folder.mkdir(parents=True, exist_ok=True)
    total = 0
    for i in range(n_files):
        stem, blob = originals[i % len(originals)]
        replica = blob.replace(AV_ID, f"{i:08d}".encode() + AV_ID[8:])
        (folder / f"{i:06d}_{stem}.csv").write_bytes(replica)
        total += len(replica)
    return total


def _measure(mode: str, src: Path, work: Path) -> dict[str, Any]:
    out = work / f"out-{mode}"
    shutil.rmtree(out, ignore_errors=True)
    proc = subprocess.run([sys.executable, "-c", _CHILD, mode, str(src), str(out)],
                          capture_output=True, text=True, check=True)
    shutil.rmtree(out, ignore_errors=True)
    result: dict[str, Any] = json.loads(proc.stdout.strip().splitlines()[-1])
    return result


def _interleaved(modes: list[str], src: Path, work: Path, repeats: int) -> dict[str, dict[str, Any]]:
    """``repeats`` rounds of one run per mode, alternating (A B A B ...): the host's speed drifts by tens of
    percent over minutes, and alternating spreads the drift over every mode instead of biasing a ratio."""
    runs: dict[str, list[dict[str, Any]]] = {mode: [] for mode in modes}
    for _ in range(repeats):
        for mode in modes:
            runs[mode].append(_measure(mode, src, work))
    return {mode: _summary(mode, mode_runs) for mode, mode_runs in runs.items()}


def one_worker_mcap(work: Path, n_files: int = 2000, repeats: int = 3) -> dict[str, Any]:
    """Issue 66: ``n_files`` replicated AV1 files, the pandas baseline against ``logpipe ingest`` with MCAP on one
    worker process (``workers=1``), interleaved, median wall seconds: the ratio baseline / ours (1.0: as fast)."""
    make_corpus(work / "one", n_files)
    runs: dict[str, list[dict[str, Any]]] = {"pandas": [], "logpipe+mcap@1": []}
    for _ in range(repeats):
        for mode, mode_runs in runs.items():
            mode_runs.append(_measure(mode, work / "one", work))
    out = {mode: _summary(mode, mode_runs) for mode, mode_runs in runs.items()}
    ratio = out["pandas"]["median_seconds"] / out["logpipe+mcap@1"]["median_seconds"]
    return {"files": n_files, **out, "pandas_wall_over_ours": round(ratio, 3),
            "per_round": [round(p["seconds"] / o["seconds"], 3)
                          for p, o in zip(runs["pandas"], runs["logpipe+mcap@1"], strict=True)]}


def _median_run(mode: str, src: Path, work: Path, repeats: int) -> dict[str, Any]:
    return _summary(mode, [_measure(mode, src, work) for _ in range(repeats)])


def _summary(mode: str, runs: list[dict[str, Any]]) -> dict[str, Any]:
    seconds = statistics.median(r["seconds"] for r in runs)
    cpu = statistics.median(r["cpu_seconds"] for r in runs)
    return {"mode": mode, "files": runs[0]["files"], "rows": runs[0]["rows"], "median_seconds": round(seconds, 3),
            "files_per_s": round(runs[0]["files"] / seconds, 1),
            "peak_rss_mb": round(max(r["peak_rss_mb"] for r in runs), 1),
            "runs_seconds": [round(r["seconds"], 3) for r in runs],
            # Whole process tree (imports, hashing, pool start-up, workers): robust on a shared machine.
            "cpu_s_per_1000_files": round(1000 * cpu / runs[0]["files"], 3),
            "runs_cpu_seconds": [round(r["cpu_seconds"], 2) for r in runs]}


def floor_cpu(folder: Path, n_files: int = 1000) -> dict[str, float]:
    """CPU seconds per 1,000 files of the steps no CSV → Parquet pipeline here can skip, in batches of 250:
    read, sha256, join, one pyarrow parse per batch, one Parquet write per batch (what bounds the speed-up),
    and of the baseline's ``pandas.read_csv`` on the same files, in the same process."""
    import io

    import pyarrow.parquet as pq

    from logpipe.formats._text import join_bodies, parse_batch
    from logpipe.formats.argoverse1 import _TYPES, COLUMNS
    from logpipe.storage.io import parquet_options, sha256_bytes

    files = sorted(folder.glob("*.csv"))[:n_files]
    spent = dict.fromkeys(("read", "sha256", "join", "parse", "write"), 0.0)

    def timed(step: str, fn: Any) -> Any:
        start = time.process_time()
        out = fn()
        spent[step] += time.process_time() - start
        return out

    for lo in range(0, len(files), 250):
        blobs = timed("read", lambda lo=lo: [f.read_bytes() for f in files[lo:lo + 250]])
        timed("sha256", lambda blobs=blobs: [sha256_bytes(b) for b in blobs])
        batch = timed("join", lambda blobs=blobs: join_bodies(blobs, 1))
        table = timed("parse", lambda batch=batch: parse_batch(batch, COLUMNS, _TYPES, ","))
        timed("write", lambda table=table: pq.write_table(table, io.BytesIO(), **parquet_options(table.schema)))
    scale = 1000 / max(len(files), 1)
    result = {k: round(v * scale, 3) for k, v in spent.items()}
    result["total"] = round(sum(spent.values()) * scale, 3)
    import pandas as pd

    start = time.process_time()
    for f in files:
        pd.read_csv(f)
    result["pandas_read_csv"] = round((time.process_time() - start) * scale, 3)
    return result


def mcap_floor_cpu(folder: Path, n_files: int = 1000) -> float:
    """CPU seconds per 1,000 files of writing the MCAPs ingest writes for ``n_files`` of them, their records
    already serialized (read back from a real ingest), through the writer ingest writes them with
    (``logpipe.mcap.bulk``, each channel's messages handed over as one list) and its settings: what the MCAP output
    costs on top of ``floor_cpu`` with this library, before any encoding."""
    from benchmarks.mcap_floor import mcap_records, rewrite_bulk
    from logpipe.stages.ingest import IngestOptions, ingest

    with tempfile.TemporaryDirectory(prefix="logpipe-mcap-floor-") as tmp:
        part = Path(tmp) / "csv"
        part.mkdir()
        files = sorted(folder.glob("*.csv"))[:n_files]
        for f in files:
            (part / f.name).write_bytes(f.read_bytes())  # links to outside are refused
        ingest([part], IngestOptions(out=Path(tmp) / "ds", write_mcap=True, workers=1))
        logs = [mcap_records(path) for path in sorted((Path(tmp) / "ds").rglob("*.mcap"))]
        start = time.process_time()
        for i, records in enumerate(logs):
            rewrite_bulk(Path(tmp) / f"{i}.mcap", records)
        spent = time.process_time() - start
    return round(spent * 1000 / max(len(files), 1), 3)


def run(quick: bool = False) -> dict[str, Any]:
    """Measure and return the figures (JSON-able)."""
    n_large, n_small, repeats = (1_000, 250, 1) if quick else (10_000, 2_500, 5)
    load_before = os.getloadavg()
    with tempfile.TemporaryDirectory(prefix="logpipe-bench-") as tmp:
        work = Path(tmp)
        nbytes = make_corpus(work / "large", n_large)
        make_corpus(work / "small", n_small)
        paired = _interleaved(["pandas", "logpipe"], work / "large", work, repeats)
        baseline, ours = paired["pandas"], paired["logpipe"]
        ours_mcap = _median_run("logpipe+mcap", work / "large", work, 1)
        ours_small = _median_run("logpipe", work / "small", work, 1)
        floor = floor_cpu(work / "large")
        floor["mcap_write"] = mcap_floor_cpu(work / "large", 250 if quick else 1000)
        one_worker = one_worker_mcap(work, 2000, 1 if quick else 3)
    if baseline["rows"] != ours["rows"]:
        raise RuntimeError(f"row counts differ: pandas {baseline['rows']} vs logpipe {ours['rows']}")
    mcap_speedup = round(ours_mcap["files_per_s"] / baseline["files_per_s"], 2)
    mcap_bound = round(2 * baseline["cpu_s_per_1000_files"] / (floor["total"] + floor["mcap_write"]), 2)
    return {
        "benchmark": "ingest_argoverse1_csv",
        "corpus": {"files": n_large, "bytes": nbytes, "replicated_from": "69 real AV1 CSVs"},
        "baseline_pandas_read_csv_concat": baseline,
        "logpipe_ingest_parquet": ours,
        "logpipe_ingest_parquet_and_mcap": ours_mcap,
        "logpipe_ingest_parquet_small_corpus": ours_small,
        "speedup_vs_baseline": round(ours["files_per_s"] / baseline["files_per_s"], 2),
        # Per round (each round ran the baseline and ours back to back): how much the ratio moves with the host.
        "speedup_per_round": [round(b / o, 2) for b, o in zip(baseline["runs_seconds"], ours["runs_seconds"],
                                                               strict=True)],
        # CPU work per file, baseline / ours: the wall-clock speed-up on two otherwise idle cores is at most
        # twice this (ours uses both, the baseline one).
        "cpu_ratio_baseline_vs_ours": round(baseline["cpu_s_per_1000_files"] / ours["cpu_s_per_1000_files"], 2),
        "load_average_1min_before_after": [round(load_before[0], 2), round(os.getloadavg()[0], 2)],
        "speedup_with_mcap_vs_baseline": mcap_speedup,
        "peak_rss_ratio_large_vs_small_corpus": round(ours["peak_rss_mb"] / ours_small["peak_rss_mb"], 2),
        "floor_cpu_s_per_1000_files": floor,
        # Both cores doing only the floor's steps, against the baseline's whole run (its CPU per file: import,
        # read_csv, concat). An earlier version divided by read_csv alone in this process, which left out the
        # baseline's concat and import and so understated the bound (ours has measured above it).
        "best_possible_2_core_speedup_at_floor": round(2 * baseline["cpu_s_per_1000_files"] / floor["total"], 2),
        # The same with MCAP: the floor's steps plus writing ingest's MCAP records, already serialized.
        "best_possible_2_core_speedup_with_mcap_at_floor": mcap_bound,
        "one_worker_with_mcap_2000_files": one_worker,
        "target": ">= 4x baseline files/s (aim 10x); peak memory independent of file count",
        "targets": [  # issue 35: ingest with MCAP on against the same pandas baseline
            {"target": "ingest with MCAP: files/s over the pandas baseline", "measured": mcap_speedup,
             "required": 2.0, "met": mcap_speedup >= 2.0, "floor": mcap_bound,
             "share_of_floor": round(mcap_speedup / mcap_bound, 3)},
            {"target": "ingest with MCAP, one worker, 2,000 files: pandas wall / ours", "required": 0.75,
             "measured": one_worker["pandas_wall_over_ours"], "met": one_worker["pandas_wall_over_ours"] >= 0.75},
        ],
    }
