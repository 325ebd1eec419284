"""Bad input: every case gives an error naming file, line and field; fail writes nothing, skip quarantines."""

from __future__ import annotations

from pathlib import Path

import pytest

from logpipe.errors import SourceError
from logpipe.stages.ingest import IngestOptions, ingest
from logpipe.storage.io import read_json

HEADER = "TIMESTAMP,TRACK_ID,OBJECT_TYPE,X,Y,CITY_NAME\n"
GOOD = HEADER + "".join(
    f"315968203.{t}00000,{tid},{kind},{10 + t}.5,{20 + t}.25,MIA\n"
    for t in range(3) for tid, kind in (("00000000-0000-0000-0000-000000000000", "AV"), ("a-1", "AGENT"))
)

AV1_CASES = {
    "missing_column": (HEADER.replace(",CITY_NAME", "") + "1.0,a,AV,1.0,2.0\n", 1, None,
                       "missing columns ['CITY_NAME']"),
    "extra_column": (HEADER.replace("CITY_NAME", "CITY_NAME,Z") + "1.0,a,AV,1.0,2.0,MIA,3\n", 1, None,
                     "unexpected columns ['Z']"),
    "non_numeric": (GOOD + "315968203.9,b,OTHERS,abc,2.0,MIA\n", 8, "X", "not a number: 'abc'"),
    "nan": (GOOD + "315968203.9,b,OTHERS,nan,2.0,MIA\n", 8, "X", "not finite"),
    "inf": (GOOD + "315968203.9,b,OTHERS,1.0,inf,MIA\n", 8, "Y", "not finite"),
    "short_row": (GOOD + "315968203.9,b,OTHERS,1.0,2.0\n", 8, None, "expected 6 columns"),
    "empty": ("", 1, None, "empty file"),
    "header_only": (HEADER, 2, None, "no data rows"),
    "duplicate": (GOOD + GOOD.splitlines(keepends=True)[-1], 8, "TRACK_ID", "duplicated (track, time) row"),
    "backwards": (GOOD + "315968203.1,b,OTHERS,1.0,2.0,MIA\n", 8, "TIMESTAMP", "time goes backwards"),
    "bad_timestamp": (GOOD.replace("315968203.200000", "3.1e8", 1), 6, "TIMESTAMP", "not a decimal number"),
    "bad_type": (GOOD + "315968203.9,b,TRUCK,1.0,2.0,MIA\n", 8, "OBJECT_TYPE", "unknown OBJECT_TYPE 'TRUCK'"),
    "not_utf8": (GOOD.encode() + b"315968203.9,b\xff\xfe,OTHERS,1.0,2.0,MIA\n", 8, "TRACK_ID", "not UTF-8 text"),
}


@pytest.mark.parametrize("case", sorted(AV1_CASES))
def test_argoverse1_bad_file_fails_with_location_and_writes_nothing(case: str, tmp_path: Path) -> None:
    text, line, field, reason = AV1_CASES[case]
    src = tmp_path / "in"
    src.mkdir()
    (src / "1.csv").write_text(GOOD)
    (src / "2.csv").write_bytes(text if isinstance(text, bytes) else text.encode())
    out = tmp_path / "out"
    with pytest.raises(SourceError) as info:
        ingest([src], IngestOptions(out=out, format="argoverse1", write_mcap=True))
    error = info.value
    assert error.file == "2.csv"
    assert error.line == line
    assert error.field == field
    assert reason in error.reason
    assert not out.exists() or not any(out.iterdir())


@pytest.mark.parametrize("case", sorted(AV1_CASES))
def test_argoverse1_skip_quarantines_bad_file_and_keeps_good(case: str, tmp_path: Path) -> None:
    text, line, field, _ = AV1_CASES[case]
    src = tmp_path / "in"
    src.mkdir()
    (src / "1.csv").write_text(GOOD)
    (src / "2.csv").write_bytes(text if isinstance(text, bytes) else text.encode())
    (src / "3.csv").write_text(GOOD.replace("a-1", "a-3"))
    out = tmp_path / "out"
    summary = ingest([src], IngestOptions(out=out, format="argoverse1", on_error="skip"))
    assert summary["logs"] == 2 and summary["rows"] == 12
    assert [q["path"] for q in summary["quarantined"]] == ["2.csv"]
    manifest = read_json(out / "manifest.json")
    assert manifest["quarantined"][0]["error"]["line"] == line
    assert manifest["quarantined"][0]["error"]["field"] == field
    assert sorted(i["path"] for i in manifest["inputs"]) == ["1.csv", "3.csv"]
    # A rerun does not retry the known-bad content.
    again = ingest([src], IngestOptions(out=out, format="argoverse1", on_error="skip"))
    assert again["inputs_ingested"] == 0 and again["inputs_skipped_already_ingested"] == 3


