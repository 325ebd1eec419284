"""Which predictor a run uses: the shipped checkpoints, the baselines, a checkpoint's fit to a dataset, and the
inference settings in effect (the checkpoint's own, chosen on validation, unless options override them).

``logpipe predict`` asks this module; reproduction scripts and benchmarks may too. Nothing here writes.
"""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import pyarrow as pa
import pyarrow.compute as pc

from logpipe.dataset.reader import Dataset
from logpipe.errors import LogpipeError
from logpipe.prediction.default_choice import checkpoint_reason, kinematic_reason
from logpipe.raster.rasteriser import DEFAULT_CHANNELS
from logpipe.storage.io import read_json, read_table

from .checkpoint.format import InferenceSettings, TrainingData, kind_accepts
from .checkpoint.weights_folder import read_weights_meta
from .residual.config import MODEL_KIND as RESIDUAL_KIND
from .residual.meta import model_kind, read_residual_meta
from .social import SOCIAL_KINDS
from .zhu2020.meta import read_meta

if TYPE_CHECKING:  # the network's modules load torch: imported where a checkpoint is used, so baselines never do
    import torch

    from .predictor import Predictor

BASELINES = {"cv": "constant_velocity", "linear": "linear", "kalman": "kalman_cv", "cv_sampler": "cv_sampler",
             "adaptive_cv": "adaptive_cv"}
"""``--predictor`` names -> ``model.kinematic.CLASSICAL`` keys."""
DEFAULT_BASELINE = "kalman"
"""The default of a dataset kind no shipped model serves (ROS bags, MCAP): Kalman CV has the lowest K=1 FDE of the
kinematic baselines in every table of docs/results (Argoverse 1: 6.90 m, CV 7.57, linear 7.95; ApolloScape: 2.91,
3.01, 3.52; ETH/UCY: 1.13, 1.14, 1.23)."""

# Shipped baselines and ablations live in folders named after their method (``ethucy/eth/lstm``,
# ``apolloscape/noise_lstm``, ``ethucy/eth/no_position``, the social baselines' ``ethucy/zara1/social_lstm``); they
# are there for the reproduction tables, never the default model.
COMPARISON_FOLDERS = frozenset({"lstm", "noise_lstm", "no_position", "paper", "social_lstm", "social_gan_20v",
                                "social_gan_20vp"})

# Dataset kinds whose shipped model lives under another folder: one driving model serves the Argoverse formats and
# CommonRoad (it is trained on all three; its ``meta.json`` kind is ``argoverse1+argoverse2+commonroad``).
KIND_FOLDERS = {"argoverse1": "argoverse", "argoverse2": "argoverse", "commonroad": "argoverse"}


@dataclass(frozen=True)
class Inference:
    """The network's inference settings for one run and where they came from.

    Attributes:
        noise_scale: standard deviation of the noise z (1 = as trained, eq. 21).
        constant_velocity_modes: modes held to constant velocity (None = the training config's).
        context_max_neighbours: neighbour cap of each target's context (None = all within the radius).
        source: ``checkpoint`` (chosen on validation, stored in ``meta.json``), ``as trained`` (none stored, or
            ``--as-trained``), or either followed by ``+ options`` when options replaced some of them.
        chosen_on: how the checkpoint's settings were chosen ("" when not from the checkpoint).
    """

    noise_scale: float = 1.0
    constant_velocity_modes: int | None = None
    context_max_neighbours: int | None = None
    source: str = "as trained"
    chosen_on: str = ""

    def summary(self) -> dict[str, object]:
        """The ``inference`` block of predict's summary."""
        return dataclasses.asdict(self)


@dataclass
class ChosenPredictor:
    """The predictor and what the outputs record about it.

    Attributes:
        model: the ``Predictor`` (None until ``load_net`` for a checkpoint).
        name: ``predictor`` column (``zhu2020``, ``cv``, ...).
        checkpoint_id: weights sha256 (plus inference settings that are not as trained), or the baseline with its
            parameters.
        checkpoint: the checkpoint folder, if any.
        needs_raster: the environment net is on (every sample needs a raster).
        raster_channels: C the net expects.
        weights_sha256: the checkpoint's weights digest (None for baselines).
        stored_settings: the inference settings the checkpoint stores (None: none, or a baseline).
        training_data: what the checkpoint was trained and validated on (None: not recorded, or a baseline).
        inference: the settings in effect (``resolve_inference``).
        why: why this predictor (the option that named it, or why it is the dataset's default).
    """

    model: Predictor | None
    name: str
    checkpoint_id: str
    checkpoint: Path | None = None
    needs_raster: bool = False
    raster_channels: int | None = None
    weights_sha256: str | None = None
    stored_settings: InferenceSettings | None = None
    training_data: TrainingData | None = None
    inference: Inference = Inference()
    why: str = ""


