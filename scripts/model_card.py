"""Write model/checkpoints/<kind>/MODEL_CARD.md from the shipped checkpoints' training summaries.

Reads only what `make train-ethucy` / `make train-apolloscape` copy next to each checkpoint (``meta.json``,
``train_summary.json``), so the card can be rebuilt from a clean clone.

Usage: ``python -m scripts.model_card [--seed N] [--seeds-dir DIR] [ethucy|apolloscape ...]`` (default: both;
seed 0, the shipped ``model/checkpoints/<kind>`` folders, else ``DIR/seedN/<kind>``, ``out/checkpoints`` by default:
``make train-* SEED=N`` trains the extra seeds there, outside the package).
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
import time
import tomllib
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from scripts.locations import CHECKPOINTS, REPO, SEEDS_DIR

METHODS = {"paper": "the paper's method as the paper specifies it (`configs/<kind>_paper.toml`: every model default, "
                    "the per-scene loss of eq. 23, no augmentation; `make train-<kind>-paper`)",
           "zhu2020": "the paper's network with our extensions (`configs/<kind>.toml`), the default of `logpipe "
                      "predict`", "noise_lstm": "Noise-LSTM (preset `baseline`)",
           "lstm": "LSTM (preset `lstm`, no noise, K=1)"}
ABLATIONS = {"ethucy": {"no_position": "the paper's method without its position feature (eqs. 1-2; preset "
                                       "`no_position`), an ablation"}}

ABOUT = {
    "ethucy": """Leave-one-scene-out models, one per held-out scene, trained with `make train-ethucy` (`logpipe train
out/ethucy --scene SCENE --config configs/ethucy.toml [--preset baseline|lstm|no_position]`). The paper's network
with our extensions is in `ethucy/<scene>/`, the paper's method as the paper specifies it in `ethucy/<scene>/paper/`
(`make train-ethucy-paper`), the baselines in `ethucy/<scene>/noise_lstm/` and `ethucy/<scene>/lstm/`, the ablation
without the position feature in `ethucy/<scene>/no_position/`.

- **Data:** `logpipe ingest ../shared/data/ethucy` (Social-GAN split files). Training logs: memberships
  `SCENE/train`; validation: `SCENE/val` (the held-out scene is never seen). Samples: 8 observed + 12 predicted steps
  at 2.5 Hz, every window whose agents are present at all 20 steps.
- **Features:** position (eqs. 1-2) and tracking (eqs. 3-4) features, GRU (eqs. 6-7), attention (13-14),
  LSTM encoder-decoder with noise (15-22), best-of-H loss (23) with H = 20. ETH/UCY has no ego vehicle and no map,
  so the ego-motion, ego-trajectory and environment features are off, as in the paper.""",
    "apolloscape": """Models trained with `make train-apolloscape` (`logpipe train out/reproduce/apolloscape/dataset
--train-split hash/train --val-split hash/val --config configs/apolloscape.toml [--preset baseline|lstm]`), in
`apolloscape/<method>/`; the paper's method as the paper specifies it in `apolloscape/paper/`
(`make train-apolloscape-paper`).

- **Data:** `logpipe ingest ../shared/data/apolloscape/prediction_train --format apolloscape`; the files are split
  70/15/15 by the sha256 of their log id (`hash/train`, `hash/val`, `hash/test`). 6 observed + 6 predicted steps at
  2 Hz; every agent present in all 12 steps of a window is a target, whatever its type.
