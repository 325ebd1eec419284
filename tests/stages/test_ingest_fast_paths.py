"""The shortcuts that make ingest fast keep its results: vectorised checks, Parquet encodings, detection, codes."""

from __future__ import annotations

import io
from dataclasses import replace
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from logpipe.dataset.log_table import canonical_order
from logpipe.dataset.samples import TrackCodes
from logpipe.formats import detect
from logpipe.formats._text import stem
from logpipe.formats.argoverse1 import Argoverse1Adapter
from logpipe.formats.inputs import collect_sources
from logpipe.formats.text_checks import times_sorted_and_unique
from logpipe.storage.io import parquet_options


@pytest.mark.parametrize(
    ("ts", "tracks", "files", "expected"),
    [
        ([1, 1, 2, 2], [0, 1, 0, 1], [0, 0, 0, 0], True),
        ([1, 1, 2, 1], [0, 1, 0, 1], [0, 0, 0, 0], False),  # time goes backwards inside a file
        ([5, 6, 1, 2], [0, 0, 0, 0], [0, 0, 1, 1], True),  # ... but may restart in the next file
        ([1, 1, 2, 2], [0, 0, 0, 1], [0, 0, 0, 0], False),  # the same (track, time) twice
        ([1, 1], [0, 0], [0, 1], True),  # the same (track, time) in two files is fine
        ([1, 2, 2, 2], [3, 0, 1, 0], [0, 0, 0, 0], False),  # duplicate not adjacent within its time
    ],
)
def test_time_and_duplicate_fast_check(ts: list[int], tracks: list[int], files: list[int], expected: bool) -> None:
    as_int = [np.array(v, dtype=np.int64) for v in (ts, tracks, files)]
    assert times_sorted_and_unique(*as_int) is expected


@pytest.mark.parametrize("relpath", ["a/b.csv", "x.tar.gz", ".hidden", "a/.b", "noext", "dir.x/file", "a/b."])
def test_stem_matches_pathlib(relpath: str) -> None:
    assert stem(relpath) == Path(relpath).stem


def test_parquet_options_split_floats_and_choose_statistics() -> None:
    table = pa.table({
        "log_id": ["a", "b"], "track_id": ["t", "u"], "x": [1.5, 2.5],
        "ids": pa.array([["p"], ["q"]], pa.list_(pa.string())), "xs": pa.array([[1.0], [2.0]], pa.list_(pa.float64())),
    })
    options = parquet_options(table.schema, string_statistics=["log_id"])
    buffer = io.BytesIO()
    pq.write_table(table, buffer, **options)
    meta = pq.ParquetFile(io.BytesIO(buffer.getvalue())).metadata.row_group(0)
    columns = {meta.column(i).path_in_schema: meta.column(i) for i in range(meta.num_columns)}
    assert "BYTE_STREAM_SPLIT" in columns["x"].encodings and "BYTE_STREAM_SPLIT" in columns["xs.list.element"].encodings
    assert "RLE_DICTIONARY" in columns["log_id"].encodings and "RLE_DICTIONARY" in columns["ids.list.element"].encodings
    assert columns["log_id"].is_stats_set and columns["x"].is_stats_set and not columns["track_id"].is_stats_set
    assert pq.read_table(io.BytesIO(buffer.getvalue())).equals(table)


def test_fast_detect_agrees_with_detect(bundled: Path, tmp_path: Path) -> None:
    from logpipe.formats import _first_files

    for name in ("argoverse1", "ethucy", "apolloscape", "rosbags"):  # one os.walk = the sorted rglob it replaced
        assert _first_files(bundled / name, 200) == sorted(p for p in (bundled / name).rglob("*") if p.is_file())
    for name in ("argoverse1", "ethucy", "apolloscape"):
        assert detect(bundled / name) == name
    mixed = tmp_path / "mixed"
    mixed.mkdir()
    (mixed / "0_readme.md").write_text("not data\n")  # first file unrecognised: the next ones decide
    for p in sorted((bundled / "argoverse1").glob("*.csv"))[:2]:
        (mixed / p.name).write_bytes(p.read_bytes())
    assert detect(mixed) == "argoverse1"


