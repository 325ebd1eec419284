"""Checkpoints of the residual driving model: ``weights.safetensors`` and ``meta.json`` in one folder, never a
pickle, replaced whole (``logpipe.storage.folder_swap``) so a crash leaves the old folder or the new one.

``meta.json`` (``model.residual.meta``) names the weights' sha256; weights load only when their sha256 is that one,
and only finite weights are accepted.
"""

from __future__ import annotations

from pathlib import Path

from ..checkpoint.format import CheckpointError
from ..checkpoint.weights_folder import load_weights, save_weights_folder
from .meta import WEIGHTS, ResidualMeta, read_residual_meta
from .net import ResidualNet


def save_residual(folder: Path, net: ResidualNet, meta: ResidualMeta) -> Path:
    """Write the checkpoint folder (replacing one that is there), ``meta.json`` last, naming the weights' sha256."""
    return save_weights_folder(folder, net.state_dict(), meta)


def load_residual(folder: Path) -> tuple[ResidualNet, ResidualMeta]:
    """The network (eval mode) and metadata of a checkpoint folder.

    Raises:
        CheckpointError: metadata as in ``read_residual_meta``; weights missing, not matching their sha256, not
            fitting the config, or not finite.
    """
    meta = read_residual_meta(folder)
    weights = folder / WEIGHTS
    state = load_weights(folder, meta.weights_sha256)
    net = ResidualNet(meta.config)
    try:
        net.load_state_dict(state)
    except RuntimeError as exc:
        raise CheckpointError(f"{weights}: weights do not fit the residual config in meta.json: "
                              f"{str(exc).splitlines()[0]}") from None
    return net.eval(), meta
