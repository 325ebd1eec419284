"""Social-LSTM behind the ``Predictor`` interface: K = 1 is the rollout of the Gaussian's mean; K > 1 are K rollouts
each drawing every agent's steps from its Gaussian (a joint draw of the window), from the sample's own seed."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

from logpipe.errors import LogpipeError
from logpipe.types import NDArrayFloat, SceneSample

from ..checkpoint.format import CheckpointError
from ..checkpoint.weights_folder import WeightsMeta, load_into, load_weights, read_weights_meta
from .config import MODEL_KIND, SocialLstmConfig
from .fit import scene_forecasts
from .net import SocialLstm


def load_net(folder: Path) -> tuple[SocialLstm, WeightsMeta]:
    """The network (eval mode) of a Social-LSTM checkpoint folder and its metadata.

    Raises:
        CheckpointError: see ``model.checkpoint.weights_folder``; a config that does not parse.
    """
    meta = read_weights_meta(folder, (MODEL_KIND,))
    try:
        config = SocialLstmConfig.from_dict(meta.config, str(folder / "meta.json"))
    except LogpipeError as exc:
        raise CheckpointError(str(exc)) from None
    net = SocialLstm(config)
    load_into(net, load_weights(folder, meta.weights_sha256), folder)
    return net.eval(), meta


class SocialLstmPredictor:
    """A Social-LSTM checkpoint as a ``Predictor``."""

    name = MODEL_KIND

    def __init__(self, net: SocialLstm, meta: WeightsMeta) -> None:
        self.net, self.meta = net.eval(), meta

    @classmethod
    def from_checkpoint(cls, folder: Path) -> SocialLstmPredictor:
        """Load a checkpoint folder (``load_net``'s checks)."""
        return cls(*load_net(folder))

    def predict(self, samples: Sequence[SceneSample], num_modes: int, seed: int) -> list[NDArrayFloat]:
        """Per sample (N_targets, num_modes, T_pred, 2) world metres."""
        return scene_forecasts(self.net, samples, num_modes, seed)