def test_text_formats_claim_no_file_another_format_claims(bundled: Path) -> None:
    """What lets detection stop at the text formats: over every bundled sample, a file a text format
    claims is claimed by no other format, and detection agrees with asking every format."""
    from logpipe.formats import FORMATS, TEXT_FORMATS, adapter_class

    files = [p for p in sorted(bundled.rglob("*")) if p.is_file()]
    claimed_by_text = 0
    for path in files:
        claims = [name for name in FORMATS if adapter_class(name)().sniff(path)]
        if set(claims) & set(TEXT_FORMATS):
            claimed_by_text += 1
            assert len(claims) == 1, (path, claims)
            assert detect(path) == claims[0]
    assert claimed_by_text >= 10


def test_adapter_codes_equal_recomputed_codes(bundled: Path) -> None:
    adapter = Argoverse1Adapter()
    parsed = adapter.read(collect_sources([bundled / "argoverse1"], adapter), keep_going=False)
    assert parsed.codes is not None
    tracks = canonical_order(parsed.tracks)
    fresh = TrackCodes.of(tracks)
    assert np.array_equal(parsed.codes.log_code, fresh.log_code) and parsed.codes.log_names == fresh.log_names
    ours = parsed.codes.track_names[parsed.codes.track_code]
    assert np.array_equal(ours, fresh.track_names[fresh.track_code])
    assert tracks.column("track_id").to_pylist() == ours.tolist()


def _write(folder: Path, name: str, data: bytes) -> Path:
    path = folder / name
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(data)
    return path


def test_fingerprint_hashes_only_possible_twins(tmp_path: Path) -> None:
    """Files that share size and head with another input, or whose size an ingested input had, are hashed and
    merged; the rest are left pending, and their digests when completed are the files' true sha256."""
    import hashlib

    from logpipe.formats.inputs import complete_hashes, fingerprint_inputs, hash_inputs
    from logpipe.types import PENDING_SHA256

    same = b"frame ped x y\n" * 400  # > 4 KiB
    files = {
        "eth/train/a.txt": same,
        "univ/train/a.txt": same,  # identical: one input with both memberships
        "zara/train/b.txt": same[:-1] + b"Z",  # same size and head, other bytes: hashed, kept apart
        "zara/train/c.txt": b"1 2 3 4\n",  # unique size
        "zara/train/d.txt": b"9" * 77,  # size of an input already in the dataset
    }
    found = [(_write(tmp_path, rel, data), rel) for rel, data in sorted(files.items())]
    sources = {s.relpath: s for s in fingerprint_inputs(found, known_sizes={77}, threads=2)}
    assert sorted(sources) == ["eth/train/a.txt", "zara/train/b.txt", "zara/train/c.txt", "zara/train/d.txt"]
    assert sources["eth/train/a.txt"].memberships == ("eth/train", "univ/train")
    assert sources["zara/train/c.txt"].sha256 == PENDING_SHA256
    assert all(sources[r].sha256 != PENDING_SHA256 for r in ("eth/train/a.txt", "zara/train/b.txt", "zara/train/d.txt"))
    completed = complete_hashes(list(sources.values()))
    assert [s.sha256 for s in completed] == [hashlib.sha256(files[s.relpath]).hexdigest() for s in completed]
    assert completed == hash_inputs(found, threads=2)
    # Sizes unknown (a manifest from before sizes were recorded): everything is hashed, as hash_inputs does.
    assert fingerprint_inputs(found, known_sizes=None, threads=2) == hash_inputs(found, threads=2)


