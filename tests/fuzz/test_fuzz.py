"""Damaged inputs (``corpus.py``) through ingest (skip and fail, MCAP writing on), inspect and the map loaders.

For every case: with ``on_error="skip"`` the good input beside the damaged one lands with exactly the rows a
clean ingest gives it, and the damaged input is either quarantined or lands judged against its undamaged
original (the same file ingested intact): values that pass every check (finite, no repeated (track, time),
times in range), and rows that are the original's where the damage did not reach and nothing invented where it
did (a truncation may only lose rows; a single changed byte may touch the rows of one time stamp; a BOM or CR
line ends none). A landed input has its MCAP. With ``"fail"`` the error is one line naming the damaged input;
``inspect`` reports, never raises. Special files (FIFO, dangling link, ``/dev/zero``) must be refused saying what
they are. A landed map must be a subset of its undamaged original's features. Anything else raised is a
traceback. The full corpus runs with ``make fuzz`` (``-m fuzz``) and writes ``out/fuzz.json`` with the count of
cases per outcome; a fast subset runs in the default suite.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
import pytest
from corpus import (  # type: ignore[import-not-found]
    REPO,
    Case,
    Sample,
    _write_damaged,
    available,
    cases,
    place_good,
)

from logpipe.dataset.reader import Dataset
from logpipe.errors import LogpipeError
from logpipe.stages.ingest import IngestOptions, ingest

ALL = cases()
RESULTS: list[dict[str, Any]] = []
_REFERENCE: dict[str, pa.Table] = {}
_ORIGINAL: dict[str, pa.Table | None] = {}
SPECIAL = ("dangling-link", "dev-zero-link", "fifo")
"""Damages that make the input no regular file: each must be refused, saying what it is."""
SPECIAL_WORDS = ("FIFO", "dangling", "device", "not a regular file", "not readable", "missing", "symbolic link")
EXACT = ("bom", "cr-only")
"""Damages that change no value: a landed input must give exactly its original's rows."""


@pytest.fixture(scope="session", autouse=True)
def _summary() -> Iterator[None]:
    """Writes the figures of the cases run to ``out/fuzz.json`` (``out/fuzz-fast.json`` for the fast subset)."""
    yield
    if not RESULTS:
        return
    full = len(RESULTS) > len([c for c in ALL if c.fast])
    counts: dict[str, int] = {}
    for r in RESULTS:
        counts[r["outcome"]] = counts.get(r["outcome"], 0) + 1
    summary = {
        "command": "make fuzz" if full else ".venv/bin/python -m pytest -q -p no:cacheprovider tests/fuzz",
        "damaged_inputs_tried": len(RESULTS),
        "clean_errors": sum(r["outcome"] in ("quarantined", "refused") for r in RESULTS),
        "ignored_not_an_input": counts.get("ignored", 0),
        "landed_harmless": sum(v for k, v in counts.items() if k.startswith("landed")),
        "outcomes": dict(sorted(counts.items())),
        "tracebacks": counts.get("traceback", 0),
        "silently_wrong": counts.get("silently_wrong", 0),
        "good_files_lost": counts.get("good_lost", 0),
        "by_format": _by_format(),
        "cases": RESULTS,
    }
    out = Path(os.environ.get("OUT", REPO / "out"))
    out.mkdir(parents=True, exist_ok=True)
    (out / ("fuzz.json" if full else "fuzz-fast.json")).write_text(json.dumps(summary, indent=1, sort_keys=True))


def _by_format() -> dict[str, dict[str, int]]:
    table: dict[str, dict[str, int]] = {}
    for r in RESULTS:
        row = table.setdefault(r["format"], {})
        row[r["outcome"]] = row.get(r["outcome"], 0) + 1
    return table


def _params(selected: list[Case], mark: pytest.MarkDecorator | None) -> list[Any]:
    marks = [mark] if mark is not None else []
    out = []
    for c in selected:
        these = list(marks)
        if c.sample.shared:
            these.append(pytest.mark.shared)
        out.append(pytest.param(c, id=c.id, marks=these))
    return out


@pytest.mark.parametrize("case", _params([c for c in ALL if c.fast], None))
def test_fast_subset(case: Case, tmp_path: Path) -> None:
    _run(case, tmp_path)


@pytest.mark.parametrize("case", _params(ALL, pytest.mark.fuzz))
def test_corpus(case: Case, tmp_path: Path) -> None:
    _run(case, tmp_path)


