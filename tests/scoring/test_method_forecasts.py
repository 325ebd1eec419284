"""One method's forecasts as ``logpipe score`` reads them (``logpipe.scoring.method_forecasts``): dense arrays from a
real prediction run folder, report labels, and the protocol check against the dataset."""

from __future__ import annotations

import shutil
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from logpipe.dataset.reader import Dataset
from logpipe.errors import ScoreError
from logpipe.scoring.method_forecasts import MethodForecasts, check_protocol, load_method, name_methods
from logpipe.stages.ingest import IngestOptions, ingest


@pytest.fixture(scope="module")
def run(bundled: Path) -> Path:
    """A ``logpipe predict`` run folder of the bundled Argoverse sample (cv_sampler, K = 6, T = 30)."""
    return bundled / "predictions_v1" / "av1_cv_sampler"


def test_a_run_folder_reads_as_dense_forecasts(run: Path) -> None:
    m = load_method(run)
    assert (m.name, m.predictor, m.run_name, m.source) == ("cv_sampler", "cv_sampler", "av1_cv_sampler", str(run))
    assert m.pred.shape == (6, 6, 30, 2) and m.num_modes == 6 and np.isfinite(m.pred).all()
    assert len(m.sample_ids) == len(m.track_ids) == len(m.object_types) == 6
    assert (m.meta.pred_len, m.meta.num_modes) == (30, 6)


def test_labels_given_else_predictor_else_folder_then_numbered(run: Path, tmp_path: Path) -> None:
    copy = tmp_path / "other_run"
    shutil.copytree(run, copy)
    a, b, c = load_method(run), load_method(copy), load_method(run)
    name_methods([a], None)
    assert a.name == "cv_sampler"  # one method: its predictor
    methods = [load_method(run), load_method(copy), c]
    name_methods(methods, None)  # predictors collide: the folder names, numbered where those collide too
    assert [m.name for m in methods] == ["av1_cv_sampler", "other_run", "av1_cv_sampler#2"]
    name_methods([a, b], ["CV", "CV"])
    assert [a.name, b.name] == ["CV", "CV#2"]
    with pytest.raises(ScoreError, match="1 labels for 2 methods"):
        name_methods([a, b], ["only one"])


def test_protocol_check_names_what_differs(run: Path, bundled: Path, tmp_path: Path) -> None:
    ingest([bundled / "argoverse1"], IngestOptions(out=tmp_path / "av1", write_mcap=False))
    ds = Dataset.open(tmp_path / "av1")
    m = load_method(run)
    check_protocol([m], ds)  # made on this sample with its protocol
    shorter: MethodForecasts = replace(m, meta=replace(m.meta, pred_len=12))
    with pytest.raises(ScoreError, match="horizon 12 steps, the dataset's protocol 30"):
        check_protocol([m, shorter], ds)
    other = replace(m, meta=replace(m.meta, protocol="ethucy", obs_len=8))
    with pytest.raises(ScoreError, match=r"protocol 'ethucy'.*; 8 observed steps"):
        check_protocol([other], ds)
