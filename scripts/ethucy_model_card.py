"""Write model/checkpoints/ethucy/MODEL_CARD.md from the training summaries of `make train-ethucy`."""

from __future__ import annotations

import json
import platform
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
SCENES = ("eth", "hotel", "univ", "zara1", "zara2")


def main() -> int:
    runs = REPO / "out" / "runs" / "ethucy"
    card = REPO / "model" / "checkpoints" / "ethucy" / "MODEL_CARD.md"
    config = (REPO / "configs" / "ethucy.toml").read_text()
    rows = []
    for scene in SCENES:
        path = runs / f"{scene}.json"
        if not path.is_file():
            rows.append(f"| {scene} | not trained | | | | | |")
            continue
        s = json.loads(path.read_text())
        rows.append(
            f"| {scene} | {s['train_samples']} / {s['val_samples']} | {s['steps']} | {s['best_step']} | "
            f"{s['best_val_ade']:.3f} / {s['best_val_fde']:.3f} | {s['train_samples_per_s']} | "
            f"{s['seconds'] / 60:.1f} |"
        )
    text = f"""# ETH/UCY leave-one-scene-out checkpoints

Five models of the Zhu et al. (IJCAI 2020) predictor, one per held-out scene, trained by project code with
`make train-ethucy` (`logpipe train out/ethucy --scene SCENE --config configs/ethucy.toml`). Each folder holds
`weights.safetensors` and `meta.json` (full config, normalisation, dataset manifest hash, logpipe version) plus the
training summary and log. Load with `logpipe.model.checkpoints.load_checkpoint(path, expect_kind="ethucy")`.

- **Data:** `logpipe ingest ../shared/data/ethucy` (Social-GAN split files). Training logs: memberships
  `SCENE/train`; validation: `SCENE/val` (the held-out scene is never seen). Samples: 8 observed + 12 predicted steps
  at 2.5 Hz, every window whose agents are present at all 20 steps (min 1 agent per window).
- **Features:** position (eqs. 1-2) and tracking (eqs. 3-4) features, GRU (eqs. 6-7), attention (13-14),
  LSTM encoder-decoder with noise (15-22), best-of-H loss (23) with H = 20. ETH/UCY has no ego vehicle and no map,
  so the ego-motion, ego-trajectory and environment features are off, as in the paper.
- **Seed:** 0. **Machine:** 2-core CPU shared with other jobs (load average 3-4 during training), one torch
  thread per run, two runs at a time. Written {time.strftime('%Y-%m-%d', time.gmtime())} on Python
  {platform.python_version()}.
- **Schedule:** shorter than the paper's 20,000 steps so a split trains in minutes here; early stopping on the
  validation best-of-20 ADE (first 300 validation samples). See the config below.
- **Validation errors** are best-of-20 ADE/FDE in metres (mean Euclidean distance, per agent min over the 20
  samples) on the validation split; test-split scores are in `docs/results/ethucy.md`.

| held-out scene | train / val samples | steps run | best step | val ADE / FDE (m) | train samples/s | minutes |
|---|---|---|---|---|---|---|
""" + "\n".join(rows) + f"""

## Config (`configs/ethucy.toml`)

```toml
{config.strip()}
```
"""
    card.parent.mkdir(parents=True, exist_ok=True)
    card.write_text(text)
    print(card)
    return 0


if __name__ == "__main__":
    sys.exit(main())