def shipped_checkpoints(kind: str) -> list[Path]:
    """Folders (with a ``meta.json``) of the paper's method shipped for a dataset kind, by path: under
    ``model/checkpoints/<kind>/`` or the kind's ``KIND_FOLDERS`` entry."""
    root = Path(__file__).parent / "checkpoints" / KIND_FOLDERS.get(kind, kind)
    found = sorted(p.parent for p in root.glob("**/meta.json")) if root.is_dir() else []
    return [p for p in found if p.name not in COMPARISON_FOLDERS]


VEHICLE_TYPES = frozenset({"vehicle", "bus_truck"})
"""Object types that make a ROS/MCAP dataset driving data (its tracks mostly of them)."""


def driving_recipe(datasets: Sequence[Dataset]) -> Path | None:
    """The shipped driving default (the residual model's checkpoint, whose config is the driving recipe) when every
    dataset is driving data: a format the driving model serves (``KIND_FOLDERS``), or ROS/MCAP logs whose track
    rows are mostly vehicles; None otherwise (``logpipe train`` then trains the paper's network)."""
    for ds in datasets:
        if ds.kind in KIND_FOLDERS:
            continue
        if ds.kind not in ("rosbag", "mcap"):
            return None
        types = ds.tracks(["object_type"]).column("object_type").to_pylist()
        if not types or sum(t in VEHICLE_TYPES for t in types) * 2 < len(types):
            return None
    found = [p for p in shipped_checkpoints(datasets[0].kind if datasets[0].kind in KIND_FOLDERS else "argoverse1")
             if model_kind(p) == RESIDUAL_KIND]
    return found[0] if found else None


def default_checkpoint(kind: str, split: str | None) -> Path:
    """The shipped checkpoint for a dataset kind: the only one, or with several (ETH/UCY ships one per left-out
    scene) the one named like the scene of ``split`` (``--filter split=eth/test`` -> ``eth``): using a model
    trained on the scene being predicted would leak its test data, so there is no silent pick.

    Raises:
        LogpipeError: none shipped, or several and the split names none of them.
    """
    found = shipped_checkpoints(kind)
    if not found:
        folder = KIND_FOLDERS.get(kind, kind)
        raise LogpipeError(f"no shipped checkpoint for dataset kind {kind!r} (looked in model/checkpoints/{folder}/); "
                           f"give --checkpoint PATH or a baseline --predictor {'|'.join(BASELINES)}")
    if len(found) == 1:
        return found[0]
    scene = split.split("/")[0] if split else None
    named = [p for p in found if p.name == scene]
    if len(named) == 1:
        return named[0]
    raise LogpipeError(f"several shipped checkpoints for {kind!r} ({', '.join(p.name for p in found)}): pick one "
                       "with --checkpoint, or --filter split=<scene>/test to use that scene's")


