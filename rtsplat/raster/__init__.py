"""Differentiable rasterizer for 2D Gaussian surfels with occupancy/opacity compositing.

Public API (small on purpose, in the spirit of gsplat)::

    from rtsplat.raster import Surfels, RasterSettings, rasterize
    out = rasterize(surfels, camera)            # RasterOutput: G-buffers + volume buffers
    out.color, out.normal, out.features, ...

One traversal of each pixel's depth-sorted list accumulates both weight sets of METHOD.md 2:
surface weights from the occupancy (G-buffers) and volume weights from occupancy x opacity
(transmitted color). ``reference`` is a readable pure-PyTorch implementation (autograd, runs on
any torch device); it is the oracle that every faster backend is tested against.
"""

from __future__ import annotations

import importlib
import importlib.util
from collections.abc import Callable

from torch import Tensor

from rtsplat.camera import Camera
from rtsplat.errors import ConfigError
from rtsplat.raster.types import RasterOutput, RasterSettings, Surfels

__all__ = [
    "Surfels", "RasterSettings", "RasterOutput", "rasterize", "available_backends", "BACKENDS", "check_backend_name",
    "register_backend",
]

# name -> "module:function". Each function has the signature
#   fn(surfels, camera, settings, screen_probe) -> RasterOutput
BACKENDS: dict[str, str] = {
    "reference": "rtsplat.raster.reference:rasterize_reference",
    "cpu": "rtsplat.raster.cpu:rasterize_cpu",
    "triton": "rtsplat.raster.gpu:rasterize_triton",
}


def check_backend_name(name: str, key: str = "backend") -> str:
    """``name`` when it is 'auto' or a registered backend, else a :class:`ConfigError` naming ``key`` and
    listing the backends."""
    if name != "auto" and name not in BACKENDS:
        raise ConfigError(f"{key} is {name!r}: not a rasterizer backend",
                          fix=f"use one of {', '.join(['auto', *sorted(BACKENDS)])}")
    return name


def register_backend(name: str, target: str) -> None:
    """Register a backend as ``"module:function"`` (imported lazily on first use)."""
    BACKENDS[name] = target


def _resolve(name: str) -> Callable:
    if name not in BACKENDS:
        raise ValueError(f"unknown rasterizer backend {name!r}; choose one of {sorted(BACKENDS)} or 'auto'")
    module, func = BACKENDS[name].split(":")
    return getattr(importlib.import_module(module), func)


def available_backends() -> list[str]:
    return sorted(BACKENDS)


def default_backend(device) -> str:
    """The backend ``auto`` picks: the fastest registered one for the device.

    CUDA tensors: ``triton`` when the triton package is installed, else ``reference``; CPU
    tensors: ``cpu``. The triton backend also runs on CPU tensors in Triton's interpreter, but
    only when asked for by name (it is a test harness there, far slower than ``cpu``).
    """
    kind = getattr(device, "type", str(device))
    preferred = ["triton"] if kind == "cuda" else ["cpu"]
    for name in preferred:
        if name in BACKENDS and (name != "triton" or importlib.util.find_spec("triton") is not None):
            return name
    return "reference"


def rasterize(
    surfels: Surfels,
    camera: Camera,
    settings: RasterSettings | None = None,
    *,
    backend: str = "auto",
    screen_probe: Tensor | None = None,
) -> RasterOutput:
    """Rasterize ``surfels`` seen by ``camera``.

    ``screen_probe``: optional zero tensor [N,2] (requires_grad) added to the projected centres;
    when omitted and gradients are enabled, one is created and returned in the output so that
    ``out.densification_grad()`` works after ``backward()``.
    """
    settings = settings or RasterSettings()
    if camera.device != surfels.device:
        raise ValueError(f"camera is on {camera.device} but surfels are on {surfels.device}")
    name = default_backend(surfels.device) if backend == "auto" else backend
    return _resolve(name)(surfels, camera, settings, screen_probe)