@pytest.mark.parametrize("header_lines", [0, 1])
def test_read_bodies_equals_join_of_whole_files(tmp_path: Path, header_lines: int) -> None:
    """Reading straight into the shared buffer gives the bytes, line counts and digests of read-then-join."""
    import hashlib

    from logpipe.formats._text import join_bodies, read_bodies
    from logpipe.types import PENDING_SHA256, SourceFile

    blobs = [b"h\na\nb\n", b"h\nc\r\n", b"h\nx\ny\n\n \t", b"h\r\nlast line\r\n",
             b"h\n" + b"row,1\n" * 3000]  # the last one is bigger than the 4 KiB head read
    sources = [SourceFile(str(_write(tmp_path, f"{i}.txt", b)), f"{i}.txt", PENDING_SHA256, len(b)) for i, b in
               enumerate(blobs)]
    batch, good, failures = read_bodies(sources, header_lines, lambda s, head, rows: None, keep_going=False)
    expected = join_bodies(blobs, header_lines)
    assert bytes(batch.buffer) == expected.buffer and batch.rows_per_file == expected.rows_per_file
    assert [s.sha256 for s in good] == [hashlib.sha256(b).hexdigest() for b in blobs] and not failures
    kept = batch.keep([0, 3])  # dropping failed files (the keep_going retry)
    assert bytes(kept.buffer) == join_bodies([blobs[0], blobs[3]], header_lines).buffer


@pytest.mark.parametrize("cut", [b"h\na\nb", b"h\r\n1 2 10.3", b"h\n1 2 3\n4 5 6 \t"])
def test_a_last_line_without_newline_is_a_truncated_record(tmp_path: Path, cut: bytes) -> None:
    """Issue 64 item 7: a file cut mid-record ends without a newline; its last line may still parse (10.3817 cut
    to 10.3), so the file is refused naming that line, and with keep_going the other files still land."""
    from logpipe.formats._text import read_bodies
    from logpipe.types import PENDING_SHA256, SourceFile

    blobs = [b"h\nfine\n", cut]
    sources = [SourceFile(str(_write(tmp_path, f"{i}.txt", b)), f"{i}.txt", PENDING_SHA256, len(b)) for i, b in
               enumerate(blobs)]
    batch, good, failures = read_bodies(sources, 1, lambda s, head, rows: None, keep_going=True)
    assert [s.relpath for s in good] == ["0.txt"] and bytes(batch.buffer) == b"fine\n"
    [error] = failures
    assert error.file == "1.txt" and error.line == cut.count(b"\n") + 1 and "truncated record" in error.reason


def test_read_bodies_passes_header_and_emptiness_to_the_check(tmp_path: Path) -> None:
    from logpipe.formats._text import read_bodies
    from logpipe.formats.argoverse1 import HEADER, _check_header
    from logpipe.types import SourceFile

    cases = {"empty.csv": b"", "spaces.csv": b"  \n\n", "header_only.csv": HEADER + b"\r\n  \n",
             "bad.csv": b"TIMESTAMP,TRACK_ID,X,Y\n1,a,2,3\n", "ok.csv": HEADER + b"\n1.0,a,AV,1,2,MIA\n"}
    sources = [SourceFile(str(_write(tmp_path, n, b)), n, "x", len(b)) for n, b in cases.items()]
    _, good, failures = read_bodies(sources, 1, _check_header, keep_going=True)
    assert [s.relpath for s in good] == ["ok.csv"]
    assert {e.file: (e.line, e.reason.split(":")[0]) for e in failures} == {
        "empty.csv": (1, "empty file (no header, no rows)"), "spaces.csv": (1, "empty file (no header, no rows)"),
        "header_only.csv": (2, "no data rows after the header"), "bad.csv": (1, "bad header")}


def test_pool_workers_and_parent_never_import_pandas(bundled: Path, tmp_path: Path) -> None:
    """pyarrow would import pandas (~1 s of CPU a process) on its first conversion: the pool workers refuse it,
    and a pooled Argoverse ingest in a fresh process leaves pandas unimported there too."""
    import subprocess
    import sys

    script = """
import os
import sys
from dataclasses import replace
from pathlib import Path
from logpipe.executor import _init_worker
from logpipe.stages.ingest import IngestOptions, ingest

if __name__ == "__main__":
    summary = ingest([Path(sys.argv[1])], IngestOptions(out=Path(sys.argv[2]), batch_files=2, workers=2))
    assert summary["shards_written"] and summary["rows"] > 0, summary
    parent_has_pandas = "pandas" in sys.modules
    _init_worker(os.getpid())
    import pyarrow as pa
    assert pa.array([1.5]).to_pylist() == [1.5]  # pyarrow works with pandas refused
    print(parent_has_pandas, "pandas" in sys.modules)
"""
    out = subprocess.run([sys.executable, "-c", script, str(bundled / "argoverse1"), str(tmp_path / "out")],
                         capture_output=True, text=True, check=True)
    assert out.stdout.split() == ["False", "False"], out.stderr


