"""Social-GAN behind the ``Predictor`` interface: K samples per window, one noise draw per window and sample shared
by its agents (so each sample is a joint forecast of the scene, as Social-GAN's evaluation takes them), drawn from
the sample's own seed (``model.training.seeding``)."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

from logpipe.errors import LogpipeError
from logpipe.types import NDArrayFloat, SceneSample

from ..checkpoint.format import CheckpointError
from ..checkpoint.weights_folder import WeightsMeta, load_into, load_weights, read_weights_meta
from .config import MODEL_KIND, SocialGanConfig
from .fit import scene_forecasts
from .net import Generator


def load_generator(folder: Path) -> tuple[Generator, WeightsMeta]:
    """The generator (eval mode) of a Social-GAN checkpoint folder and its metadata (the discriminator's weights
    are checked with the rest but not built).

    Raises:
        CheckpointError: see ``model.checkpoint.weights_folder``; a config that does not parse.
    """
    meta = read_weights_meta(folder, (MODEL_KIND,))
    try:
        config = SocialGanConfig.from_dict(meta.config, str(folder / "meta.json"))
    except LogpipeError as exc:
        raise CheckpointError(str(exc)) from None
    state = load_weights(folder, meta.weights_sha256)
    generator = Generator(config)
    prefix = "generator."
    load_into(generator, {k[len(prefix):]: v for k, v in state.items() if k.startswith(prefix)}, folder)
    return generator.eval(), meta


class SocialGanPredictor:
    """A Social-GAN checkpoint as a ``Predictor``."""

    name = MODEL_KIND

    def __init__(self, generator: Generator, meta: WeightsMeta) -> None:
        self.generator, self.meta = generator.eval(), meta

    @classmethod
    def from_checkpoint(cls, folder: Path) -> SocialGanPredictor:
        """Load a checkpoint folder (``load_generator``'s checks)."""
        return cls(*load_generator(folder))

    def predict(self, samples: Sequence[SceneSample], num_modes: int, seed: int) -> list[NDArrayFloat]:
        """Per sample (N_targets, num_modes, T_pred, 2) world metres."""
        return scene_forecasts(self.generator, samples, num_modes, seed)
