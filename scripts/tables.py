"""Markdown pieces every results file shares: the method names of the paper's network, the rows every table
leads with, ``ADE/FDE`` cells, the beaten / split verdict, and the note on how long a run took and on what."""

from __future__ import annotations

import platform
from collections.abc import Sequence
from typing import Any

AS_TRAINED = "zhu2020_scale1"
"""Method name of the paper's network run as trained (noise scale 1, its config's constant-velocity modes), beside
the tuned run."""

PAPER = "zhu2020_paper"
"""Method name of the paper's method as the paper specifies it (``configs/ethucy_paper.toml``: the model defaults, the
per-scene loss of eq. 23), sampled as trained (noise scale 1, no constant-velocity mode): the rows the table leads
with. ``zhu2020`` is the same network with our extensions, chosen on validation."""

PAPER_ROWS = (  # (label, method, k, ade key, fde key): the rows every results table leads with
    ("The paper's method as specified, best-of-20 per agent", PAPER, 20, "ade", "fde"),
    ("The paper's method as specified, best-of-20 joint (Social-GAN eval)", PAPER, 20, "ade_joint", "fde_joint"),
    ("The paper's method as specified, K=1", PAPER, 1, "ade", "fde"),
)

NETWORK_ROWS = (  # Noise-LSTM and ours, both best-of-K rules (the ETH/UCY and ApolloScape tables)
    ("Noise-LSTM, best-of-20 per agent (inference settings chosen on val)", "noise_lstm", 20, "ade", "fde"),
    ("Noise-LSTM, best-of-20 joint (inference settings chosen on val)", "noise_lstm", 20, "ade_joint", "fde_joint"),
    ("Ours: the method with our extensions (zhu2020), best-of-20 per agent (inference settings chosen on val)",
     "zhu2020", 20, "ade", "fde"),
    ("Ours: the method with our extensions (zhu2020), best-of-20 joint (inference settings chosen on val)",
     "zhu2020", 20, "ade_joint", "fde_joint"),
    ("Ours: the method with our extensions (zhu2020), best-of-20 per agent, as trained (s = 1)", AS_TRAINED, 20,
     "ade", "fde"),
    ("Ours: the method with our extensions (zhu2020), K=1, as trained (s = 1)", AS_TRAINED, 1, "ade", "fde"),
)


def pair(block: dict[str, Any] | None, a: str = "ade", f: str = "fde") -> str:
    """``ADE/FDE`` with two decimals."""
    return f"{block[a]:.2f}/{block[f]:.2f}" if block else "—"


def verdict(mine: Sequence[float], other: Sequence[float]) -> str:
    """The standing of (ADE, FDE) ``mine`` against ``other``: both lower beats it, neither lower does not."""
    if mine[0] < other[0] and mine[1] < other[1]:
        return "beaten"
    return "**not beaten**" if mine[0] >= other[0] and mine[1] >= other[1] else "split"


def machine_note(seconds: float) -> str:
    """How long it took, and on what."""
    import os

    load = os.getloadavg()[0]  # other jobs (training runs) share these cores: say so next to the time
    return (f"Wall time {seconds:.1f} s on this {os.cpu_count()}-core machine ({platform.processor() or 'cpu'}, "
            f"Python {platform.python_version()}, no GPU; 1-minute load average {load:.1f} at the end, so the machine "
            "was shared with other jobs when above 2).")