def choose_predictor(
    dataset: Dataset, checkpoint: Path | None, predictor: str | None, *, split: str | None = None
) -> ChosenPredictor:
    """Resolve ``--checkpoint`` / ``--predictor``; the default is the shipped checkpoint for the dataset kind, or
    ``DEFAULT_BASELINE`` for a kind none serves. ``why`` says which applied.

    Only reads the checkpoint's metadata; ``check_fit`` compares it with the dataset before weights load.
    """
    pred_len = dataset.protocol.pred_len
    if checkpoint is not None and predictor is not None:
        raise LogpipeError("give either --checkpoint or --predictor, not both")
    if predictor is not None:
        if predictor not in BASELINES:
            raise LogpipeError(f"unknown --predictor {predictor!r}; baselines: {', '.join(BASELINES)}")
        from .kinematic import CLASSICAL

        model = CLASSICAL[BASELINES[predictor]](pred_len=pred_len)
        params = {k: v for k, v in dataclasses.asdict(model).items() if k != "name"}
        return ChosenPredictor(model, predictor, f"{predictor}:{json.dumps(params, sort_keys=True)}",
                               why=f"--predictor {predictor}")
    why = f"--checkpoint {checkpoint}"
    if checkpoint is None and not shipped_checkpoints(dataset.kind):
        chosen = choose_predictor(dataset, None, DEFAULT_BASELINE)
        chosen.why = kinematic_reason(dataset)
        return chosen
    if checkpoint is None:
        checkpoint = default_checkpoint(dataset.kind, split)
        why = checkpoint_reason(dataset, checkpoint, driving=dataset.kind in KIND_FOLDERS)
    folder = checkpoint.parent if checkpoint.name == "meta.json" else checkpoint
    kind = model_kind(folder)
    if kind in SOCIAL_KINDS:  # Social-LSTM / Social-GAN: tracks only, no inference settings
        social = read_weights_meta(folder, SOCIAL_KINDS)
        return ChosenPredictor(None, social.model_kind, social.weights_sha256, folder, False, None,
                               social.weights_sha256, None, social.training_data)
    if kind == RESIDUAL_KIND:
        residual = read_residual_meta(folder)
        return ChosenPredictor(None, "residual", residual.weights_sha256, folder, residual.config.environment,
                               len(DEFAULT_CHANNELS), residual.weights_sha256, None, residual.training_data, why=why)
    meta = read_meta(folder)
    model_cfg = meta.config.model
    return ChosenPredictor(None, "zhu2020", meta.weights_sha256, folder, model_cfg.features.environment,
                           model_cfg.raster_channels, meta.weights_sha256, meta.inference, meta.training_data, why=why)


def resolve_inference(chosen: ChosenPredictor, *, num_modes: int, noise_scale: float | None = None,
                      constant_velocity_modes: int | None = None, context_max_neighbours: int | None = None,
                      as_trained: bool = False) -> Inference:
    """The settings a run uses: the checkpoint's stored ones (unless ``as_trained``), each replaced by the option
    given for it; sets ``chosen.inference`` and records them in ``chosen.checkpoint_id``.

    Raises:
        LogpipeError: an option for a baseline, or a value out of range.
    """
    options = [v is not None for v in (noise_scale, constant_velocity_modes, context_max_neighbours)]
    if chosen.name in ("residual", *SOCIAL_KINDS) and (any(options) or as_trained):
        raise LogpipeError("--noise-scale, --constant-velocity-modes, --context-max-neighbours and --as-trained "
                           f"apply to the paper's network, not to a {chosen.name} checkpoint")
    if chosen.checkpoint is None or chosen.name in ("residual", *SOCIAL_KINDS):
        if any(options) or as_trained:
            raise LogpipeError("--noise-scale, --constant-velocity-modes, --context-max-neighbours and --as-trained "
                               "apply to a checkpoint's network, not to a --predictor baseline")
        return chosen.inference
    if noise_scale is not None and not noise_scale > 0:
        raise LogpipeError(f"--noise-scale must be > 0, got {noise_scale}")
    if context_max_neighbours is not None and context_max_neighbours < 0:
        raise LogpipeError(f"--context-max-neighbours must be >= 0, got {context_max_neighbours}")
    stored = None if as_trained else chosen.stored_settings
    base = Inference() if stored is None else Inference(
        stored.noise_scale, stored.constant_velocity_modes, stored.context_max_neighbours, "checkpoint",
        stored.chosen_on)
    inference = base if not any(options) else Inference(
        base.noise_scale if noise_scale is None else noise_scale,
        base.constant_velocity_modes if constant_velocity_modes is None else constant_velocity_modes,
        base.context_max_neighbours if context_max_neighbours is None else context_max_neighbours,
        base.source + " + options", base.chosen_on)
    cv = inference.constant_velocity_modes
    if cv is not None and not 0 <= cv <= num_modes:
        origin = "--constant-velocity-modes" if constant_velocity_modes is not None else "the checkpoint"
        raise LogpipeError(f"constant-velocity modes must be in 0..{num_modes} (--modes), got {cv} from {origin}")
    from .predictor import inference_id

    chosen.inference = inference
    chosen.checkpoint_id = inference_id(chosen.weights_sha256 or chosen.checkpoint_id, inference.noise_scale,
                                        inference.constant_velocity_modes, inference.context_max_neighbours)
    return inference


