"""Checkpoints of the residual driving model: ``weights.safetensors`` and ``meta.json`` in one folder, never a
pickle, replaced whole (``logpipe.storage.folder_swap``) so a crash leaves the old folder or the new one.

``meta.json`` (``model.residual.meta``) names the weights' sha256; weights load only when their sha256 is that one,
and only finite weights are accepted.
"""

from __future__ import annotations

import json
import os
import shutil
import time
from pathlib import Path

from safetensors.torch import save_file

from logpipe.storage.folder_swap import recover_folder, replace_folder, staging_folder_for
from logpipe.storage.io import sha256_file

from ..checkpoint.format import CheckpointError, logpipe_version
from ..checkpoint.weights_folder import load_weights
from .meta import META, WEIGHTS, ResidualMeta, read_residual_meta
from .net import ResidualNet


def save_residual(folder: Path, net: ResidualNet, meta: ResidualMeta) -> Path:
    """Write the checkpoint folder (replacing one that is there), ``meta.json`` last, naming the weights' sha256."""
    recover_folder(folder)
    staging = staging_folder_for(folder)
    try:
        staging.mkdir(parents=True, exist_ok=True)
        weights = staging / WEIGHTS
        save_file({k: v.detach().cpu().contiguous().clone() for k, v in net.state_dict().items()}, str(weights))
        meta.weights_sha256 = sha256_file(weights)
        meta.logpipe_version, meta.created_unix = logpipe_version(), time.time()
        tmp = staging / (META + ".tmp")
        tmp.write_text(json.dumps(meta.to_dict(), indent=2, sort_keys=True) + "\n", encoding="utf-8")
        os.replace(tmp, staging / META)
        replace_folder(staging, folder)
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    return folder


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