def _run(case: Case, tmp_path: Path) -> None:
    if not available(case):
        pytest.skip(f"sample {case.sample.victim} is absent (../shared/data is not on this machine)")
    result = _check_maps(case, tmp_path) if case.sample.fmt == "maps" else _check_ingest(case, tmp_path)
    result |= {"id": case.id, "format": case.sample.fmt, "damage": case.damage}
    RESULTS.append(result)
    assert result["outcome"] not in ("traceback", "silently_wrong", "good_lost"), result


# --- ingest


def _options(out: Path, fmt: str, on_error: str, *, mcap: bool = True) -> IngestOptions:
    """MCAP writing on (the native writer is fuzzed too) except for the references, which need only rows."""
    return IngestOptions(out=out, format=fmt, on_error=on_error, workers=1, write_mcap=mcap)  # type: ignore[arg-type]


def _reference(sample: Sample, tmp_path: Path) -> pa.Table:
    """Rows of the good input ingested alone (once per sample)."""
    key = f"{sample.fmt}-{sample.name}"
    if key not in _REFERENCE:
        folder = tmp_path / "ref-in"
        folder.mkdir()
        place_good(sample, folder)
        ingest([folder], _options(tmp_path / "ref-out", sample.fmt, "fail", mcap=False))
        _REFERENCE[key] = _rows(Dataset.open(tmp_path / "ref-out"))
    return _REFERENCE[key]


def _original(sample: Sample, tmp_path: Path) -> pa.Table | None:
    """Rows of the undamaged victim, placed as its damaged copies are and ingested alone (once per sample);
    None when the intact input does not land by itself (then only ``_sane`` judges what lands)."""
    key = f"{sample.fmt}-{sample.name}"
    if key not in _ORIGINAL:
        folder = tmp_path / "orig-in"
        folder.mkdir()
        _write_damaged(sample, folder, "orig", sample.victim.read_bytes())
        try:
            ingest([folder], _options(tmp_path / "orig-out", sample.fmt, "fail", mcap=False))
            _ORIGINAL[key] = _rows(Dataset.open(tmp_path / "orig-out"))
        except LogpipeError:
            _ORIGINAL[key] = None
    return _ORIGINAL[key]


def _keyed(rows: pa.Table) -> dict[tuple[str, int], tuple[float, float]]:
    """(track id, time) -> (x, y) of ``rows``."""
    return dict(zip(zip(rows.column("track_id").to_pylist(), rows.column("timestamp_ns").to_pylist(), strict=True),
                    zip(rows.column("x").to_pylist(), rows.column("y").to_pylist(), strict=True), strict=True))


def _judge(case: Case, landed: pa.Table, original: pa.Table | None) -> tuple[str, str]:
    """(outcome, detail) of a damaged input that landed, against its undamaged original's rows."""
    if original is None:
        return "landed_unjudged", f"{landed.num_rows} rows (the intact input does not land alone)"
    mine, theirs = _keyed(landed), _keyed(original)
    invented = [k for k in mine if k not in theirs]
    changed = [k for k in mine if k in theirs and mine[k] != theirs[k]]
    lost = len(theirs) - (len(mine) - len(invented))
    detail = f"{len(mine)} rows: {len(invented)} invented, {len(changed)} changed, {lost} lost of {len(theirs)}"
    touched_times = {t for _, t in invented + changed}
    if case.damage in EXACT:
        allowed = not invented and not changed and lost == 0
    elif case.damage.startswith("trunc"):
        allowed = not invented and not changed
    else:  # one place damaged: the rows of at most one time stamp (a flipped time moves one row to another);
        # in a bag or MCAP a changed transform also changes the rows interpolated from it (one more time stamp)
        allowed = len(touched_times) <= (2 if invented else 1) + (case.sample.fmt in ("rosbag", "mcap"))
    if not allowed:
        return "silently_wrong", f"{case.damage} reached too far: {detail}"
    if invented or changed:
        return "landed_changed", detail
    return ("landed_exact" if lost == 0 else "landed_subset"), detail


