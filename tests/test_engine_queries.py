"""Every output table reads with one glob in DuckDB, Polars and ``pyarrow.dataset``, with its dictionary and
fixed-size list types intact; the README's example queries give what ``logpipe score`` and the manifests say."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import duckdb
import numpy as np
import polars as pl
import pyarrow as pa
import pyarrow.dataset as pds
import pytest

from logpipe.dataset.reader import Dataset
from logpipe.stages.index import reindex
from logpipe.stages.ingest import IngestOptions, ingest
from logpipe.stages.predict import predict_dataset
from logpipe.stages.score import score

K, T = 6, 30  # Argoverse protocol: 6 modes, 30 future steps
IDS = {"logs": ["log_id", "source_format", "map_id", "shard"], "samples": ["sample_id", "log_id", "focal_track_id"],
       "predictions": ["log_id", "sample_id", "track_id", "object_type"]}
"""Id and label columns per table (the tracks': log_id, track_id, object_type)."""


@pytest.fixture(scope="module")
def outputs(bundled: Path, tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """The AV1 sample ingested, re-indexed with every fully observed agent but the ego as a target (several
    agents per sample), and constant-velocity forecasts of it."""
    root = tmp_path_factory.mktemp("engines")
    ingest([bundled / "argoverse1"], IngestOptions(out=root / "av1", write_mcap=False))
    reindex(root / "av1", replace(Dataset.open(root / "av1").protocol, targets="fully_observed_no_ego"))
    predict_dataset(root / "av1", root / "cv", predictor="cv", write_mcap=False, threads=1)
    return root / "av1", root / "cv"


def _globs(outputs: tuple[Path, Path]) -> dict[str, tuple[str, int]]:
    """Each table's glob and the row count its manifest commits."""
    ds_dir, run_dir = outputs
    manifest = json.loads((ds_dir / "manifest.json").read_text())
    run = json.loads((run_dir / "manifest.json").read_text())
    totals = manifest["totals"]
    predicted = sum(entry["rows"] for rel, entry in run["files"].items() if rel.startswith("predictions/"))
    return {"tracks": (f"{ds_dir}/tracks/*.parquet", totals["rows"]),
            "logs": (f"{ds_dir}/logs/*.parquet", totals["logs"]),
            "samples": (f"{ds_dir}/samples/*.parquet", totals["samples"]),
            "predictions": (f"{run_dir}/predictions/*.parquet", predicted)}


def test_one_glob_reads_one_table_in_every_engine(outputs: tuple[Path, Path]) -> None:
    ds_dir, _ = outputs
    assert json.loads((ds_dir / "manifest.json").read_text())["generation"] == 2  # the re-index wrote samples again
    for name, (glob, rows) in _globs(outputs).items():
        assert rows > 0, name
        assert duckdb.sql(f"SELECT count(*) FROM read_parquet('{glob}')").fetchall() == [(rows,)], name
        assert pl.scan_parquet(glob).select(pl.len()).collect().item() == rows, name
        folder = Path(glob).parent
        assert pds.dataset(folder, format="parquet").count_rows() == rows, name
    assert _globs(outputs)["predictions"][1] == _targets(ds_dir) * K  # one row per (sample, agent, mode)


def _targets(ds_dir: Path) -> int:
    return sum(len(t) for t in Dataset.open(ds_dir).samples().column("target_track_ids").to_pylist())


def test_ids_are_plain_strings_in_every_table_and_lists_survive(outputs: tuple[Path, Path]) -> None:
    for name, (glob, _) in _globs(outputs).items():
        arrow = pds.dataset(Path(glob).parent, format="parquet").schema
        polars = pl.scan_parquet(glob).collect_schema()
        for column in IDS.get(name, ["log_id", "track_id", "object_type"]):  # tracks: the last three
            assert arrow.field(column).type == pa.string(), (name, column)
            assert polars[column] == pl.String, (name, column)
    glob = _globs(outputs)["predictions"][0]
    arrow = pds.dataset(Path(glob).parent, format="parquet").schema
    polars = pl.scan_parquet(glob).collect_schema()
    for column, item in (("x", pa.float64()), ("y", pa.float64()), ("timestamp_ns", pa.int64())):
        assert arrow.field(column).type == pa.list_(item, T)
        assert polars[column] == pl.Array(pl.Float64 if column != "timestamp_ns" else pl.Int64, T)
    assert duckdb.sql(f"SELECT min(len(x)), max(len(y)), count(DISTINCT mode) FROM read_parquet('{glob}')"
                      ).fetchall() == [(T, T, K)]
    assert not {"predictor", "checkpoint_id", "step"} & set(arrow.names)  # constants live in the metadata


def test_readme_queries(outputs: tuple[Path, Path], tmp_path: Path) -> None:
    """The three queries of README.md "Querying outputs", on these outputs."""
    ds_dir, run_dir = outputs
    # 1. mode-0 final displacement error in DuckDB: the truth row is the track's row at the last future time.
    fde = duckdb.sql(f"""
        SELECT p.sample_id, p.track_id,
               sqrt((p.x[-1] - t.x) ** 2 + (p.y[-1] - t.y) ** 2) AS fde_m
        FROM read_parquet('{run_dir}/predictions/*.parquet') p
        JOIN read_parquet('{ds_dir}/tracks/*.parquet') t
          ON t.log_id = p.log_id AND t.track_id = p.track_id AND t.timestamp_ns = p.timestamp_ns[-1]
        WHERE p.mode = 0
    """).fetchall()
    report = score([run_dir], ds_dir, tmp_path / "report", plots=False)
    k1 = report["methods"]["cv"]["overall"]
    assert len(fde) == k1["agents"] == _targets(ds_dir) > 6  # several agents per sample
    assert np.mean([r[2] for r in fde]) == pytest.approx(k1["k1"]["fde"], rel=1e-12)
    # 2. the constants of a predictions file, from its Parquet metadata.
    meta = duckdb.sql(f"""
        SELECT DISTINCT json_extract_string(decode(value), '$.predictor') AS predictor,
                        json_extract(decode(value), '$.num_modes')::INT AS k,
                        json_extract(decode(value), '$.pred_len')::INT AS t
        FROM parquet_kv_metadata('{run_dir}/predictions/*.parquet')
        WHERE decode(key) = 'logpipe.predictions'
    """).fetchall()
    assert meta == [("cv", K, T)]
    # 3. Polars: predicted agents per city, joining the string ids across tables (no cast).
    per_city = (
        pl.scan_parquet(f"{run_dir}/predictions/*.parquet")
        .filter(pl.col("mode") == 0)
        .join(pl.scan_parquet(f"{ds_dir}/logs/*.parquet"), on="log_id")
        .group_by("map_id").agg(pl.len().alias("agents"), pl.col("sample_id").n_unique().alias("samples"))
        .sort("map_id").collect()
    )
    logs = Dataset.open(ds_dir).logs()
    assert set(per_city["map_id"].to_list()) == set(logs.column("map_id").to_pylist())
    assert per_city["agents"].sum() == _targets(ds_dir) and per_city["samples"].sum() == 6


def test_natural_joins_work_in_duckdb_polars_and_pandas(outputs: tuple[Path, Path]) -> None:
    """predictions ⋈ tracks on (log, track, last future time), predictions ⋈ samples on sample_id, samples ⋈ logs
    on log_id: the same row counts in the three engines, none of them casting a column."""
    import pandas as pd

    g = {name: glob for name, (glob, _) in _globs(outputs).items()}
    agents = _targets(outputs[0])
    duck = duckdb.sql(f"""
        SELECT count(*) FROM read_parquet('{g["predictions"]}') p
        JOIN read_parquet('{g["tracks"]}') t ON t.log_id = p.log_id AND t.track_id = p.track_id
         AND t.timestamp_ns = p.timestamp_ns[-1]
        JOIN read_parquet('{g["samples"]}') s ON s.sample_id = p.sample_id
        JOIN read_parquet('{g["logs"]}') l ON l.log_id = s.log_id""").fetchall()[0][0]
    assert duck == agents * K
    tracks, preds = pl.scan_parquet(g["tracks"]), pl.scan_parquet(g["predictions"])
    polars = (preds.with_columns(pl.col("timestamp_ns").arr.last().alias("t_last"))
              .join(tracks, left_on=["log_id", "track_id", "t_last"], right_on=["log_id", "track_id", "timestamp_ns"])
              .join(pl.scan_parquet(g["samples"]), on="sample_id")
              .join(pl.scan_parquet(g["logs"]), left_on="log_id", right_on="log_id").select(pl.len()).collect().item())
    assert polars == duck
    frames = {name: pd.read_parquet(Path(glob).parent) for name, glob in g.items()}
    frames["predictions"]["t_last"] = frames["predictions"]["timestamp_ns"].map(lambda v: v[-1])
    merged = (frames["predictions"]
              .merge(frames["tracks"], left_on=["log_id", "track_id", "t_last"],
                     right_on=["log_id", "track_id", "timestamp_ns"])
              .merge(frames["samples"], on="sample_id").merge(frames["logs"], left_on="log_id_x", right_on="log_id"))
    assert len(merged) == duck


def test_predictions_written_with_dictionary_ids_score_the_same(outputs: tuple[Path, Path], tmp_path: Path) -> None:
    """Files of earlier versions stored the ids as dictionaries: read alike (``as_current`` casts them)."""
    import pyarrow.parquet as pq

    ds_dir, run_dir = outputs
    [path] = sorted((run_dir / "predictions").glob("*.parquet"))  # one shard: one file is one method
    table = pq.read_table(path)
    encoded = pa.table({n: table[n].dictionary_encode() if n in IDS["predictions"] else table[n]
                        for n in table.column_names}).replace_schema_metadata(table.schema.metadata)
    assert encoded.schema.field("track_id").type == pa.dictionary(pa.int32(), pa.string())
    pq.write_table(encoded, tmp_path / "old.parquet")
    now = score([run_dir], ds_dir, tmp_path / "now", plots=False)["methods"]["cv"]["overall"]
    before = score([tmp_path / "old.parquet"], ds_dir, tmp_path / "before", plots=False)["methods"]["cv"]["overall"]
    assert before == now
