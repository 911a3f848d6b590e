"""The torch device a stage runs on, from a device string: ``auto``, ``cpu``, ``cuda`` or ``cuda:N``.

``auto`` is the first CUDA device when torch sees one, else the CPU. Asking for CUDA where torch
cannot use it is a :class:`~rtsplat.errors.ConfigError` that says why (a CPU-only build of torch, no
GPU visible, a device index out of range) and what to do instead.
"""

from __future__ import annotations

import re
import typing

from rtsplat.errors import ConfigError

if typing.TYPE_CHECKING:
    import torch

__all__ = ["DEVICE_PATTERN", "resolve_device"]

DEVICE_PATTERN = r"^(auto|cpu|cuda(:[0-9]+)?)$"


def resolve_device(name: str | torch.device, *, key: str = "--device") -> torch.device:
    """The torch device that ``name`` asks for; ``key`` (the flag or config key) is named in errors."""
    import torch  # here, not at the top: the pipeline config reads DEVICE_PATTERN without torch

    if isinstance(name, torch.device):
        name = str(name)
    text = str(name).strip().lower()
    if not re.match(DEVICE_PATTERN, text):
        raise ConfigError(f"{key}: unknown device {name!r}", fix="use auto, cpu, cuda or cuda:N")
    if text == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if text == "cpu":
        return torch.device("cpu")
    if torch.version.cuda is None:
        raise ConfigError(
            f"{key}: {text} asked for, but this torch ({torch.__version__}) is a build without CUDA",
            fix=f"install the CUDA build of torch {torch.__version__.split('+')[0]} (README, 'Running on a GPU'), "
            f"or pass {key} cpu",
        )
    if not torch.cuda.is_available():
        raise ConfigError(
            f"{key}: {text} asked for, but torch (CUDA {torch.version.cuda}) sees no GPU on this machine",
            fix=f"run on a machine with a GPU (check nvidia-smi and CUDA_VISIBLE_DEVICES), or pass {key} cpu "
            "(or auto); on a machine that never has a GPU, install the CPU build of torch",
        )
    device = torch.device(text)
    count = torch.cuda.device_count()
    if device.index is not None and device.index >= count:
        raise ConfigError(f"{key}: {text} asked for, but torch sees {count} GPU(s)",
                          fix=f"use cuda:0 .. cuda:{count - 1}, or cuda")
    return device