def check_fit(dataset: Dataset, chosen: ChosenPredictor, logs: pa.Table) -> list[str]:
    """Every way the checkpoint does not fit the dataset (empty for baselines): kind (one of a several-format
    checkpoint's formats fits), obs/pred lengths and the optional ``frame_rate_hz`` / ``object_types`` entries of
    ``meta.json``."""
    if chosen.checkpoint is None:
        return []
    raw = read_json(chosen.checkpoint / "meta.json")
    protocol = dataset.protocol
    if chosen.name == "residual":
        residual = read_residual_meta(chosen.checkpoint)
        kind, lengths = residual.dataset_kind, (residual.config.obs_len, residual.config.pred_len)
    elif chosen.name in SOCIAL_KINDS:
        social = read_weights_meta(chosen.checkpoint, SOCIAL_KINDS)
        kind, lengths = social.dataset_kind, (social.obs_len, social.pred_len)
    else:
        meta = read_meta(chosen.checkpoint)
        kind, lengths = meta.dataset_kind, (meta.config.model.obs_len, meta.config.model.pred_len)
    problems = []
    if not kind_accepts(kind, dataset.kind):
        problems.append(f"dataset kind: checkpoint {kind!r}, dataset {dataset.kind!r}")
    if lengths != (protocol.obs_len, protocol.pred_len):
        problems.append(f"obs/pred lengths: checkpoint {lengths[0]}+{lengths[1]} steps, dataset "
                        f"{protocol.obs_len}+{protocol.pred_len} ({protocol.name})")
    rate = raw.get("frame_rate_hz")
    if rate is not None:
        rates = sorted({float(r) for r in logs.column("frame_rate_hz").to_pylist()})
        if any(abs(r - float(rate)) > 1e-6 for r in rates):
            problems.append(f"frame rate: checkpoint {rate} Hz, dataset {rates} Hz")
    types = raw.get("object_types")
    if types is not None:
        seen = set()
        for path in dataset.shard_paths:
            seen |= set(pc.unique(read_table(path, columns=["object_type"]).column(0)).to_pylist())
        unknown = sorted(seen - set(types))
        if unknown:
            problems.append(f"agent types: dataset has {unknown}, checkpoint was trained on {sorted(types)}")
    return problems


def seen_in_training(chosen: ChosenPredictor, logs: pa.Table) -> list[str]:
    """Warnings for selected logs whose recording the checkpoint was trained or validated on (matched by the
    recording's sha256, so copies and re-ingested files count): their forecasts are not a held-out test."""
    data = chosen.training_data
    if data is None or not len(logs):
        return []
    ids, sources = logs.column("log_id").to_pylist(), logs.column("source_sha256").to_pylist()
    warnings = []
    for role, split, known in (("trained", data.train_split, set(data.train_sources)),
                               ("validated", data.val_split, set(data.val_sources))):
        hits = [str(log) for log, sha in zip(ids, sources, strict=True) if sha in known]
        if hits:
            shown = ", ".join(hits[:5]) + (f" and {len(hits) - 5} more" if len(hits) > 5 else "")
            warnings.append(f"{len(hits)} of the {len(ids)} selected logs come from recordings this checkpoint was "
                            f"{role} on (split {split}): {shown}; their scores are not a held-out test")
    return warnings


def load_net(chosen: ChosenPredictor, dataset: Dataset, batch_size: int, device: torch.device | str = "cpu") -> None:
    """Load the checkpoint's weights into ``chosen.model`` with ``chosen.inference``, on ``device`` (after
    ``check_fit``)."""
    if chosen.model is not None or chosen.checkpoint is None:
        return
    if chosen.name == "residual":
        from .residual.predictor import ResidualPredictor

        chosen.model = ResidualPredictor.from_checkpoint(chosen.checkpoint)
        return
    if chosen.name in SOCIAL_KINDS:
        from .social import load_social

        chosen.model = load_social(chosen.checkpoint, chosen.name)
        return
    from .zhu2020.predictor import NetPredictor

    settings = chosen.inference
    chosen.model = NetPredictor.from_checkpoint(chosen.checkpoint, expect_kind=dataset.kind, batch_size=batch_size,
                                                noise_scale=settings.noise_scale,
                                                constant_velocity_modes=settings.constant_velocity_modes,
                                                context_max_neighbours=settings.context_max_neighbours,
                                                device=device)
