"""How well the residual model's ``ood_score`` ranks the targets where its single forecast loses to its own
adaptive prior (issue 62, item 2): on the predictions of a residual checkpoint and of ``--predictor adaptive_cv``
over the same held-out dataset, per target the K = 1 FDE of both, then the ROC AUC of ``ood_score`` for "the model
is worse than the prior" (0.5: no better than chance), the flagged share and the loss among flagged and unflagged
targets::

    python -m scripts.ood_ranking --model PRED --prior PRED --truth DATASET

Prints one JSON object (metres).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

import duckdb
import numpy as np


def per_target(model: Path, prior: Path, truth: Path) -> dict[str, np.ndarray]:
    """Per target (mode 0 of each run): model FDE, prior FDE, ood_score, ood_flag."""
    relation = duckdb.sql(f"""
        WITH m AS (SELECT log_id, sample_id, track_id, x[-1] AS x, y[-1] AS y, timestamp_ns[-1] AS t, ood_score,
                          ood_flag FROM read_parquet('{model}/predictions/*.parquet') WHERE mode = 0),
             p AS (SELECT sample_id, track_id, x[-1] AS x, y[-1] AS y
                   FROM read_parquet('{prior}/predictions/*.parquet') WHERE mode = 0),
             g AS (SELECT log_id, track_id, timestamp_ns, x, y FROM read_parquet('{truth}/tracks/*.parquet'))
        SELECT sqrt((m.x - g.x) ** 2 + (m.y - g.y) ** 2), sqrt((p.x - g.x) ** 2 + (p.y - g.y) ** 2),
               m.ood_score, m.ood_flag
        FROM m JOIN p USING (sample_id, track_id)
        JOIN g ON g.log_id = m.log_id AND g.track_id = m.track_id AND g.timestamp_ns = m.t""")
    rows = relation.fetchall() if relation is not None else []
    if not rows:
        raise SystemExit("no target is in both runs and the truth")
    a = np.asarray(rows, dtype=object)
    return {"model_fde": a[:, 0].astype(float), "prior_fde": a[:, 1].astype(float),
            "score": a[:, 2].astype(float), "flag": a[:, 3].astype(bool)}


def roc_auc(score: np.ndarray, positive: np.ndarray) -> float:
    """P(score of a random positive > score of a random negative), ties counted half (Mann-Whitney U)."""
    pos, neg = score[positive], score[~positive]
    if not len(pos) or not len(neg):
        return float("nan")
    greater = (pos[:, None] > neg[None, :]).mean()
    ties = (pos[:, None] == neg[None, :]).mean()
    return float(greater + 0.5 * ties)


def summary(t: dict[str, np.ndarray]) -> dict[str, Any]:
    """The figures the module docstring names."""
    loses = t["model_fde"] > t["prior_fde"]
    flag = t["flag"]

    def mean(v: np.ndarray, rows: np.ndarray) -> float | None:
        return round(float(v[rows].mean()), 3) if rows.any() else None

    return {"targets": len(loses), "model_fde": mean(t["model_fde"], ~np.zeros_like(flag)),
            "prior_fde": mean(t["prior_fde"], ~np.zeros_like(flag)), "model_loses_share": round(float(loses.mean()), 3),
            "flagged": int(flag.sum()), "roc_auc_ood_score_for_loss": round(roc_auc(t["score"], loses), 3),
            "flagged_model_fde": mean(t["model_fde"], flag), "flagged_prior_fde": mean(t["prior_fde"], flag),
            "unflagged_model_fde": mean(t["model_fde"], ~flag), "unflagged_prior_fde": mean(t["prior_fde"], ~flag)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", type=Path, required=True, help="predict run of a residual checkpoint")
    parser.add_argument("--prior", type=Path, required=True, help="predict run of --predictor adaptive_cv")
    parser.add_argument("--truth", type=Path, required=True, help="the dataset both predicted")
    args = parser.parse_args()
    print(json.dumps(summary(per_target(args.model, args.prior, args.truth)), indent=2))


if __name__ == "__main__":
    main()
