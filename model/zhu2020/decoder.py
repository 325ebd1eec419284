"""The decoder of the Trajectory Prediction Network of Zhu et al. (IJCAI 2020): the noise z concatenated to
LSTM_E's last state (eq. 21) initialises LSTM_D (eq. 22), which then runs on its own predicted displacements
(eqs. 17-18) while the AIN (eqs. 1-10) and the EN (eqs. 11-12) are re-read at each predicted position; each step
output o_t (eq. 19) moves the agent (eq. 20). This is the reference form, with autograd, that training uses;
``fast_decoder.decode_fast`` is the same equations restructured for inference.

Decoder indexing (a reading of the paper made explicit): h_d^(T_obs) comes from eq. 22 and gives the first
displacement through eq. 19; LSTM_D then runs for t = T_obs+1 .. T_pred-1 on the predicted positions
(eqs. 17-20). The paper leaves the decoder's cell state open; it starts from the encoder's cell state. The
tracking feature pools h_d^(t-1) (see ``encoder``). With the ego plan in use (EMF or ETF on), the ego row is
not predicted but follows its given future (the paper's "planned trajectory ... given for reference").

Step outputs (``ModelConfig.step_output``): ``displacement`` is eq. 19-20 as written; the velocity-change forms
add o_t to a constant-velocity step (``carried_first_step``), ``agent_velocity_change`` in the agent's own
frame and speed (``agent_output_basis``); ``mode_open`` gates each mode's o_t. Positions are model-frame metres.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import torch
from torch import Tensor

from ..training.row_blocks import sigmoid
from .batching import Batch
from .config import ConfigError, ModelConfig
from .encoder import Encoded, attention_q, lstm_step, lstm_weights, map_features
from .layers import TrajectoryLayers


@dataclass
class Prediction:
    """Decoder output.

    Attributes:
        positions: (M, R, T_pred - T_obs, 2) model-frame metres p̂^(T_obs+1 .. T_pred).
        rows: (R,) batch rows that were decoded (the agents observed at the current step).
    """

    positions: Tensor
    rows: Tensor


class Decoder(Protocol):
    """The one decoder interface (eqs. 17-22): ``decode`` (training, with autograd) and
    ``fast_decoder.decode_fast`` (inference) both take the layers, the encoded batch and the (M, R, noise_dim) z of
    the rows observed at the current step, and return the same ``Prediction`` (equal up to float rounding)."""

    def __call__(self, net: TrajectoryLayers, batch: Batch, enc: Encoded, noise: Tensor,
                 constant_velocity_modes: int | None = None, /) -> Prediction:
        """Decode M modes of ``batch``'s current rows."""
        ...


def carried_first_step(config: ModelConfig, batch: Batch, rows: Tensor) -> Tensor | None:
    """(R, 2) last observed displacement p_(T_obs) - p_(T_obs - 1) that the velocity-change step outputs
    carry into the first predicted step (zero where p_(T_obs - 1) is unobserved); None otherwise."""
    if config.step_output == "displacement":
        return None
    t_obs = batch.obs_len
    step = batch.positions[rows, t_obs - 1] - batch.positions[rows, t_obs - 2]
    return torch.where(batch.valid[rows, t_obs - 2][:, None], step, torch.zeros_like(step))


def agent_output_basis(config: ModelConfig, carried: Tensor | None) -> Tensor | None:
    """(R, 2, 2) map of ``agent_velocity_change``'s o_t = (along, across) to model-frame metres: columns
    s e and s e_perp, e the direction of the last observed step (+x where it is zero) and s its length
    floored at ``agent_min_step_m``; None for the other step outputs."""
    if config.step_output != "agent_velocity_change" or carried is None:
        return None
    # At inference as products, a sum and a root per row: a norm's reduction took other kernels for one agent than
    # for several and moved its bits (see ``row_blocks``).
    length = (torch.linalg.vector_norm(carried, dim=-1, keepdim=True) if torch.is_grad_enabled()
              else torch.sqrt(carried[:, :1] * carried[:, :1] + carried[:, 1:] * carried[:, 1:]))
    unit = torch.where(length > 1e-6, carried / length.clamp(min=1e-6), carried.new_tensor([1.0, 0.0]))
    s = length.clamp(min=config.agent_min_step_m)
    along = unit * s
    across = torch.stack((-along[:, 1], along[:, 0]), dim=-1)
    return torch.stack((along, across), dim=-1)