def _rows(ds: Dataset) -> pa.Table:
    tables = [pa.Table.from_batches(pa.ipc.open_file(p).read_all().to_batches()) if p.suffix == ".arrow"
              else _read(p) for p in ds.shard_paths]
    if not tables:
        return pa.table({})
    table = pa.concat_tables([t.cast(tables[0].schema) for t in tables])
    return table.sort_by([("log_id", "ascending"), ("timestamp_ns", "ascending"), ("track_id", "ascending")])


def _read(path: Path) -> pa.Table:
    import pyarrow.parquet as pq

    table = pq.read_table(path)
    return table.cast(pa.schema([pa.field(f.name, f.type.value_type if pa.types.is_dictionary(f.type) else f.type)
                                 for f in table.schema]))


def _sane(rows: pa.Table) -> str | None:
    """Why rows that landed are wrong (non-finite values, repeated (track, time), absurd times), else None."""
    if rows.num_rows == 0:
        return None
    for name in ("x", "y", "heading", "vx", "vy", "length", "width"):
        if name in rows.column_names:
            values = rows.column(name).to_numpy(zero_copy_only=False).astype(np.float64)
            if np.isinf(values).any() or (np.isnan(values) & ~np.asarray(
                    rows.column(name).is_null().to_numpy(zero_copy_only=False), dtype=bool)).any():
                return f"non-finite {name} landed"
    ts = rows.column("timestamp_ns").to_numpy()
    if (np.abs(ts) >= 1 << 62).any():
        return "timestamp beyond 2^62 ns landed"
    keys = rows.select(["log_id", "track_id", "timestamp_ns"])
    if keys.group_by(keys.column_names).aggregate([]).num_rows < keys.num_rows:
        return "duplicated (log, track, time) landed"
    for log_id in pc.unique(rows.column("log_id")).to_pylist():
        if not log_id or "/" in log_id or log_id in (".", "..") or "\x00" in log_id:
            return f"unsafe log id {log_id!r} landed"
    return None


def _check_ingest(case: Case, tmp_path: Path) -> dict[str, Any]:  # noqa: PLR0912  one return per fuzz outcome
    sample = case.sample
    reference = _reference(sample, tmp_path)
    folder = tmp_path / "in"
    folder.mkdir()
    good = place_good(sample, folder)
    assert good is not None
    damaged = case.build(folder)
    good_rel, bad_rel = good.name, damaged.name
    result: dict[str, Any] = {}
    try:
        summary = ingest([folder], _options(tmp_path / "skip", sample.fmt, "skip"))
    except LogpipeError as err:
        return {"outcome": "good_lost", "detail": f"skip run raised {type(err).__name__}: {err}"}
    except Exception as err:
        return {"outcome": "traceback", "detail": f"skip run: {type(err).__name__}: {err}"}
    quarantined = {q["path"]: q["error"] for q in summary["quarantined"]}
    ds = Dataset.open(tmp_path / "skip")
    logs = ds.logs()
    sources = logs.column("source_file").to_pylist()
    if good_rel not in sources or good_rel in quarantined:
        return {"outcome": "good_lost", "detail": f"good input {good_rel} not landed: {quarantined}"}
    foreign_name = case.sample.victim_dir is not None and sample.fmt != "rosbag" and damaged.suffix == ".bag"
    if case.damage in SPECIAL and not foreign_name and (bad_rel not in quarantined or not any(
            w in str(quarantined[bad_rel].get("reason")) for w in SPECIAL_WORDS)):
        return {"outcome": "silently_wrong", "detail": f"{case.damage} not refused as what it is: {quarantined}"}
    rows = _rows(ds)
    good_id = logs.column("log_id")[sources.index(good_rel)].as_py()
    good_rows = rows.filter(pc.equal(rows.column("log_id"), good_id))
    if good_rows.drop_columns(["log_id"]).to_pylist() != reference.drop_columns(["log_id"]).to_pylist():
        return {"outcome": "good_lost", "detail": "good input's rows differ from a clean ingest"}
    if bad_rel in quarantined:
        result = {"outcome": "quarantined", "detail": quarantined[bad_rel]}
    elif bad_rel in sources:
        bad_id = logs.column("log_id")[sources.index(bad_rel)].as_py()
        bad_rows = rows.filter(pc.equal(rows.column("log_id"), bad_id))
        why = _sane(bad_rows)
        if why or case.must_refuse:
            return {"outcome": "silently_wrong", "detail": why or "must be refused but landed"}
        if not ds.mcap_path(bad_id).is_file():
            return {"outcome": "silently_wrong", "detail": f"landed without its MCAP {ds.mcap_path(bad_id)}"}
        outcome, detail = _judge(case, bad_rows, _original(sample, tmp_path))
        if outcome == "silently_wrong":
            return {"outcome": outcome, "detail": detail}
        result = {"outcome": outcome, "detail": detail}
    elif case.damage == "dir-named-like-input":
        result = {"outcome": "ignored", "detail": "a folder named like an input is not one"}
    elif case.sample.victim_dir is not None and sample.fmt != "rosbag" and damaged.suffix == ".bag":
        # The corpus names special files of folder inputs "z_<kind>.bag": no input of this format (an AV2 sensor
        # log is a folder), so not taken for one.
        result = {"outcome": "ignored", "detail": f"{damaged.name} is not named like a {sample.fmt} input"}
    else:
        return {"outcome": "silently_wrong", "detail": "damaged input neither landed nor quarantined"}
    # on_error=fail: one line naming the damaged input, or success when the damage was harmless
    try:
        ingest([folder], _options(tmp_path / "fail", sample.fmt, "fail"))
    except LogpipeError as err:
        text = str(err)
        if "\n" in text or bad_rel not in text:
            return {"outcome": "traceback", "detail": f"fail-mode error is not one line naming {bad_rel}: {text}"}
    except Exception as err:
        return {"outcome": "traceback", "detail": f"fail run: {type(err).__name__}: {err}"}
    else:
        if result["outcome"] == "quarantined":
            return {"outcome": "silently_wrong", "detail": "fail mode accepted what skip mode quarantined"}
    inspected = _inspect(damaged)
    if inspected:
        return {"outcome": "traceback", "detail": inspected}
    return result


