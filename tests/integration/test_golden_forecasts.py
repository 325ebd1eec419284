"""Every shipped checkpoint's forecasts on the bundled samples, pinned: a refactor must not move them.

``logpipe predict`` (its defaults: the checkpoint's stored inference settings, seed 0) runs every shipped checkpoint
over the first 59 samples of the bundled ETH ``eth/test`` scene, the bundled ApolloScape files, or the two held-out
Argoverse 1 sequences over their lane rasters. ``tests/data/golden/forecasts.npz`` pins, per checkpoint, the sha256
of the dense (agents, K, T, 2) float32 forecasts, the first 8 agents' forecasts and every agent's mean forecast point
(small enough for git). Across machines the CPU's vector units may change the last bits of float32 maths, so the
test compares those arrays to 1e-4 m plus 4 float32 ulps; ``LOGPIPE_GOLDEN_EXACT=1`` demands the same sha256 (the
before/after check of a restructuring on one machine);

``LOGPIPE_GOLDEN_WRITE=1`` writes this machine's pins into the file (only when a change is meant to move forecasts;
say why in the commit).

A checkpoint with the environment net runs its backbone in bf16 on a CPU with native bf16
(``model.zhu2020.backbone``): its forecasts there move by up to ~1 cm, far past the fp32 tolerance, so they are
pinned apart, under ``NAME@bf16``. Each machine checks the pins of the arithmetic it runs; writing keeps the other
arithmetic's pins.
"""

from __future__ import annotations

import hashlib
import os
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from logpipe.cli import app
from logpipe.model.residual.meta import model_kind
from logpipe.model.zhu2020.backbone import backbone_runs_bf16
from logpipe.model.zhu2020.meta import MODEL_KIND as ZHU2020_KIND
from logpipe.model.zhu2020.meta import read_meta
from logpipe.prediction.runs import PredictionRun

pytestmark = pytest.mark.slow  # minutes of end-to-end work

REPO = Path(__file__).resolve().parents[2]
DATA = REPO / "tests" / "data"
GOLDEN = DATA / "golden" / "forecasts.npz"
SHIPPED = REPO / "model" / "checkpoints"
CHECKPOINTS = sorted(p for p in (m.parent.relative_to(SHIPPED) for m in SHIPPED.glob("**/meta.json"))
                     if p.parts[0] in ("ethucy", "apolloscape", "argoverse"))
# Forecasts are world coordinates: at ~2,500 m one float32 ulp is 2.4e-4 m, so a CPU with other vector units may
# move a point by a few ulps (seen: 1 ulp at 2,523 m between the machine that wrote the pins and an AMD EPYC
# with AVX-512).
FLOAT32_ULPS = 4 * float(np.finfo(np.float32).eps)
runner = CliRunner()


def _run(*args: str) -> None:
    result = runner.invoke(app, ["-q", *args])
    assert result.exit_code == 0, result.output


@pytest.fixture(scope="module")
def datasets(tmp_path_factory: pytest.TempPathFactory) -> dict[str, tuple[Path, list[str]]]:
    """Ingested (and, for Argoverse, rasterised) bundled samples per checkpoint family, with predict's filter."""
    root = tmp_path_factory.mktemp("golden")
    driving = DATA / "driving"
    _run("ingest", str(DATA / "ethucy"), "--out", str(root / "ethucy"), "--no-mcap")
    _run("ingest", str(DATA / "apolloscape"), "--out", str(root / "apolloscape"), "--no-mcap")
    _run("ingest", str(driving / "20.csv"), str(driving / "32.csv"), "--out", str(root / "argoverse"), "--no-mcap")
    _run("rasterise", str(root / "argoverse"), "--map", f"MIA={driving / 'MIA_lane_centerlines_crop_20.npz'}",
         "--map", f"PIT={driving / 'PIT_lane_centerlines_crop_32.npz'}", "--rotate")
    # The first 59 of the 253 eth/test samples: 25 checkpoints run on them, and the rest pass the same code.
    eth_test_head = ["--filter", "split=eth/test", "--filter", "time=:340000000000"]
    return {"ethucy": (root / "ethucy", eth_test_head), "apolloscape": (root / "apolloscape", []),
            "argoverse": (root / "argoverse", [])}


def _forecasts(checkpoint: Path, data: Path, filters: list[str], out: Path) -> np.ndarray:
    _run("predict", str(data), "--checkpoint", str(SHIPPED / checkpoint), *filters,
         "--out", str(out), "--no-mcap")
    dense = PredictionRun.open(out).dense()
    return np.asarray(dense.pred, dtype=np.float32)


def test_shipped_checkpoints_predict_the_pinned_forecasts(datasets: dict[str, tuple[Path, list[str]]],
                                                          tmp_path: Path) -> None:
    assert len(CHECKPOINTS) >= 11 and {Path("argoverse/paper"), Path("argoverse/residual")} <= set(CHECKPOINTS)
    got = {}
    for i, ckpt in enumerate(CHECKPOINTS):
        data, filters = datasets[ckpt.parts[0]]
        got[str(ckpt)] = _forecasts(ckpt, data, filters, tmp_path / f"p{i}")
        assert np.isfinite(got[str(ckpt)]).all() and got[str(ckpt)].shape[0] > 0
    pins = {f"{name}{_arithmetic(Path(name))}:{part}": value for name, forecasts in got.items()
            for part, value in _pins(forecasts).items()}
    if os.environ.get("LOGPIPE_GOLDEN_WRITE") == "1":
        GOLDEN.parent.mkdir(parents=True, exist_ok=True)
        kept = {k: v for k, v in np.load(GOLDEN).items() if k not in pins} if GOLDEN.exists() else {}
        np.savez_compressed(GOLDEN, **kept, **pins)  # type: ignore[arg-type]  # numpy types **kwds against allow_pickle
    pinned = np.load(GOLDEN)
    assert {k.split(":")[0].split("@")[0] for k in pinned.files} == set(got), (
        "a shipped checkpoint was added or removed: rewrite the golden file")
    unpinned = sorted(set(pins) - set(pinned.files))
    assert not unpinned, f"no pins for this machine's arithmetic: {unpinned}"
    exact = os.environ.get("LOGPIPE_GOLDEN_EXACT") == "1"
    moved = []
    for key, value in pins.items():
        if key.endswith(":sha256"):
            if exact and str(pinned[key]) != str(value):
                moved.append(f"{key}: another sha256")
        elif not np.allclose(value, pinned[key], rtol=FLOAT32_ULPS, atol=1e-4):
            moved.append(f"{key}: moved by up to {np.abs(value - pinned[key]).max():.3g} m")
    assert not moved, moved


def _arithmetic(checkpoint: Path) -> str:
    """``@bf16`` where the checkpoint's backbone runs in bf16 on this CPU, else '' (only the paper's network has
    one: the residual model and the social baselines run fp32 everywhere)."""
    if model_kind(SHIPPED / checkpoint) != ZHU2020_KIND:
        return ""
    return "@bf16" if backbone_runs_bf16(read_meta(SHIPPED / checkpoint).config.model) else ""


def _pins(forecasts: np.ndarray) -> dict[str, np.ndarray]:
    """What the golden file keeps of one checkpoint's (N, K, T, 2) forecasts."""
    return {"sha256": np.array(hashlib.sha256(np.ascontiguousarray(forecasts).tobytes()).hexdigest()),
            "head": forecasts[:8], "mean": forecasts.mean(axis=(1, 2), dtype=np.float64)}
