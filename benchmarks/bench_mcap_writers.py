"""The MCAP writers we could write with, on our own records: every record of the MCAPs ingest writes for real
Argoverse 1 logs (already serialized, read back), written again by each candidate, in interleaved rounds (median
CPU seconds, ratios to the ``mcap`` writer with the stages' old settings measured in the same rounds).

Candidates: the pure-Python ``mcap`` writer as the stages used it (zstd, 1 MiB chunks), with 16 MiB chunks, and
with the least per-record work it allows (no CRCs, no indexes: not a file we could ship, only how far that writer
goes); the Rust writer of ``foxglove-sdk`` as ``logpipe.mcap.native`` drives it (a ``Context`` per file, channels
from ``Context._create_channel``), and through the public ``foxglove.Channel`` wrapper; ``logpipe.mcap.bulk`` (each
channel's messages handed over as one list, the file laid out whole) at zstd levels -5, -3, -1, 1, 3 and 5 and with
lz4 chunks (the format's other compression), with the bytes each writes (how ``bulk.COMPRESSION_LEVEL`` was chosen:
size against CPU).
"""

from __future__ import annotations

import statistics
import tempfile
import time
from collections.abc import Callable
from functools import partial
from pathlib import Path
from typing import Any

from benchmarks.mcap_floor import mcap_records, rewrite_bulk, rewrite_mcap, rewrite_native

REPO = Path(__file__).resolve().parents[1]
SOURCE = REPO.parent / "shared" / "data" / "argoverse1" / "data"
FALLBACK = REPO / "tests" / "data" / "argoverse1"


def _mcap_writer(**settings: Any) -> Callable[[Path, list[Any]], None]:
    from mcap.writer import CompressionType, Writer

    def write(target: Path, records: list[Any]) -> None:
        with target.open("wb") as fh:
            rewrite_mcap(Writer(fh, compression=CompressionType.ZSTD, **settings), records)

    return write


def _public_channel(target: Path, records: list[Any]) -> None:
    """``rewrite_native`` through ``foxglove.Channel`` (and its per-message Python checks)."""
    import foxglove
    from foxglove.mcap import MCAPWriteOptions
    from mcap.records import Channel, Message, Metadata, Schema

    context = foxglove.Context()
    schemas: dict[int, Any] = {}
    channels: dict[int, Any] = {}
    with foxglove.open_mcap(target, allow_overwrite=True, context=context,
                            writer_options=MCAPWriteOptions(compression_threads=0)) as writer:
        for r in records:
            if isinstance(r, Schema):
                schemas[r.id] = foxglove.Schema(name=r.name, encoding=r.encoding, data=bytes(r.data))
            elif isinstance(r, Channel):
                channels[r.id] = foxglove.Channel(r.topic, schema=schemas[r.schema_id],
                                                  message_encoding=r.message_encoding, context=context)
            elif isinstance(r, Message):
                channels[r.channel_id].log(r.data, log_time=r.log_time)
            elif isinstance(r, Metadata):
                writer.write_metadata(r.name, dict(r.metadata))


def candidates() -> dict[str, Callable[[Path, list[Any]], None]]:
    """Name -> writer of one file's records."""
    from mcap.writer import IndexType

    from logpipe.mcap.bulk import COMPRESSION_LEVEL

    return {
        "mcap (zstd, 1 MiB chunks: the stages' old writer)": _mcap_writer(),
        "mcap, 16 MiB chunks": _mcap_writer(chunk_size=16 << 20),
        "mcap, no CRCs or indexes (not shippable)": _mcap_writer(index_types=IndexType.NONE, enable_crcs=False),
        "foxglove-sdk, logpipe.mcap.native (the stages' writer until issue 66)": rewrite_native,
        "foxglove-sdk, public foxglove.Channel": _public_channel,
        **{f"logpipe.mcap.bulk, zstd level {level}{' (the stages)' if level == COMPRESSION_LEVEL else ''}":
           partial(_bulk, level=level) for level in (-5, -3, -1, 1, 3, 5)},
        "logpipe.mcap.bulk, lz4 (frame, level 0)": partial(_bulk, level=0, compression="lz4"),
    }


def _bulk(target: Path, records: list[Any], level: int, compression: str = "zstd") -> None:
    rewrite_bulk(target, records, level=level, compression=compression)


def run(quick: bool = False) -> dict[str, Any]:
    """Measure and return the figures (JSON-able)."""
    from logpipe.stages.ingest import IngestOptions, ingest

    rounds = 3 if quick else 5
    source = SOURCE if SOURCE.is_dir() else FALLBACK
    writers = candidates()
    spent: dict[str, list[float]] = {name: [] for name in writers}
    sizes: dict[str, int] = {}
    with tempfile.TemporaryDirectory(prefix="logpipe-mcap-writers-") as tmp:
        part = Path(tmp) / "csv"
        part.mkdir()
        for f in sorted(source.glob("*.csv")):  # the 69 real logs
            (part / f.name).write_bytes(f.read_bytes())  # links to outside are refused
        ingest([part], IngestOptions(out=Path(tmp) / "ds", write_mcap=True, workers=1))
        logs = [mcap_records(path) for path in sorted((Path(tmp) / "ds").rglob("*.mcap"))]
        messages = sum(type(r).__name__ == "Message" for records in logs for r in records)
        nbytes = sum(len(r.data) for records in logs for r in records if type(r).__name__ == "Message")
        for _ in range(rounds):
            for k, (name, write) in enumerate(writers.items()):
                start = time.process_time()
                for i, records in enumerate(logs):
                    write(Path(tmp) / f"{k}-{i}.mcap", records)
                spent[name].append(time.process_time() - start)
                sizes[name] = sum(p.stat().st_size for p in Path(tmp).glob(f"{k}-*.mcap"))
    base = statistics.median(spent[next(iter(writers))])
    rows = {}
    for name, times in spent.items():
        cpu = statistics.median(times)
        rows[name] = {"records_per_cpu_s": round(messages / cpu), "files_per_cpu_s": round(len(logs) / cpu, 1),
                      "speedup_vs_mcap": round(base / cpu, 2), "file_bytes": sizes[name],
                      "runs_cpu_s": [round(t, 4) for t in times]}
    return {"benchmark": "mcap_writers", "files": len(logs), "messages": messages,
            "mean_message_bytes": round(nbytes / max(messages, 1)), "rounds": rounds, "writers": rows}


if __name__ == "__main__":
    import json
    import sys

    print(json.dumps(run(quick="--quick" in sys.argv), indent=2))
