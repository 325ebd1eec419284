"""Where the network runs: ``--device auto|cpu|cuda`` and the mixed precision that goes with CUDA.

On the CPU nothing changes: no autocast, no gradient scaling, so CPU results are bit-identical to a run without
a device option. On CUDA the forward passes run under ``torch.autocast`` in bf16 where the GPU supports it, else
fp16, whose small exponent range needs a ``GradScaler`` in training (bf16 has fp32's range and needs none).
Random draws (noise z, augmentation, shuffling) stay on CPU generators whatever the device, so a run draws the
same numbers on every device; only the arithmetic differs.
"""

from __future__ import annotations

import contextlib
from typing import TYPE_CHECKING, Any

from logpipe.errors import LogpipeError

if TYPE_CHECKING:
    import torch

# torch is imported where a function needs it: ``logpipe predict`` with a baseline checks --device here and never
# loads torch (~1 s of a small run's start).


class DeviceError(LogpipeError):
    """A ``--device`` value that is unknown, or names a device torch cannot use here."""


DEVICE_CHOICES = ("auto", "cpu", "cuda")
"""``--device`` values: ``auto`` is CUDA when torch can use a GPU, else the CPU."""


def resolve_device(name: str | torch.device) -> torch.device:
    """The torch device for a ``--device`` value (a ``torch.device`` is taken as it is).

    Raises:
        DeviceError: a value not in ``DEVICE_CHOICES``, or ``cuda`` when torch cannot use a GPU (the message
            says what torch reports: a CPU-only build, or no visible GPU).
    """
    import torch

    if isinstance(name, torch.device):
        return name
    check_device_name(name)
    if name == "cpu":
        return torch.device("cpu")
    if not torch.cuda.is_available():
        if name == "auto":
            return torch.device("cpu")
        raise DeviceError(f"--device cuda: torch cannot use a GPU here ({_cuda_report()}); use --device cpu or auto")
    return torch.device("cuda")


def check_device_name(name: str) -> None:
    """Raise ``DeviceError`` unless ``name`` is one of ``DEVICE_CHOICES`` (for runs that use no device, such as
    the classical baselines, where a typo should still be reported)."""
    if name not in DEVICE_CHOICES:
        raise DeviceError(f"--device must be one of {', '.join(DEVICE_CHOICES)}, got {name!r}")


def _cuda_report() -> str:
    """Why ``torch.cuda.is_available()`` is False, in torch's terms."""
    import torch

    if torch.version.cuda is None:
        return f"torch {torch.__version__} is a CPU-only build"
    return (f"torch {torch.__version__} is built for CUDA {torch.version.cuda} but sees "
            f"{torch.cuda.device_count()} usable GPUs")


def autocast_dtype(device: torch.device) -> torch.dtype | None:
    """The autocast precision on ``device``: bf16 on a GPU that supports it, else fp16; None (fp32) on the CPU."""
    if device.type != "cuda":
        return None
    import torch

    return torch.bfloat16 if torch.cuda.is_bf16_supported() else torch.float16


def autocast(device: torch.device) -> contextlib.AbstractContextManager[Any]:
    """Mixed precision for forward passes on ``device`` (``autocast_dtype``); a no-op context on the CPU."""
    dtype = autocast_dtype(device)
    if dtype is None:
        return contextlib.nullcontext()
    import torch

    return torch.autocast(device.type, dtype=dtype)


def grad_scaler(device: torch.device) -> torch.amp.GradScaler | None:
    """A loss scaler for training under fp16 autocast (fp16 gradients underflow without it); None otherwise."""
    import torch

    if autocast_dtype(device) != torch.float16:
        return None
    return torch.amp.GradScaler(device.type)
