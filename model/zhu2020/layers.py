"""The parameters of the paper's network, Zhu et al. (IJCAI 2020): the Agent Interaction Network (eqs. 1-10,
``interaction``), the Environment Network (eqs. 11-12, ``environment``) and the layers of the Trajectory
Prediction Network (eqs. 13-22). Their attribute names are the checkpoints' state_dict keys.

The encoder and both decoders (``encoder``, ``decoder``, ``fast_decoder``) are functions of these layers; the
network (``network.TrajectoryNet``) adds the noise z and the choice of decoder. Neither the layers nor the functions
import the network, so the parts form no import circle.
"""

from __future__ import annotations

from pathlib import Path

from torch import nn

from ..training.row_blocks import RowLinear
from .backbone import read_state_dict
from .config import ModelConfig
from .environment import EnvironmentNet
from .interaction import AgentInteractionNet


class TrajectoryLayers(nn.Module):
    """Every layer of the network (eqs. 1-22), built in the order that fixes the initial weights."""

    def __init__(self, config: ModelConfig, *, load_backbone: bool = True) -> None:
        super().__init__()
        # Built in this order: it fixes the initial weights drawn from torch's RNG and the parameters' order.
        self.config = config
        feats, d, hid = config.features, config.embed_dim, config.lstm_dim
        self.ain = AgentInteractionNet(config)
        self.env = EnvironmentNet(config) if feats.environment else None
        if self.env is not None and config.backbone_weights and load_backbone:
            self.env.backbone.load_torchvision_state_dict(read_state_dict(Path(config.backbone_weights)))
        d_fst = self.ain.out_dim
        self.attention = RowLinear(2, d_fst) if d_fst else None  # eq. 13, W_c, b_c
        self.disp_embed = RowLinear(2, d)  # eqs. 15/17, W_p, b_p
        lstm_in = d + (d if self.env is not None else 0) + d_fst
        self.encoder = nn.LSTMCell(lstm_in, hid)  # eq. 16, LSTM_E
        self.decoder = nn.LSTMCell(lstm_in, hid)  # eq. 18, LSTM_D
        self.out = RowLinear(hid, 2)  # eq. 19, W_u, b_u
        self.init_decoder = RowLinear(hid + config.noise_dim, hid)  # eqs. 21-22, W_phi, b_phi
        self.mode_gate = RowLinear(hid, 1) if config.mode_gate else None  # see ModelConfig.mode_gate