- **Features:** position and tracking features, GRU, attention, LSTM encoder-decoder with noise, best-of-H loss
  with H = 20. The logs have no ego vehicle and no map here, so the ego and environment features are off.""",
}


def _row(name: str, folder: Path) -> str:
    meta_path, summary_path = folder / "meta.json", folder / "train_summary.json"
    if not meta_path.is_file():
        return f"| {name} | not trained | | | | | |"
    meta: dict[str, Any] = json.loads(meta_path.read_text())
    s: dict[str, Any] = json.loads(summary_path.read_text()) if summary_path.is_file() else {}
    seconds = s.get("seconds_total", s.get("seconds"))  # a resumed run's total covers every part
    minutes = f"{seconds / 60:.1f}" if seconds is not None else "?"
    metrics = meta.get("metrics", {})
    k = meta["config"]["val_modes"]
    steps = s.get("steps", "?")
    if "resumed_at_step" in s:  # trained in two parts: to resumed_at_step, then `logpipe train --resume`
        steps = f"{steps} (resumed at {s['resumed_at_step']})"
    return (f"| {name} | {s.get('train_samples', '?')} / {s.get('val_samples', '?')} | {steps} | "
            f"{meta['step']} | {metrics.get('val_ade', float('nan')):.3f} / {metrics.get('val_fde', float('nan')):.3f}"
            f" (K={k}) | {s.get('train_samples_per_s', '?')} | {minutes} |")


def card(kind: str, seed: int = 0, seeds_dir: Path = SEEDS_DIR) -> str:
    """The Markdown card of ``model/checkpoints/<kind>`` (of ``seeds_dir/seed<seed>/<kind>`` for seed > 0)."""
    root = _root(seed, seeds_dir) / kind
    config = (REPO / "configs" / f"{kind}.toml").read_text()
    val_limit = tomllib.loads(config).get("train", {}).get("val_max_samples")
    val_on = f"first {val_limit} validation samples" if val_limit else "the whole validation split"
    trained = METHODS | ABLATIONS.get(kind, {})
    if kind == "ethucy":
        scenes = ("eth", "hotel", "univ", "zara1", "zara2")
        folders = [(f"{s} ({m})", root / s if m == "zhu2020" else root / s / m) for m in trained for s in scenes]
        label = "held-out scene (method)"
    else:
        folders = [(m, root / m) for m in trained]
        label = "method"
    rows = "\n".join(_row(name, folder) for name, folder in folders)
    methods = "; ".join(f"`{k}`: {v.replace('<kind>', kind)}" for k, v in trained.items())
    paper_config = REPO / "configs" / f"{kind}_paper.toml"
    seed_note = str(seed) if seed == 0 else (f"{seed} (`make train-{kind} SEED={seed}`; seed 0 is in "
                                             f"`model/checkpoints/{kind}/`)")
    return f"""# {kind} checkpoints

{ABOUT[kind]}
- **Methods:** {methods}. The baselines train with `configs/{kind}.toml`; `--preset` only switches the features off
  (and, for LSTM, the noise), so the schedule, data and augmentation match. `paper` shares that schedule only.
- **Seed:** {seed_note}, one torch thread per run, two runs at a time on a 2-core CPU shared with other jobs.
  Card written {time.strftime('%Y-%m-%d', time.gmtime())} on Python {platform.python_version()}.
- **Schedule:** much shorter than the paper's 20,000 steps, so a model trains in minutes here; early stopping on
  the validation ADE ({val_on}). See the config below. A run "resumed at N" was trained to step N under
  the config's earlier step count and continued with `logpipe train --resume` (an exact resume: the same weights
  as one uninterrupted run); its minutes add both parts and its samples/s is the second part's.
- **Validation errors** are per-agent best-of-K ADE/FDE in metres (mean Euclidean distance) on the validation
  split at the best step; test scores are in `docs/results/{kind}.md`.

Each folder holds `weights.safetensors` (safetensors, no pickle), `meta.json` (full config, normalisation, dataset
manifest hash, logpipe version, the splits and recordings (sha256) it was trained and validated on, and, once
`make reproduce-*` has chosen them on validation, the inference settings K, constant-velocity modes, noise scale and
neighbour cap that `logpipe predict` uses by default), `train_summary.json` and `train_log.jsonl`. Load with
`logpipe.model.zhu2020.checkpoint.load_checkpoint(path, expect_kind="{kind}")`.

| {label} | train / val samples | steps run | best step | val ADE / FDE (m) | train samples/s | minutes |
|---|---|---|---|---|---|---|
{rows}

## Config (`configs/{kind}.toml`)

```toml
{config.strip()}
```
""" + (f"""
## Config of `paper` (`configs/{kind}_paper.toml`)

```toml
{paper_config.read_text().strip()}
```
""" if paper_config.is_file() else "")


def _root(seed: int, seeds_dir: Path) -> Path:
    """Where ``make train-* SEED=seed`` puts its checkpoints: the package for seed 0, ``seeds_dir/seedN`` else."""
    return CHECKPOINTS if seed == 0 else seeds_dir / f"seed{seed}"


def main(argv: Sequence[str] | None = None) -> int:
    """Write the cards; returns the exit code."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    # no `choices`: argparse rejects an empty `nargs="*"` list against them (the default: every dataset)
    ap.add_argument("kinds", nargs="*", metavar="{ethucy,apolloscape}", help="datasets (default: both)")
    ap.add_argument("--seed", type=int, default=0, help="training seed (0: the shipped checkpoints)")
    ap.add_argument("--seeds-dir", type=Path, default=SEEDS_DIR,
                    help="the extra seeds' checkpoints, seedN/<kind>/... (default: out/checkpoints)")
    args = ap.parse_args(argv)
    if unknown := sorted(set(args.kinds) - set(ABOUT)):
        ap.error(f"unknown datasets {unknown}: expected some of {sorted(ABOUT)}")
    for kind in args.kinds or ["ethucy", "apolloscape"]:
        path = _root(args.seed, args.seeds_dir) / kind / "MODEL_CARD.md"
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(card(kind, args.seed, args.seeds_dir))
        print(path)
    return 0


if __name__ == "__main__":
    sys.exit(main())