def test_first_ingest_with_unseen_twins_is_redone_merging_them(bundled: Path, tmp_path: Path) -> None:
    """A first ingest of distinctly named files hashes nothing up front; when two of them turn out identical
    the run is redone with fingerprinting, so the twins become one input exactly as a fingerprinted run makes."""
    from logpipe.formats import get_adapter
    from logpipe.formats.inputs import find_inputs, unhashed_inputs
    from logpipe.stages.ingest import IngestOptions, ingest
    from logpipe.storage.io import read_json

    src = tmp_path / "in"
    src.mkdir()
    originals = sorted((bundled / "argoverse1").glob("*.csv"))[:3]
    for p in originals:
        (src / p.name).write_bytes(p.read_bytes())
    (src / "copy_of_first.csv").write_bytes(originals[0].read_bytes())  # a twin under another name
    adapter = Argoverse1Adapter()
    assert unhashed_inputs(find_inputs([src], adapter)) is not None  # distinct names: the optimistic path
    assert unhashed_inputs(find_inputs([bundled / "ethucy"], get_adapter("ethucy"))) is None  # same names: not
    summary = ingest([src], IngestOptions(out=tmp_path / "out", batch_files=1, workers=2, write_mcap=False))
    manifest = read_json(tmp_path / "out" / "manifest.json")
    assert [i["path"] for i in manifest["inputs"]] == sorted(p.name for p in originals)
    assert summary["inputs_found"] == 3 and summary["logs"] == 3 and manifest["totals"]["logs"] == 3
    assert len({i["sha256"] for i in manifest["inputs"]}) == 3
    rerun = ingest([src], IngestOptions(out=tmp_path / "out", write_mcap=False))
    assert rerun["inputs_skipped_already_ingested"] == 3 and rerun["inputs_ingested"] == 0


def test_read_ahead_leaves_files_unchanged_and_skips_missing_ones(bundled: Path, tmp_path: Path) -> None:
    from logpipe.formats.inputs import read_ahead
    from logpipe.types import SourceFile

    real = sorted((bundled / "argoverse1").glob("*.csv"))[:2]
    before = [p.read_bytes() for p in real]
    sources = [SourceFile(str(p), p.name, "", p.stat().st_size) for p in real]
    read_ahead([*sources, SourceFile(str(tmp_path / "gone.csv"), "gone.csv", "", 1)])
    assert [p.read_bytes() for p in real] == before


@pytest.mark.parametrize("focal_only", [True, False])
def test_sample_index_is_the_same_counted_densely_or_by_sorting(
    bundled: Path, focal_only: bool, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The (log, track) counts behind the first-window index come from a bincount, or from a sort when the
    key range is too sparse; both give the same samples on real Argoverse files."""
    from logpipe.dataset import samples
    from logpipe.formats.inputs import find_inputs, unhashed_inputs
    from logpipe.types import PROTOCOLS

    adapter = Argoverse1Adapter()
    sources = unhashed_inputs(find_inputs([bundled / "argoverse1"], adapter))
    assert sources
    parsed = adapter.read(sources, keep_going=False)
    protocol = replace(PROTOCOLS["argoverse"], targets="focal" if focal_only else "fully_observed")
    dense = samples.build_samples(parsed.tracks, parsed.logs, protocol, parsed.codes)
    monkeypatch.setattr(samples, "DENSE_KEYS_PER_ROW", 0)
    by_sort = samples.build_samples(parsed.tracks, parsed.logs, protocol, parsed.codes)
    assert dense.num_rows == len(parsed.logs)
    assert dense.equals(by_sort)
    if not focal_only:
        assert max(len(t) for t in dense.column("target_track_ids").to_pylist()) > 1
