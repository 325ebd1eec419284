"""Every hyper-parameter of the predictor and its training, in two frozen dataclasses.

Defaults are the paper's (Zhu et al., IJCAI 2020, "Implementation Details"): embeddings 64 wide, GRU with
128 cells (eq. 6), LSTM encoder/decoder with 64 cells (eqs. 16, 18), ROIAlign pool K=3 over R_s=20 m
(eqs. 11-12), Adam with lr 5e-4, batch 8, 20,000 steps, H=20 modes (eq. 23).

A config file is JSON (``.json``) or TOML (``.toml``) with two tables, ``model`` (with a nested
``features`` table) and ``train``; unknown keys are an error so a typo never silently falls back to a
default.
"""

from __future__ import annotations

import dataclasses
import json
import math
import tomllib
from dataclasses import dataclass, field, fields, replace
from pathlib import Path
from typing import Any, Literal, TypeVar, get_args

from logpipe.errors import LogpipeError

Frame = Literal["world", "ego"]
LossReduction = Literal["scene", "agent"]
StepOutput = Literal["displacement", "velocity_change", "agent_velocity_change"]
ContextOrigin = Literal["window", "target"]


class ConfigError(LogpipeError):
    """A model/training config is malformed or inconsistent."""


@dataclass(frozen=True)
class Features:
    """Switches for the five components of the ablation (paper Table 4).

    Attributes:
        position: PF, global position feature o^(t) (eqs. 1-2).
        tracking: TF, global tracking feature r^(t) from the LSTM hidden states (eqs. 3-4).
        ego_motion: EMF, ego displacement embedding m^(t) (eq. 5); needs an ego in the sample.
        ego_trajectory: ETF, future ego-trajectory feature f^(t) (eqs. 8-9); needs the ego's future
            (its planned/actual trajectory) in the sample.
        environment: EF, raster feature v_i^(t) from ResNet18 stages 1-2 + ROIAlign (eqs. 11-12); needs a
            raster in the sample.
    """

    position: bool = True
    tracking: bool = True
    ego_motion: bool = True
    ego_trajectory: bool = True
    environment: bool = True

    @property
    def uses_gru(self) -> bool:
        """Whether the AIN's GRU (eqs. 6-7) has any input, i.e. st^(t) exists."""
        return self.position or self.tracking or self.ego_motion

    @property
    def uses_ego_plan(self) -> bool:
        """Whether the ego's future positions are a model input (EMF during decoding, or ETF)."""
        return self.ego_motion or self.ego_trajectory


SPEED_SCALE_MIN = 0.25
"""Smallest per-scene scale of ``ModelConfig.speed_unit_m`` (scenes moving 4x the unit or faster)."""
SPEED_SCALE_MAX = 4.0
"""Largest per-scene scale (scenes of people standing still or moving under a quarter of the unit)."""


MODEL_SIZE_LIMITS = {"obs_len": 1000, "pred_len": 1000, "embed_dim": 4096, "gru_dim": 4096, "lstm_dim": 4096,
                     "noise_dim": 4096, "raster_channels": 64, "roi_pool": 64, "roi_sampling": 64}
"""Largest accepted sizes: 64x the paper's widths (a 4096-cell LSTM is ~0.5 GB), far above any config here."""


