"""A baseline runs numpy: ``logpipe predict`` with one never imports torch, whose import is most of a small run's
start (a constant-velocity CLI run on ETH/UCY hotel/test: ~2.2 s with it, ~0.8 s without)."""

from __future__ import annotations

import subprocess
import sys
import textwrap
from pathlib import Path

from logpipe.stages.ingest import IngestOptions, ingest


def test_a_baseline_run_never_imports_torch(bundled: Path, driving_rasterised: Path, tmp_path: Path) -> None:
    # Both predict paths, in a fresh interpreter: column-wise (Parquet only) and per sample (raster images in the
    # MCAPs), then a --device check, which a baseline run also does.
    ingest([bundled / "ethucy"], IngestOptions(out=tmp_path / "eth", workers=1, write_mcap=False))
    script = textwrap.dedent(f"""
        import sys
        from pathlib import Path
        from logpipe.stages.predict import predict_dataset
        columnar = predict_dataset(Path({str(tmp_path / "eth")!r}), Path({str(tmp_path / "p1")!r}),
                                   predictor="cv", write_mcap=False, workers=1)
        rasters = predict_dataset(Path({str(driving_rasterised)!r}), Path({str(tmp_path / "p2")!r}),
                                  predictor="cv", raster_images=True, workers=1, device="auto")
        print(columnar["samples"], rasters["samples"], rasters["mcap_files"], "torch" in sys.modules)
    """)
    done = subprocess.run([sys.executable, "-c", script], check=True, capture_output=True, text=True)
    columnar, rasters, mcaps, torch_loaded = done.stdout.split()
    assert int(columnar) > 0 and int(rasters) > 0 and int(mcaps) > 0
    assert torch_loaded == "False"
