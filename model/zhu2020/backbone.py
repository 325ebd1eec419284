"""ResNet18 stages 1-2 (output stride 8) and ROIAlign, in plain torch (Environment Network, eqs. 11-12).

The module names match torchvision's ``resnet18`` (``conv1``, ``bn1``, ``layer1``, ``layer2``) so a
torchvision-layout state dict loads directly; ``layer3``/``layer4``/``fc`` keys are ignored.

Pixel convention: raster pixel coordinates (col, row) have integer values at pixel *centres* (OpenCV's
drawing convention). With "same" padding, feature cell ``i`` of the stride-8 output is centred on pixel
``8 i`` (conv1 /2, maxpool /2, layer2 /2), so a pixel coordinate ``u`` is feature coordinate ``u / 8``.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import torch
from torch import Tensor, nn
from torch.nn import functional as F  # noqa: N812

from logpipe.errors import LogpipeError

if TYPE_CHECKING:
    from .config import ModelConfig

BACKBONE_STRIDE = 8
BACKBONE_CHANNELS = 128


class BackboneWeightsError(LogpipeError):
    """A pre-trained backbone file is unreadable or does not have the ResNet18 layout."""


def native_bf16() -> bool:
    """Whether this CPU computes bf16 natively (AVX512-BF16 or AMX). Without it oneDNN emulates bf16, and the
    backbone ran 4-5x slower in bf16 than in fp32 (AVX2 AMD EPYC: 5 against 23 images/s on 2 threads)."""
    checks = ("_is_avx512_bf16_supported", "_is_amx_tile_supported")
    return any(bool(getattr(torch.cpu, name, lambda: False)()) for name in checks)


def backbone_runs_bf16(config: ModelConfig) -> bool:
    """Whether a model of ``config`` runs its backbone in bf16 on this CPU: it has the environment net, asks for
    ``backbone_bf16`` and the CPU computes bf16 natively."""
    return config.features.environment and config.backbone_bf16 and native_bf16()


class BasicBlock(nn.Module):
    """ResNet basic block: two 3x3 convs with batch norm and an identity (or 1x1 projection) shortcut."""

    def __init__(self, in_ch: int, out_ch: int, stride: int) -> None:
        super().__init__()
        self.conv1 = nn.Conv2d(in_ch, out_ch, 3, stride, 1, bias=False)
        self.bn1 = nn.BatchNorm2d(out_ch)
        self.conv2 = nn.Conv2d(out_ch, out_ch, 3, 1, 1, bias=False)
        self.bn2 = nn.BatchNorm2d(out_ch)
        self.downsample: nn.Sequential | None = None
        if stride != 1 or in_ch != out_ch:
            self.downsample = nn.Sequential(
                nn.Conv2d(in_ch, out_ch, 1, stride, bias=False), nn.BatchNorm2d(out_ch)
            )

    def forward(self, x: Tensor) -> Tensor:
        """(N, in_ch, H, W) -> (N, out_ch, H / stride, W / stride)."""
        out = F.relu(self.bn1(self.conv1(x)))
        out = self.bn2(self.conv2(out))
        shortcut = x if self.downsample is None else self.downsample(x)
        return F.relu(out + shortcut)


class ResNet18Stages12(nn.Module):
    """Stem + ``layer1`` + ``layer2`` of ResNet18: (N, C_in, H, W) -> (N, 128, H/8, W/8).

    Attributes:
        in_channels: raster channels C.
        use_bf16: run under bf16 autocast with channels_last memory (output is returned as float32), when
            the CPU has native bf16 (``native_bf16``); asked for elsewhere, the backbone runs in fp32.
    """

    def __init__(self, in_channels: int, use_bf16: bool = False) -> None:
        super().__init__()
        self.in_channels = in_channels
        self.use_bf16 = use_bf16 and native_bf16()
        self.conv1 = nn.Conv2d(in_channels, 64, 7, 2, 3, bias=False)
        self.bn1 = nn.BatchNorm2d(64)
        self.maxpool = nn.MaxPool2d(3, 2, 1)
        self.layer1 = nn.Sequential(BasicBlock(64, 64, 1), BasicBlock(64, 64, 1))
        self.layer2 = nn.Sequential(BasicBlock(64, 128, 2), BasicBlock(128, 128, 1))
        for m in self.modules():  # He init as in the reference ResNet
            if isinstance(m, nn.Conv2d):
                nn.init.kaiming_normal_(m.weight, mode="fan_out", nonlinearity="relu")

    def _features(self, x: Tensor) -> Tensor:
        x = self.maxpool(F.relu(self.bn1(self.conv1(x))))
        return self.layer2(self.layer1(x))  # type: ignore[no-any-return]

    def forward(self, x: Tensor) -> Tensor:
        """Feature map at output stride 8, float32 (contiguous NCHW)."""
        # channels_last in both precisions: fp32 ran 1.28x the images/s of NCHW on an AVX2 EPYC (32.7 against
        # 25.5 on 2 threads), bf16 autocast ~3x fp32 on AMX CPUs.
        x = x.contiguous(memory_format=torch.channels_last)
        # On a GPU the caller's autocast (``model.training.device``) rules.
        if not self.use_bf16 or x.device.type != "cpu":
            return self._features(x).contiguous()
        with torch.autocast("cpu", dtype=torch.bfloat16):
            out = self._features(x)
        return out.float().contiguous()

    def load_torchvision_state_dict(self, state: dict[str, Tensor]) -> None:
        """Load the stage-1/2 tensors of a torchvision ResNet18 state dict.

        ``conv1`` of an RGB checkpoint is adapted to ``in_channels`` by averaging over RGB and repeating
        (scaled by 3 / C so activations keep their magnitude), the usual trick for non-RGB inputs.
        """
        wanted = {k: v for k, v in state.items() if k.split(".")[0] in ("conv1", "bn1", "layer1", "layer2")}
        own = self.state_dict()
        missing = sorted(set(own) - set(wanted))
        if missing:
            raise BackboneWeightsError(f"ResNet18 state dict lacks {len(missing)} keys, e.g. {missing[:3]}")
        conv1 = wanted["conv1.weight"]
        if conv1.shape[1] != self.in_channels:
            mean = conv1.float().mean(dim=1, keepdim=True)
            wanted["conv1.weight"] = mean.repeat(1, self.in_channels, 1, 1) * (conv1.shape[1] / self.in_channels)
        for key, value in wanted.items():
            if key in own and tuple(own[key].shape) != tuple(value.shape):
                raise BackboneWeightsError(
                    f"{key}: shape {tuple(value.shape)} does not match ResNet18's {tuple(own[key].shape)}"
                )
        self.load_state_dict({k: v.to(own[k].dtype) for k, v in wanted.items() if k in own})


def read_state_dict(path: Path) -> dict[str, Tensor]:
    """Tensors of a safetensors file, or of a ``torch.save`` file loaded with ``weights_only=True``
    (never unpickles arbitrary objects)."""
    try:
        if path.suffix == ".safetensors":
            from safetensors.torch import load_file

            return load_file(str(path))
        data = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # torch/safetensors raise many types for a bad file
        raise BackboneWeightsError(f"{path}: cannot read backbone weights: {exc}") from exc
    if isinstance(data, dict) and "state_dict" in data:
        data = data["state_dict"]
    if not isinstance(data, dict) or not all(isinstance(v, Tensor) for v in data.values()):
        raise BackboneWeightsError(f"{path}: expected a mapping of tensor names to tensors")
    return {str(k).removeprefix("module."): v for k, v in data.items()}


def roi_align(features: Tensor, boxes: Tensor, pool: int, sampling: int = 2) -> Tensor:
    """ROIAlign by bilinear sampling (eq. 11's G_i^(t)).

    Args:
        features: (B, C, Hf, Wf) feature maps.
        boxes: (B, R, 4) boxes ``(x0, y0, x1, y1)`` in feature coordinates (integer = cell centre),
            R boxes per map, pooled from the map of the same batch index.
        pool: K, bins per side.
        sampling: bilinear samples per bin per side, averaged.

    Returns:
        (B, R, C, K, K): per bin, the mean of ``sampling**2`` bilinear samples at the bin's sub-cell
        centres; samples outside the map read zeros beyond the border cells (as ``grid_sample`` zero
        padding does).
    """
    b, c, hf, wf = features.shape
    r = boxes.shape[1]
    # Fractions of the box side at which samples lie, ordered (bin, sub-sample).
    steps = (torch.arange(pool * sampling, dtype=boxes.dtype, device=boxes.device) + 0.5) / (pool * sampling)
    x0, y0, x1, y1 = boxes.unbind(-1)
    xs = x0[..., None] + (x1 - x0)[..., None] * steps  # (B, R, K*S)
    ys = y0[..., None] + (y1 - y0)[..., None] * steps
    # align_corners=True: -1 and +1 are the centres of the first and last cells.
    xn = xs * (2.0 / max(wf - 1, 1)) - 1.0
    yn = ys * (2.0 / max(hf - 1, 1)) - 1.0
    n = pool * sampling
    grid = torch.stack(
        (xn[:, :, None, :].expand(b, r, n, n), yn[:, :, :, None].expand(b, r, n, n)), dim=-1
    ).reshape(b, r, n * n, 2)
    sampled = F.grid_sample(
        features, grid.to(features.dtype), mode="bilinear", padding_mode="zeros", align_corners=True
    )  # (B, C, R, (ky, sy, kx, sx))
    sampled = sampled.view(b, c, r, pool, sampling, pool, sampling).mean(dim=(4, 6))
    return sampled.permute(0, 2, 1, 3, 4)
