"""Specular-aware gradient gating (RT-Splatting section 3.3).

g(x) = exp(-k * s(x)) with s the local (3x3) specular complexity; the forward value of C_trans is
unchanged while its gradient is scaled by g:

    C_trans_gated = (1 - g) * stopgrad(C_trans) + g * C_trans

Two measures of complexity, per colour channel:
* ``variance``: the paper's equation, plain variance of C_spec over the 3x3 window;
* ``weighted_std``: what the authors' code does, the weighted standard deviation over a
  reflect-padded 3x3 window with weights (1 - surface alpha), detached.
g itself is never differentiated. On CPU tensors (float32 or float64, numba installed) :func:`gate_factor` runs the
numba kernel of :mod:`rtsplat.model.gating_kernels`; :func:`gate_factor_reference` is the torch version it is tested
against, used on other devices.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

from rtsplat.raster.numba_runtime import kernels_take, load_numba_module

MODES = ("weighted_std", "variance")


def _windows(image_chw: Tensor) -> Tensor:
    """3x3 neighbourhoods [C, 9, H, W] with reflect padding."""
    C, H, W = image_chw.shape
    padded = F.pad(image_chw[None], (1, 1, 1, 1), mode="reflect")
    return F.unfold(padded, 3).reshape(C, 9, H, W)


def specular_complexity(specular: Tensor, surface_alpha: Tensor, mode: str = "weighted_std") -> Tensor:
    """[H,W,3], [H,W,1] -> per-channel complexity [H,W,3] (detached)."""
    with torch.no_grad():
        spec = _windows(specular.permute(2, 0, 1))  # [3,9,H,W]
        if mode == "variance":
            return spec.var(dim=1, unbiased=False).permute(1, 2, 0)
        if mode != "weighted_std":
            raise ValueError(f"unknown gating mode {mode!r}")
        weight = _windows((1.0 - surface_alpha).clamp_min(0).permute(2, 0, 1))  # [1,9,H,W]
        total = weight.sum(1, keepdim=True).clamp_min(1e-8)
        mean = (weight * spec).sum(1, keepdim=True) / total
        var = (weight * (spec - mean) ** 2).sum(1) / total[:, 0]
        return var.clamp_min(0).sqrt().permute(1, 2, 0)


def gate_factor(specular: Tensor, surface_alpha: Tensor, k: float = 4.0, mode: str = "weighted_std") -> Tensor:
    """g = exp(-k s) [H,W,3] (detached) for ``specular`` [H,W,3] and ``surface_alpha`` [H,W,1]: on the CPU the numba
    kernel (the same values to float32 rounding, in a fifth of the time at 100x75), else
    :func:`gate_factor_reference`."""
    if mode not in MODES:
        raise ValueError(f"unknown gating mode {mode!r}")
    if not _kernel_applies(specular, surface_alpha):
        return gate_factor_reference(specular, surface_alpha, k, mode)
    spec = specular.detach().contiguous()
    alpha = surface_alpha.detach().to(spec.dtype).reshape(spec.shape[:2]).contiguous()
    out = torch.empty_like(spec)
    load_numba_module("rtsplat.model.gating_kernels").gate_factor_kernel(
        spec.numpy(), alpha.numpy(), float(k), mode == "weighted_std", out.numpy())
    return out


def gate_factor_reference(specular: Tensor, surface_alpha: Tensor, k: float = 4.0,
                          mode: str = "weighted_std") -> Tensor:
    """:func:`gate_factor` in torch's ops, on any device."""
    return torch.exp(-k * specular_complexity(specular, surface_alpha, mode))


def _kernel_applies(specular: Tensor, surface_alpha: Tensor) -> bool:
    """CPU float32/float64 images of at least 2x2 pixels (reflect padding; the alpha in any float type, read in the
    specular's) and numba installed."""
    if surface_alpha.device.type != "cpu" or specular.dim() != 3 or specular.shape[0] < 2 or specular.shape[1] < 2:
        return False
    return kernels_take("rtsplat.model.gating_kernels", specular)


def gate_gradient(value: Tensor, g: Tensor) -> Tensor:
    """Forward: ``value``; backward: gradient times ``g``."""
    g = g.detach()
    return (1.0 - g) * value.detach() + g * value