def _inspect(path: Path) -> str | None:
    from logpipe.inspect import inspect_paths

    try:
        reports = inspect_paths([path])
    except Exception as err:
        return f"inspect raised {type(err).__name__}: {err}"
    for r in reports:
        if r.get("error") and "\n" in str(r["error"]).strip():
            return f"inspect error is not one line: {r['error']}"
    return None


# --- maps


def _check_maps(case: Case, tmp_path: Path) -> dict[str, Any]:
    from logpipe.maps import MapSource, load_map

    folder = tmp_path / "maps"
    folder.mkdir()
    damaged = case.build(folder)
    try:
        store = load_map(damaged)
    except LogpipeError as err:
        if "\n" in str(err) or damaged.name not in str(err):
            return {"outcome": "traceback", "detail": f"not one line naming the file: {err}"}
        if case.damage in SPECIAL and not any(w in str(err) for w in (*SPECIAL_WORDS, "no map named")):
            return {"outcome": "silently_wrong", "detail": f"{case.damage} not refused as what it is: {err}"}
        outcome = {"outcome": "refused", "detail": str(err)}
    except Exception as err:
        return {"outcome": "traceback", "detail": f"load_map: {type(err).__name__}: {err}"}
    else:
        if case.must_refuse:
            return {"outcome": "silently_wrong", "detail": "damaged map loaded"}
        outcome = _judge_map(case, store.table, load_map(case.sample.victim).table)
        if outcome["outcome"] == "silently_wrong":
            return outcome
    # --maps folder lookup: a damaged map must be an error, never "no map"
    source = MapSource(roots=(folder,))
    stem = case.sample.victim.name
    map_id = stem[:3] if stem.endswith(".npz") or stem.endswith(".osm") else None
    log_id = stem.removeprefix("log_map_archive_").removesuffix(".json") if stem.endswith(".json") else None
    try:
        found = source.get(map_id, log_id)
    except LogpipeError as err:
        if "\n" in str(err):
            return {"outcome": "traceback", "detail": f"not one line: {err}"}
    except Exception as err:
        return {"outcome": "traceback", "detail": f"MapSource.get: {type(err).__name__}: {err}"}
    else:
        special = case.damage in ("dangling-link", "dev-zero-link", "fifo", "dir-named-like-input")
        if found is None and outcome["outcome"] == "refused" and not special and not stem.endswith(".osm"):
            return {"outcome": "silently_wrong", "detail": "damaged map under --maps became 'no map'"}
    return outcome