@dataclass(frozen=True)
class ModelConfig:
    """Architecture, input frame and normalisation of the trajectory network.

    Attributes:
        features: component switches (Table 4).
        obs_len: T_obs, observed steps including the current one.
        pred_len: T_pred - T_obs, predicted steps.
        embed_dim: width of every embedding layer (d_o, d_r, d_m, d_f, d_p, d_v and st), 64 in the paper.
        gru_dim: GRU cells of the AIN (eq. 6), 128 in the paper.
        lstm_dim: cells of LSTM_E and LSTM_D (eqs. 16, 18), 64 in the paper.
        noise_dim: size of the Gaussian noise z of eq. 21 (not given in the paper; 0 disables noise).
        raster_channels: C of the input raster (semantic layers), taken from the rasteriser's output.
        roi_pool: K, ROIAlign output size per side (eq. 11).
        roi_half_size_m: R_s in metres; the ROI is the square of side 2 R_s centred on the agent, which is
            the paper's window of H R_s / (4h) feature cells at stride 8.
        roi_sampling: bilinear samples per ROI bin per side (ROIAlign's sampling ratio).
        backbone_weights: optional path of a torchvision-layout ResNet18 state dict (safetensors or a
            ``torch.save`` file read with ``weights_only=True``) for the "pre-trained" backbone.
        freeze_backbone: keep the backbone's weights fixed (and in eval mode) during training.
        backbone_bf16: run the backbone in bf16 autocast with channels_last where the CPU has native bf16
            (AMX / AVX512-BF16): ~4x the fp32 images/s there, for a 0.6% relative L2 error of the feature map
            and 0.3% of the pooled feature v (``benchmarks/bench_model.py``). Other CPUs run fp32 whatever
            this says (emulated bf16 was 4-5x slower than fp32 on an AVX2 EPYC).
        frame: ``world`` (world axes, origin at the targets' mean current position) or ``ego`` (origin at
            the ego's current position, +x along the ego's last observed heading); Table 3 reports both.
        pos_scale_m: positions are divided by this (metres) before the position/attention/ETF layers.
        disp_scale_m: displacements are divided by this (metres per step) before eqs. 5, 15, 17 and the
            output of eq. 19 is multiplied by it.
        step_output: what eq. 19's output o_t means. ``displacement`` (the paper): p_t = p_(t-1) + o_t.
            ``velocity_change``: p_t = p_(t-1) + (p_(t-1) - p_(t-2)) + o_t, i.e. the decoder corrects a
            constant-velocity step (the last observed displacement carried on; zero where p_(t-2) of the
            first predicted step was not observed). Same network and loss; only the output's reference moves.
            ``agent_velocity_change``: as ``velocity_change``, with o_t read in each agent's own frame and
            speed: o_t = (along, across) is multiplied by the last observed step's length (at least
            ``agent_min_step_m``) along and across its direction, so o_t is a relative speed change and a
            turn rate, the two quantities the constant-velocity sampler perturbs, and the same output means
            the same manoeuvre for a slow and a fast walker heading anywhere (``disp_scale_m`` then scales
            only the inputs).
        agent_min_step_m: floor (metres per step) of the speed that scales ``agent_velocity_change``'s output,
            so that agents standing still (whose last step is position noise) can still start to move.
        mode_gate: scale each mode's step outputs o_t (eq. 19) by g = sigmoid(w . h_d^(T_obs) + b), one gate per
            agent and mode read from the decoder's initial state (eqs. 21-22, so from the noise z too). With a
            velocity-change output a mode whose gate closes is exactly the constant-velocity forecast, which for
            a pedestrian standing still is standing still: a linear output reaches zero only by balancing its
            weights, a saturated sigmoid reaches it for a whole region of z. Not in the paper (False there).
        constant_velocity_modes: the first this many of the K modes drawn get no step outputs, in training
            (so the best-of-H loss leaves the agents that constant velocity fits to them and the other modes
            learn the rest) and by default at inference. With a velocity-change output such a mode is exactly
            the constant-velocity forecast. At most K - 1 are held, so a single draw is the network's own.
            Needs a velocity-change ``step_output``. 0 in the paper.
        speed_unit_m: None (the paper: model frame in metres) or a length in metres. When set, each scene's
            model frame is also scaled by ``clip(speed_unit_m / u, SPEED_SCALE_MIN, SPEED_SCALE_MAX)``, u
            being the mean length of the scene's observed one-step displacements: a scene whose people
            walk twice as fast is seen at half the size, so what the network learns about motion carries
            over between scenes of different speeds (and frame rates), as the constant-velocity sampler's
            relative speed noise does. Outputs and reported errors are mapped back to metres.
        context_radius_m: None (the paper: the interaction features pool every agent of the scene) or a radius
            in metres. When set, each target is predicted in a scene of its own, seen in its window's model
            frame: itself, the agents observed at the current step within this distance of it (decoded as
            context, not scored) and the ego, in training as at inference. The pools of eqs. 2 and 4 (and the
            AIN's GRU) then see a neighbourhood whose size does not grow with the crowd (ETH/UCY's UNIV fold
            trains on windows of at most 14 pedestrians and is tested on windows of 20-57); nothing else
            changes, and without PF and TF (Noise-LSTM, LSTM) it changes nothing. Not in the paper, whose AIN
            is global.
        context_origin: with ``context_radius_m``, where each target's scene has its origin: ``window`` (its
            window's model-frame origin) or ``target`` (the target's current position; axes, rotation and speed
            scale stay the window's). With ``target`` the max-pool of eq. 2 over linear embeddings of positions
            reads the neighbours' extent relative to the target itself, as the paper's ego-centred frame does
            for the ego.
        context_max_neighbours: with ``context_radius_m``, at most this many of the agents within the radius
            (the nearest at the current step; the ego is kept besides) join each target's scene. None: all of
            them. Its use is at inference: a model trained where few targets had more neighbours than this
            sees crowds of the size its training covered (the pools of eqs. 2 and 4 take maxima, which grow
            with the number pooled).
        interaction_while_decoding: True (the paper): PF, TF, EMF and the AIN's GRU run on at every predicted
            step, pooling the agents' predicted positions and decoder states in the same mode. False: the
            decoder reads fst^(T_obs), the AIN as observed (eq. 13's attention still reads each predicted
            position). With the best mode taken per agent (``TrainConfig.loss_min_over = "agent"``) mode m of
            one agent and mode m of its neighbour are not one joint future, so what the predicted-step pools
            see is the neighbours' unrelated samples.
    """

    features: Features = field(default_factory=Features)
    obs_len: int = 8
    pred_len: int = 12
    embed_dim: int = 64
    gru_dim: int = 128
    lstm_dim: int = 64
    noise_dim: int = 16
    raster_channels: int = 4
    roi_pool: int = 3
    roi_half_size_m: float = 20.0
    roi_sampling: int = 2
    backbone_weights: str | None = None
    freeze_backbone: bool = False
    backbone_bf16: bool = True
    frame: Frame = "world"
    pos_scale_m: float = 10.0
    disp_scale_m: float = 1.0
    step_output: StepOutput = "displacement"
    speed_unit_m: float | None = None
    agent_min_step_m: float = 0.1
    mode_gate: bool = False
    constant_velocity_modes: int = 0
    context_radius_m: float | None = None
    context_origin: ContextOrigin = "window"
    context_max_neighbours: int | None = None
    interaction_while_decoding: bool = True

    @property
    def pools_context(self) -> bool:
        """Whether each target is predicted in its own neighbourhood: a context radius and at least one of the
        pools that read other agents (PF, TF: eqs. 2 and 4)."""
        return self.context_radius_m is not None and (self.features.position or self.features.tracking)

    def effective(self) -> ModelConfig:
        """This config with the settings its network cannot feel at their defaults, so two configs that train the
        same computation compare equal: the context options without the pools that read other agents
        (``pools_context``; Noise-LSTM and LSTM collate windows as they are), and ``interaction_while_decoding``
        without an AIN output (no fst^(t) to hold)."""
        out = self
        if not self.pools_context:
            out = replace(out, context_radius_m=None, context_origin="window", context_max_neighbours=None)
        if not (self.features.uses_gru or self.features.ego_trajectory):
            out = replace(out, interaction_while_decoding=True)
        return out

    def __post_init__(self) -> None:  # noqa: PLR0912  one flat check per field, in field order
        if self.obs_len < 2 or self.pred_len < 1:
            raise ConfigError(f"obs_len must be >= 2 and pred_len >= 1, got {self.obs_len}, {self.pred_len}")
        for name in ("embed_dim", "gru_dim", "lstm_dim", "raster_channels", "roi_pool", "roi_sampling"):
            if getattr(self, name) < 1:
                raise ConfigError(f"model.{name} must be >= 1, got {getattr(self, name)}")
        # Bounded before any allocation: a damaged or hostile meta.json asking for lstm_dim 200000 would try to
        # allocate hundreds of GB (a traceback, or the machine swapping) instead of one line.
        for name, most in MODEL_SIZE_LIMITS.items():
            if not 0 <= getattr(self, name) <= most:
                raise ConfigError(f"model.{name} must be at most {most}, got {getattr(self, name)}")
        if self.noise_dim < 0:
            raise ConfigError(f"model.noise_dim must be >= 0, got {self.noise_dim}")
        if self.step_output not in get_args(StepOutput):
            raise ConfigError(
                f"model.step_output must be one of {list(get_args(StepOutput))}, got {self.step_output!r}")
        if self.frame not in ("world", "ego"):
            raise ConfigError(f"model.frame must be 'world' or 'ego', got {self.frame!r}")
        if self.speed_unit_m is not None and not (math.isfinite(self.speed_unit_m) and self.speed_unit_m > 0):
            raise ConfigError(f"model.speed_unit_m must be a positive number or absent, got {self.speed_unit_m}")
        if self.context_radius_m is not None and not (
                math.isfinite(self.context_radius_m) and self.context_radius_m > 0):
            raise ConfigError(
                f"model.context_radius_m must be a positive number or absent, got {self.context_radius_m}")
        if self.context_max_neighbours is not None and self.context_max_neighbours < 0:
            raise ConfigError(
                f"model.context_max_neighbours must be >= 0 or absent, got {self.context_max_neighbours}")
        if self.context_origin not in get_args(ContextOrigin):
            raise ConfigError(
                f"model.context_origin must be one of {list(get_args(ContextOrigin))}, got {self.context_origin!r}"
            )
        for name in ("pos_scale_m", "disp_scale_m", "roi_half_size_m", "agent_min_step_m"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ConfigError(f"model.{name} must be a positive number, got {value}")
        if self.constant_velocity_modes < 0:
            raise ConfigError(f"model.constant_velocity_modes must be >= 0, got {self.constant_velocity_modes}")
        if self.constant_velocity_modes and self.step_output == "displacement":
            raise ConfigError("model.constant_velocity_modes needs a velocity-change step_output; with "
                              "'displacement' a zero output means standing still, not constant velocity")

    def held_modes(self, num_modes: int) -> int:
        """How many of ``num_modes`` draws ``constant_velocity_modes`` holds: at most ``num_modes - 1``, so a
        single draw is the network's own."""
        return min(self.constant_velocity_modes, num_modes - 1)

    def resolved(self, *, has_ego: bool, has_map: bool) -> ModelConfig:
        """This config with the features the data cannot feed switched off (paper: no EMF/ETF/EF on
        ETH/UCY and ApolloScape, which have no ego and no HD map)."""
        feats = self.features
        if not has_ego:
            feats = replace(feats, ego_motion=False, ego_trajectory=False)
        if not has_map:
            feats = replace(feats, environment=False)
        return replace(self, features=feats)


@dataclass(frozen=True)
class TrainConfig:
    """Optimisation, evaluation and bookkeeping of one training run.

    Attributes:
        model: the architecture being trained.
        seed: seeds torch and numpy; the run is deterministic for a fixed seed and thread count.
        steps: optimiser steps (paper: 20,000).
        batch_size: scenes per step (paper: 8).
        lr: Adam learning rate (paper: 5e-4).
        lr_decay: multiplicative learning-rate decay applied every ``lr_decay_every`` steps (1.0 = none).
        lr_decay_every: steps between decays.
        weight_decay: Adam L2 penalty.
        grad_clip: max global gradient norm (0 disables).
        ema_decay: validate and keep as ``best/`` an exponential moving average of the weights, updated after
            every optimiser step with this decay (0 disables: the raw weights). ``last/`` keeps the raw weights
            and the average, so a resumed run continues both.
        num_modes: H, decoder samples per scene in the best-of-H loss (eq. 23; paper: 20 on ETH/UCY).
        loss_min_over: ``scene`` takes eq. 23's min over modes of the error summed over a scene's targets
            (the paper); ``agent`` takes the min per target.
        select_then_backprop: decode the H modes without autograd, then re-decode only the picked modes
            with autograd (same gradient as eq. 23; ~2-3x cheaper with the per-scene min, less with the
            per-agent one, which re-decodes as many modes as a scene has distinct picks).
        augment_rotate: rotate each training scene by a uniform random angle about its origin.
        eval_every: steps between validation passes (and checkpoints).
        val_modes: K for the validation best-of-K ADE/FDE.
        val_max_samples: validate on the first this many validation samples (None = all).
        early_stop_patience: stop after this many validations without a better val ADE (0 = never).
        early_stop_min_steps: never stop early before this step (validation at a high learning rate is noisy
            enough that a lucky early evaluation can end a run that had hardly trained).
        log_every: steps between training-log lines.
        num_threads: ``torch.set_num_threads`` value (0 leaves torch's default).
        shuffle_buffer: buffer size for shuffling a training stream that is not a Sequence.
        cache_backbone_features: keep each training sample's backbone feature map in memory after its first
            step, so later epochs skip the backbone (``feature_cache``: exact, float32); needs
            ``model.freeze_backbone``.
        cache_backbone_max_mb: bound (MB, 10^6 bytes) on that cache: 0.4 MB per 224 x 224 raster, 6.4 GB for 16k
            samples; a step drawing a sample beyond it runs the backbone on its whole batch.
    """

    model: ModelConfig = field(default_factory=ModelConfig)
    seed: int = 0
    steps: int = 20_000
    batch_size: int = 8
    lr: float = 5e-4
    lr_decay: float = 1.0
    lr_decay_every: int = 1000
    weight_decay: float = 0.0
    grad_clip: float = 1.5
    ema_decay: float = 0.0
    num_modes: int = 20
    loss_min_over: LossReduction = "scene"
    select_then_backprop: bool = True
    augment_rotate: bool = False
    eval_every: int = 500
    val_modes: int = 20
    val_max_samples: int | None = None
    early_stop_patience: int = 10
    early_stop_min_steps: int = 0
    log_every: int = 50
    num_threads: int = 2
    shuffle_buffer: int = 1024
    cache_backbone_features: bool = False
    cache_backbone_max_mb: int = 8000

    def __post_init__(self) -> None:
        for name in ("steps", "batch_size", "num_modes", "eval_every", "val_modes", "log_every", "lr_decay_every"):
            if getattr(self, name) < 1:
                raise ConfigError(f"train.{name} must be >= 1, got {getattr(self, name)}")
        if not (self.lr > 0 and 0 < self.lr_decay <= 1):
            raise ConfigError(f"train.lr must be > 0 and lr_decay in (0, 1], got {self.lr}, {self.lr_decay}")
        if self.loss_min_over not in ("scene", "agent"):
            raise ConfigError(f"train.loss_min_over must be 'scene' or 'agent', got {self.loss_min_over!r}")
        if self.early_stop_patience < 0 or self.early_stop_min_steps < 0:
            raise ConfigError(
                "train.early_stop_patience and train.early_stop_min_steps must be >= 0, "
                f"got {self.early_stop_patience}, {self.early_stop_min_steps}"
            )
        if not 0 <= self.ema_decay < 1:
            raise ConfigError(f"train.ema_decay must be in [0, 1), got {self.ema_decay}")
        if self.val_max_samples is not None and self.val_max_samples < 1:
            raise ConfigError(f"train.val_max_samples must be >= 1 or unset, got {self.val_max_samples}")
        if self.cache_backbone_features and not self.model.freeze_backbone:
            raise ConfigError("train.cache_backbone_features needs model.freeze_backbone = true: a trained "
                              "backbone's feature maps change every step")
        if self.cache_backbone_max_mb < 1:
            raise ConfigError(f"train.cache_backbone_max_mb must be >= 1, got {self.cache_backbone_max_mb}")


# ---------------------------------------------------------------------------------------------------------
# Presets: the rows of the paper's tables, one config away.

ALL_OFF = Features(False, False, False, False, False)

PRESETS: dict[str, Features] = {
    # Table 4 rows.
    "baseline": ALL_OFF,  # Noise-LSTM (with noise_dim > 0 and H > 1)
    "v1": Features(True, False, False, False, False),
    "v2": Features(True, True, False, False, False),
    "v3": Features(True, True, True, False, False),
    "v4": Features(True, True, True, True, False),
    "full": Features(),
    # Not in the paper: the full model without PF (eqs. 1-2), the ablation ETH/UCY's UNIV fold asks for.
    "no_position": Features(False, True, True, True, True),
}


def preset(name: str, **model_overrides: Any) -> ModelConfig:
    """ModelConfig for a named row: ``full``, ``v1``..``v4``, ``baseline`` (Noise-LSTM) or ``lstm``
    (vanilla LSTM encoder-decoder: no features, no noise)."""
    if name == "lstm":
        return ModelConfig(features=ALL_OFF, noise_dim=0, **model_overrides)
    if name not in PRESETS:
        raise ConfigError(f"unknown preset {name!r}; known: {[*PRESETS, 'lstm']}")
    return ModelConfig(features=PRESETS[name], **model_overrides)


# ---------------------------------------------------------------------------------------------------------
# (De)serialisation.

_T = TypeVar("_T")


def _from_dict(cls: type[_T], data: dict[str, Any], where: str) -> _T:
    if not isinstance(data, dict):
        raise ConfigError(f"{where}: expected a table, got {type(data).__name__}")
    known = {f.name: f for f in fields(cls)}  # type: ignore[arg-type]
    unknown = sorted(set(data) - set(known))
    if unknown:
        raise ConfigError(f"{where}: unknown keys {unknown}; known: {sorted(known)}")
    kwargs: dict[str, Any] = {}
    for key, value in data.items():
        if key == "features":
            kwargs[key] = _from_dict(Features, value, f"{where}.features")
        elif key == "model":
            kwargs[key] = _from_dict(ModelConfig, value, f"{where}.model")
        else:
            kwargs[key] = value
    try:
        return cls(**kwargs)
    except TypeError as exc:
        raise ConfigError(f"{where}: {exc}") from exc


def config_to_dict(config: TrainConfig | ModelConfig) -> dict[str, Any]:
    """Plain nested dict (JSON-able) of a config."""
    return dataclasses.asdict(config)


def train_config_from_dict(data: dict[str, Any]) -> TrainConfig:
    """Inverse of ``config_to_dict`` for a TrainConfig; unknown keys raise ``ConfigError``."""
    return _from_dict(TrainConfig, data, "train")


def model_config_from_dict(data: dict[str, Any]) -> ModelConfig:
    """Inverse of ``config_to_dict`` for a ModelConfig; unknown keys raise ``ConfigError``."""
    return _from_dict(ModelConfig, data, "model")


def _toml_value(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int | float):
        return repr(value)
    if isinstance(value, str):
        return json.dumps(value)  # a JSON string literal is a valid TOML basic string
    raise ConfigError(f"cannot write {value!r} to TOML")


def _toml_lines(table: dict[str, Any], prefix: str) -> list[str]:
    lines = [f"[{prefix}]"]
    nested = []
    for key, value in table.items():
        if isinstance(value, dict):
            nested.append((key, value))
        elif value is not None:  # TOML has no null: an absent key loads as the default (None)
            lines.append(f"{key} = {_toml_value(value)}")
    for key, value in nested:
        lines += ["", *_toml_lines(value, f"{prefix}.{key}")]
    return lines


def save_config(config: TrainConfig, path: Path) -> None:
    """Write ``config`` as JSON or TOML according to the suffix of ``path``."""
    data = config_to_dict(config)
    model = data.pop("model")
    if path.suffix == ".toml":
        text = "\n".join([*_toml_lines(model, "model"), "", *_toml_lines(data, "train")]) + "\n"
    elif path.suffix == ".json":
        text = json.dumps({"model": model, "train": data}, indent=2) + "\n"
    else:
        raise ConfigError(f"{path}: config files are .json or .toml")
    path.write_text(text, encoding="utf-8")


def load_config(path: Path) -> TrainConfig:
    """Read a JSON or TOML config file (tables ``model`` and ``train``, both optional)."""
    try:
        raw = path.read_bytes()
        data: Any = tomllib.loads(raw.decode()) if path.suffix == ".toml" else json.loads(raw)
    except (OSError, ValueError) as exc:
        raise ConfigError(f"{path}: cannot read config: {exc}") from exc
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: expected a table at the top level")
    unknown = sorted(set(data) - {"model", "train"})
    if unknown:
        raise ConfigError(f"{path}: unknown top-level keys {unknown}; expected 'model' and 'train'")
    train = dict(data.get("train", {}))
    train["model"] = data.get("model", {})
    return train_config_from_dict(train)