ETH_GOOD = "".join(f"{f}.0\t{p}.0\t{f / 10:.2f}\t{p:.2f}\n" for f in range(0, 100, 10) for p in (1, 2))
ETH_CASES = {
    "non_numeric": (ETH_GOOD + "200\t1\tx\t2\n", 21, "x"),
    "nan": (ETH_GOOD + "200\t1\tnan\t2\n", 21, "x"),
    "columns": (ETH_GOOD + "200\t1\t2\n", 21, None),
    "duplicate": (ETH_GOOD + "90.0\t2.0\t1\t1\n", 21, "ped_id"),
    "backwards": (ETH_GOOD + "50\t3\t1\t1\n", 21, "frame_id"),
    "fractional_frame": (ETH_GOOD + "200.5\t3\t1\t1\n", 21, "frame_id"),
    "empty": ("", 1, None),
}


@pytest.mark.parametrize("case", sorted(ETH_CASES))
def test_ethucy_bad_files(case: str, tmp_path: Path) -> None:
    text, line, field = ETH_CASES[case]
    src = tmp_path / "eth" / "test"
    src.mkdir(parents=True)
    (src / "good.txt").write_text(ETH_GOOD)
    (src / "bad.txt").write_text(text)
    with pytest.raises(SourceError) as info:
        ingest([tmp_path / "eth"], IngestOptions(out=tmp_path / "out", format="ethucy"))
    assert (info.value.file, info.value.line, info.value.field) == ("test/bad.txt", line, field)
    summary = ingest([tmp_path / "eth"], IngestOptions(out=tmp_path / "out2", format="ethucy", on_error="skip"))
    assert summary["logs"] == 1 and summary["rows"] == 20


APOLLO_GOOD = "".join(f"{f} {i} {c} 1.0 2.0 3.0 4.0 2.0 1.5 0.1\r\n" for f in range(3) for i, c in ((1, 1), (2, 3)))


@pytest.mark.parametrize(
    ("text", "line", "field"),
    [
        (APOLLO_GOOD + "3 1 7 1 2 3 4 2 1 0\r\n", 7, "object_type"),
        (APOLLO_GOOD + "3 1 1 1 2 3 4 2 1\r\n", 7, None),
        (APOLLO_GOOD + "3 1 1 1 2 3 4 2 1 inf\r\n", 7, "heading"),
    ],
)
def test_apolloscape_bad_files(text: str, line: int, field: str | None, tmp_path: Path) -> None:
    (tmp_path / "in").mkdir()
    (tmp_path / "in" / "a.txt").write_text(APOLLO_GOOD)
    (tmp_path / "in" / "b.txt").write_text(text)
    with pytest.raises(SourceError) as info:
        ingest([tmp_path / "in"], IngestOptions(out=tmp_path / "out", format="apolloscape"))
    assert (info.value.file, info.value.line, info.value.field) == ("b.txt", line, field)


def test_mixed_directory_of_real_and_broken_files(bundled: Path, tmp_path: Path) -> None:
    src = tmp_path / "in"
    src.mkdir()
    for p in (bundled / "argoverse1").glob("*.csv"):
        (src / p.name).write_bytes(p.read_bytes())
    real = (bundled / "argoverse1" / "2645.csv").read_text().splitlines(keepends=True)
    (src / "9001.csv").write_text("".join(real[:100]) + real[100].replace(",MIA", ",").replace(",AV,", ",AV,x"))
    (src / "9002.csv").write_text("")
    summary = ingest([src], IngestOptions(out=tmp_path / "out", on_error="skip", workers=2, batch_files=3))
    assert summary["logs"] == 6
    assert sorted(q["path"] for q in summary["quarantined"]) == ["9001.csv", "9002.csv"]
    assert summary["totals"]["quarantined"] == 2