def _judge_map(case: Case, landed: pa.Table, original: pa.Table) -> dict[str, Any]:
    """A map that loaded despite its damage, against the undamaged file's features: every coordinate finite, no
    feature invented, and (one place damaged) at most one feature's geometry changed."""
    def features(table: pa.Table) -> dict[tuple[Any, ...], tuple[Any, ...]]:
        key = [c for c in ("kind", "feature_id", "id") if c in table.column_names]
        rows = table.select([*key, "xs", "ys"]).to_pylist()
        return {tuple(r[k] for k in key): (tuple(r["xs"] or ()), tuple(r["ys"] or ())) for r in rows}

    for name in ("xs", "ys"):
        values = pc.list_flatten(landed.column(name)).to_numpy(zero_copy_only=False).astype(np.float64)
        if not np.isfinite(values).all():
            return {"outcome": "silently_wrong", "detail": f"non-finite {name} in a landed map"}
    mine, theirs = features(landed), features(original)
    invented = [k for k in mine if k not in theirs]
    changed = [k for k in mine if k in theirs and mine[k] != theirs[k]]
    detail = (f"{len(mine)} features: {len(invented)} invented, {len(changed)} changed, "
              f"{len(theirs) - len(mine) + len(invented)} lost of {len(theirs)}")
    if invented or len(changed) > (0 if case.damage.startswith("trunc") else 1):
        return {"outcome": "silently_wrong", "detail": f"{case.damage} reached too far: {detail}"}
    return {"outcome": "landed_changed" if changed else "landed_exact" if len(mine) == len(theirs)
            else "landed_subset", "detail": detail}


# --- the CLI, for a handful: exit codes and no traceback on stderr


CLI_CASES = ["ethucy-eth-bom", "argoverse1-av1-fifo", "rosbag-datmo-trunc0.5"]


@pytest.mark.parametrize("case_id", CLI_CASES)
def test_cli_never_prints_a_traceback(case_id: str, tmp_path: Path) -> None:
    case = next(c for c in ALL if c.id == case_id)
    folder = tmp_path / "in"
    folder.mkdir()
    place_good(case.sample, folder)
    damaged = case.build(folder)
    cli = [sys.executable, "-m", "logpipe.cli"]
    skip = subprocess.run([*cli, "ingest", str(folder), "--out", str(tmp_path / "ds"), "--format", case.sample.fmt,
                           "--on-error", "skip", "--no-mcap", "--workers", "1"],
                          check=False, capture_output=True, text=True, timeout=300, cwd=REPO)
    assert skip.returncode == 0 and "Traceback" not in skip.stderr, skip.stderr
    fail = subprocess.run([*cli, "ingest", str(folder), "--out", str(tmp_path / "ds2"), "--format",
                           case.sample.fmt, "--no-mcap", "--workers", "1"],
                          check=False, capture_output=True, text=True, timeout=300, cwd=REPO)
    assert fail.returncode == 2 and "Traceback" not in fail.stderr, fail.stderr
    assert damaged.name in fail.stderr + fail.stdout
    inspect = subprocess.run([*cli, "inspect", str(damaged)], check=False, capture_output=True, text=True,
                             timeout=120, cwd=REPO)
    assert inspect.returncode in (0, 2) and "Traceback" not in inspect.stderr, inspect.stderr


# --- checkpoints: a damaged safetensors file is one line naming it


@pytest.mark.parametrize("blob", [
    b"", b"\x00" * 4, (1 << 40).to_bytes(8, "little") + b"{}", (2).to_bytes(8, "little") + b"{x",
    (30).to_bytes(8, "little") + b'{"w": {"dtype": "F32", "shape": [4], "data_offsets": [0, 16]}}',
], ids=["empty", "short", "huge-header", "bad-json", "data-missing"])
def test_damaged_safetensors_is_one_line(blob: bytes, tmp_path: Path) -> None:
    from types import SimpleNamespace

    from logpipe.model.checkpoint.format import CheckpointError
    from logpipe.model.zhu2020.checkpoint import _verified_weights
    from logpipe.storage.io import sha256_file

    weights = tmp_path / "weights.safetensors"
    weights.write_bytes(blob)
    meta = SimpleNamespace(weights_sha256=sha256_file(weights))  # as if meta.json was written for these bytes
    with pytest.raises(CheckpointError) as caught:
        _verified_weights(tmp_path, meta)  # type: ignore[arg-type]
    assert "\n" not in str(caught.value) and "weights.safetensors" in str(caught.value)