def mode_open(net: TrajectoryLayers, h0: Tensor, constant_velocity_modes: int | None, mode_dim: int) -> Tensor | None:
    """The factor (..., 1) on each mode's step outputs o_t, from the decoder's initial state ``h0`` whose
    modes run along ``mode_dim``: the mode gate (``ModelConfig.mode_gate``), times 0 for the first
    ``constant_velocity_modes`` modes. With a velocity-change output such a mode is exactly the
    constant-velocity forecast (standing still for an agent standing still), a mode the learned gate may
    never reach; None when every factor is 1. ``constant_velocity_modes`` None: the config's
    (``ModelConfig.held_modes``)."""
    gate = None if net.mode_gate is None else sigmoid(net.mode_gate(h0))  # row_blocks.sigmoid: see there
    num_modes = h0.shape[mode_dim]
    if constant_velocity_modes is None:
        constant_velocity_modes = net.config.held_modes(num_modes)
    if constant_velocity_modes == 0:
        return gate
    if net.config.step_output == "displacement":
        raise ConfigError("constant-velocity modes need a velocity-change step_output; with 'displacement' "
                          "a zero output means standing still, not constant velocity")
    if not 0 < constant_velocity_modes <= num_modes:
        raise ConfigError(f"constant_velocity_modes must be in 0..{num_modes} (the modes drawn), "
                          f"got {constant_velocity_modes}")
    shape = [1] * h0.dim()
    shape[mode_dim] = num_modes
    keep = (torch.arange(num_modes, device=h0.device) >= constant_velocity_modes).to(h0.dtype).view(shape)
    return keep if gate is None else gate * keep


def decode(net: TrajectoryLayers, batch: Batch, enc: Encoded, noise: Tensor,
           constant_velocity_modes: int | None = None) -> Prediction:
    """``net``'s eqs. 17-22 for M modes of the rows observed at the current step.

    Args:
        net: the network whose layers run.
        batch: the batch that was encoded.
        enc: ``encode(batch)``.
        noise: (M, R, noise_dim) Gaussian z of eq. 21, R = number of active rows.
        constant_velocity_modes: the first this many modes get no step outputs (see ``mode_open``;
            None: the config's).
    """
    cfg = net.config
    ps, ds = cfg.pos_scale_m, cfg.disp_scale_m
    t_obs = batch.obs_len
    rows = batch.active.nonzero().squeeze(1)
    mm, r, _ = noise.shape
    b = batch.size
    hid = cfg.lstm_dim
    scene = batch.scene[rows]
    every = torch.ones(mm, r, dtype=torch.bool, device=noise.device)
    h = net.init_decoder(torch.cat((enc.h[rows][None].expand(mm, r, hid), noise), dim=-1))  # eqs. 21-22
    open_factor = mode_open(net, h, constant_velocity_modes, mode_dim=0)  # (M, R, 1)
    c = enc.c[rows][None].expand(mm, r, hid).reshape(mm * r, hid)
    h_gru = None if enc.h_gru is None else enc.h_gru[None].expand(mm, b, -1).reshape(mm * b, -1)
    ego_ok = (batch.ego[rows][:, None] & enc.ego_ok[scene]) if cfg.features.uses_ego_plan else None
    p_prev = batch.positions[rows, t_obs - 2][None].expand(mm, r, 2)
    p_cur = batch.positions[rows, t_obs - 1][None].expand(mm, r, 2)
    carried = carried_first_step(cfg, batch, rows)
    basis = agent_output_basis(cfg, carried)
    outputs: list[Tensor] = []
    lstm_d = lstm_weights(net.decoder)
    for k in range(cfg.pred_len):
        if k > 0:  # one LSTM_D step at t = T_obs + k on the predicted positions
            t = t_obs - 1 + k
            f_t = None if enc.f_all is None else enc.f_all[None, :, t].expand(mm, b, -1).reshape(mm * b, -1)
            if cfg.interaction_while_decoding:
                parts = []
                if net.ain.position is not None:
                    parts.append(net.ain.position(p_cur / ps, every, batch, rows).reshape(mm * b, -1))
                if net.ain.tracking is not None:  # h_d^(t-1)
                    parts.append(net.ain.tracking(h, every, batch, rows).reshape(mm * b, -1))
                if enc.m_all is not None:
                    parts.append(enc.m_all[None, :, t].expand(mm, b, -1).reshape(mm * b, -1))
                fst, h_gru = net.ain.step(parts, f_t, h_gru)
            else:  # the AIN's state as observed at T_obs
                fst = net.ain.output(f_t, h_gru)
            x = [net.disp_embed((p_cur - p_prev) / ds)]  # eq. 17
            if net.env is not None:
                x.append(map_features(net, enc.proj, p_cur, batch, rows))
            q = attention_q(net, None if fst is None else fst.view(mm, b, -1), scene, p_cur / ps)
            if q is not None:
                x.append(q)
            h_flat, c = lstm_step(lstm_d, torch.cat(x, dim=-1).reshape(mm * r, -1), h.reshape(mm * r, hid), c)
            h = h_flat.view(mm, r, hid)  # eq. 18
        o = net.out(h) if open_factor is None else net.out(h) * open_factor  # mode_gate, constant_velocity_modes
        # eqs. 19-20; agent_velocity_change reads o_t in the agent's frame and speed units
        p_next = p_cur + (o * ds if basis is None else torch.einsum("mrj,rij->mri", o, basis))
        if carried is not None:  # the velocity-change outputs: o_t corrects a constant-velocity step
            p_next = p_next + (carried[None] if k == 0 else p_cur - p_prev)
        if ego_ok is not None:  # the ego follows its given (planned) future
            given = ego_ok[:, t_obs + k]
            p_next = torch.where(given[None, :, None], enc.ego_pos[scene, t_obs + k][None], p_next)
        outputs.append(p_next)
        p_prev, p_cur = p_cur, p_next
    return Prediction(torch.stack(outputs, dim=2), rows)
