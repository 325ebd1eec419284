"""Displacement metrics for trajectory forecasts: pure, vectorised functions over NumPy arrays.

Shapes and units, once for the module:

* ``pred``: (N, K, T, 2) predicted positions, metres, world frame; N agents, K modes (mode 0 = the most
  likely one, as the predictions contract orders them), T future steps.
* ``truth``: (N, T, 2) true future positions, metres, same frame.
* ``err``: (N, K, T) Euclidean (L2) distance between prediction and truth per step, metres.

Conventions (the literature disagrees on them; every function says which one it implements):

* **ADE** is the *mean Euclidean distance* over the T future steps, in metres. The Zhu et al. paper calls
  it a "mean square error", but the numbers it compares against (Social-GAN, Argoverse) are mean L2
  distances, not squared errors, so that is what we compute.
* **FDE** is the Euclidean distance at the last future step, in metres.
* **K=1** uses mode 0 only.
* **Per-agent best-of-K** (Social-STGCNN, most ETH/UCY papers after it): for each agent independently the
  minimum ADE over the K modes, and, separately, the minimum FDE over the K modes (the two minima may come
  from different modes).
* **Joint (scene) best-of-K** (Social-GAN's ``evaluate_model.py``): for each sample the mode whose ADE
  *summed over the sample's agents* is lowest (one mode index for the whole scene), likewise for FDE.
* **Argoverse** (argoverse-api ``eval_forecasting``): for each agent the mode with the lowest FDE; *its*
  ADE and FDE are reported (minADE is therefore not the minimum ADE); a miss is that FDE > 2.0 m.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from logpipe.types import NDArrayBool, NDArrayFloat, NDArrayInt

MISS_THRESHOLD_M = 2.0
"""Argoverse miss threshold on the final displacement, metres (the official evaluator's default run)."""


def displacement_errors(pred: NDArrayFloat, truth: NDArrayFloat) -> NDArrayFloat:
    """L2 distance per agent, mode and step.

    Args:
        pred: (N, K, T, 2) metres.
        truth: (N, T, 2) metres.

    Returns:
        (N, K, T) metres; NaN wherever either side is NaN.
    """
    if pred.ndim != 4 or truth.ndim != 3 or pred.shape[0] != truth.shape[0] or pred.shape[2:] != truth.shape[1:]:
        raise ValueError(f"shapes do not match: pred {pred.shape} (N, K, T, 2), truth {truth.shape} (N, T, 2)")
    diff = pred - truth[:, None]
    out: NDArrayFloat = np.hypot(diff[..., 0], diff[..., 1])
    return out


def ade_per_mode(err: NDArrayFloat) -> NDArrayFloat:
    """(N, K) mean L2 over the T steps, metres."""
    out: NDArrayFloat = err.mean(axis=-1)
    return out


def fde_per_mode(err: NDArrayFloat) -> NDArrayFloat:
    """(N, K) L2 at the last step, metres."""
    out: NDArrayFloat = err[..., -1]
    return out


def top_k(err: NDArrayFloat, k: int) -> NDArrayFloat:
    """The first ``k`` modes (the ``k`` most likely ones, since modes are sorted by descending score).

    This is how the Argoverse evaluator applies ``max_n_guesses``: K=1 of a 6-mode forecast is its mode 0.
    """
    if not 1 <= k <= err.shape[1]:
        raise ValueError(f"k={k} but the forecast has {err.shape[1]} modes")
    return err[:, :k]


@dataclass(frozen=True)
class AgentScores:
    """Per-agent results of one convention (arrays of length N, metres).

    Attributes:
        ade: the ADE this convention reports for each agent.
        fde: the FDE this convention reports for each agent.
        mode: (N,) mode index whose per-step errors make the agent's horizon curve.
    """

    ade: NDArrayFloat
    fde: NDArrayFloat
    mode: NDArrayInt


def best_of_k_per_agent(err: NDArrayFloat) -> AgentScores:
    """Per-agent best-of-K (ETH/UCY literature): min over modes of ADE and, independently, of FDE.

    ``mode`` is the argmin-ADE mode, so the mean of ``error_by_step`` over steps equals the mean ``ade``.
    With K=1 this is plain ADE/FDE.
    """
    ade = ade_per_mode(err)
    fde = fde_per_mode(err)
    return AgentScores(ade=ade.min(axis=1), fde=fde.min(axis=1), mode=np.argmin(ade, axis=1).astype(np.int64))


def argoverse(err: NDArrayFloat) -> AgentScores:
    """Argoverse convention: the mode with the lowest FDE (first on ties), and that mode's ADE and FDE."""
    fde = fde_per_mode(err)
    mode = np.argmin(fde, axis=1).astype(np.int64)
    rows = np.arange(err.shape[0])
    return AgentScores(ade=ade_per_mode(err)[rows, mode], fde=fde[rows, mode], mode=mode)


def miss(fde: NDArrayFloat, threshold_m: float = MISS_THRESHOLD_M) -> NDArrayBool:
    """(N,) True where the final displacement exceeds ``threshold_m`` metres (Argoverse: 2.0 m)."""
    out: NDArrayBool = fde > threshold_m
    return out


def best_of_k_joint(err: NDArrayFloat, group: NDArrayInt) -> AgentScores:
    """Joint (scene) best-of-K, Social-GAN's evaluation: one mode per sample, chosen by summed error.

    Args:
        err: (N, K, T) metres.
        group: (N,) integer sample index of each agent (any labels; agents of a sample share one).

    Returns:
        per-agent ADE (from the sample's min-summed-ADE mode) and FDE (from its min-summed-FDE mode); their
        means over agents equal Social-GAN's ``sum over samples of min_k sum over agents / number of agents``.
    """
    _, inverse = np.unique(group, return_inverse=True)
    n_groups = int(inverse.max()) + 1 if len(inverse) else 0
    ade = ade_per_mode(err)
    fde = fde_per_mode(err)
    k = err.shape[1]
    sums_ade = np.zeros((n_groups, k))
    sums_fde = np.zeros((n_groups, k))
    np.add.at(sums_ade, inverse, ade)
    np.add.at(sums_fde, inverse, fde)
    mode_ade = np.argmin(sums_ade, axis=1)[inverse]
    mode_fde = np.argmin(sums_fde, axis=1)[inverse]
    rows = np.arange(err.shape[0])
    return AgentScores(ade=ade[rows, mode_ade], fde=fde[rows, mode_fde], mode=mode_ade.astype(np.int64))


def error_by_step(err: NDArrayFloat, mode: NDArrayInt) -> NDArrayFloat:
    """(T,) mean over agents of the L2 error at each future step, using each agent's ``mode``, metres."""
    if err.shape[0] == 0:
        return np.full(err.shape[2], np.nan)
    out: NDArrayFloat = err[np.arange(err.shape[0]), mode].mean(axis=0)
    return out


def group_metrics(err: NDArrayFloat, sample_idx: NDArrayInt, ks: Sequence[int], miss_threshold_m: float
                  ) -> dict[str, Any]:
    """A report block for one group of agents: counts and, for each k in ``ks``, every convention's means over
    the agents of ``err`` (N, K, T) metres; ``sample_idx`` (N,) the sample of each agent (for the joint choice).
    ``kN`` is None when the group has no agent."""
    out: dict[str, Any] = {"samples": len(np.unique(sample_idx)), "agents": int(err.shape[0])}
    for k in ks:
        e = top_k(err, k)
        if e.shape[0] == 0:
            out[f"k{k}"] = None
            continue
        per_agent = best_of_k_per_agent(e)
        joint = best_of_k_joint(e, sample_idx)
        argo = argoverse(e)
        out[f"k{k}"] = {
            "ade": float(per_agent.ade.mean()),
            "fde": float(per_agent.fde.mean()),
            "ade_joint": float(joint.ade.mean()),
            "fde_joint": float(joint.fde.mean()),
            "argo_ade": float(argo.ade.mean()),
            "argo_fde": float(argo.fde.mean()),
            "miss_rate": float(miss(argo.fde, miss_threshold_m).mean()),
            "error_by_step": [float(v) for v in error_by_step(e, per_agent.mode)],
        }
    return out


@dataclass(frozen=True)
class PairedDifference:
    """Mean of per-agent paired differences (method A minus method B, metres) and its bootstrap interval.

    Attributes:
        mean: mean difference over the agents (negative: A's error is lower).
        low: lower end of the interval.
        high: upper end of the interval.
        agents: agents averaged.
        clusters: resampling units (e.g. blocks of overlapping windows).
    """

    mean: float
    low: float
    high: float
    agents: int
    clusters: int


def paired_difference_interval(diff: NDArrayFloat, cluster: NDArrayInt, *, resamples: int = 2000,
                               level: float = 0.95, seed: int = 0) -> PairedDifference:
    """Percentile cluster bootstrap of the mean of ``diff`` (N,) per-agent paired differences.

    Whole clusters (``cluster`` (N,) integer labels) are resampled with replacement and the agent-weighted mean
    is taken of each resample, so agents that share a cluster (the targets of one window, windows that overlap
    in time) are not counted as independent. The interval covers test sampling only, not training seeds.
    Hand-written (a dozen lines of NumPy): scipy is not a dependency, and its ``bootstrap`` resamples
    observations, not clusters.
    """
    if diff.shape != cluster.shape or diff.ndim != 1 or not len(diff):
        raise ValueError(f"diff {diff.shape} and cluster {cluster.shape} must be equal, non-empty 1-D arrays")
    _, label = np.unique(cluster, return_inverse=True)
    n = int(label.max()) + 1
    total = np.bincount(label, weights=diff, minlength=n)
    count = np.bincount(label, minlength=n).astype(np.float64)
    picks = np.random.default_rng(seed).integers(0, n, size=(resamples, n))
    means = total[picks].sum(axis=1) / count[picks].sum(axis=1)
    tail = (1.0 - level) / 2 * 100
    low, high = np.percentile(means, [tail, 100 - tail])
    return PairedDifference(float(diff.mean()), float(low), float(high), len(diff), n)
