"""The specular pass's per-pixel inputs from the G-buffer (paper section 3.2): at the shaded pixels, the reflected
direction, ``|cos|`` of the angle of incidence, the roughness, the material feature and the reflectance.

:func:`specular_inputs` computes them on the CPU in numba kernels with a hand-written backward
(:class:`SpecularInputs`, :mod:`rtsplat.model.specular_inputs_kernels`): one pass over the shaded pixels each way,
instead of some twenty torch operations, their row gathers and the full-image gradients of each. Elsewhere, and as
the kernels' oracle, :func:`specular_inputs_reference` computes them in torch's operations.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from rtsplat.raster.numba_runtime import kernels_take, load_numba_module


class ShadingInputs(NamedTuple):
    """Per shaded pixel [N]: ``reflected`` [N,3] (unit), ``cos_incidence`` [N,1] in [0, 1], ``roughness`` [N] and
    ``reflectance`` [N,1] in [0, 1], ``material`` [N,4] (unit)."""

    reflected: Tensor
    cos_incidence: Tensor
    roughness: Tensor
    material: Tensor
    reflectance: Tensor


def specular_inputs(rays: Tensor, normal: Tensor, roughness: Tensor, material: Tensor, reflectance: Tensor,
                    alpha: Tensor, idx: Tensor | None) -> ShadingInputs:
    """The inputs at the pixels ``idx`` [N] of the flattened image (None: every pixel) from the unit pixel ``rays``
    [...,3] (no gradient), the unit blended ``normal`` [...,3], the blended (alpha-weighted) ``roughness``,
    ``material`` and ``reflectance`` channels [...,1 / 4 / 1] and the surface ``alpha`` [...,1] (at least 1e-6):

    * ``cos_incidence = min(|i . n|, 1)`` and ``reflected = normalize(i - 2 (i . n) n)``;
    * ``roughness``, ``reflectance``: the channel over ``alpha``, clamped to [0, 1];
    * ``material``: the channel normalised.

    On CPU float32/float64 tensors with numba, :class:`SpecularInputs`; else :func:`specular_inputs_reference`."""
    if not kernels_take("rtsplat.model.specular_inputs_kernels", rays, normal, roughness, material, reflectance,
                        alpha):
        return specular_inputs_reference(rays, normal, roughness, material, reflectance, alpha, idx)
    if idx is None:
        idx = torch.arange(alpha.numel(), device=alpha.device)
    return ShadingInputs(*SpecularInputs.apply(rays.reshape(-1, 3), normal.reshape(-1, 3), roughness.reshape(-1),
                                               material.reshape(-1, 4), reflectance.reshape(-1), alpha.reshape(-1),
                                               idx))


def specular_inputs_reference(rays: Tensor, normal: Tensor, roughness: Tensor, material: Tensor,
                              reflectance: Tensor, alpha: Tensor, idx: Tensor | None) -> ShadingInputs:
    """:func:`specular_inputs` in torch's operations, on any device."""
    rows = (lambda t: t) if idx is None else (lambda t: t[idx])  # noqa: E731
    incident = rows(rays.reshape(-1, 3))
    n = rows(normal.reshape(-1, 3))
    incidence = (incident * n).sum(-1, keepdim=True)  # cosine of the angle of incidence (signed)
    cos_incidence = incidence.abs().clamp(0, 1)
    reflected = F.normalize(incident - 2.0 * incidence * n, dim=-1)
    rough = rows((roughness / alpha).reshape(-1)).clamp(0, 1)
    unit_material = F.normalize(rows(material.reshape(-1, 4)), dim=-1)
    refl = rows((reflectance / alpha).reshape(-1, 1)).clamp(0, 1)
    return ShadingInputs(reflected, cos_incidence, rough, unit_material, refl)


def _array(t: Tensor) -> np.ndarray:
    """A CPU tensor's values as a numpy array (shared memory; any strides)."""
    return t.detach().numpy()


class SpecularInputs(torch.autograd.Function):
    """:func:`specular_inputs` on the CPU: ``apply(rays [P,3], normal [P,3], roughness [P], material [P,4],
    reflectance [P], alpha [P], idx [N])`` -> (reflected [N,3], cos_incidence [N,1], roughness [N], material [N,4],
    reflectance [N,1]), computed in float64 and returned in the inputs' float type. The rows of ``idx`` must be
    distinct (each pixel's gradient is written, not added). The backward returns full-image gradients [P,...], zero
    outside ``idx``; the rays get none."""

    @staticmethod
    def forward(ctx, rays, normal, roughness, material, reflectance, alpha, idx):
        kernels = load_numba_module("rtsplat.model.specular_inputs_kernels")
        n = idx.shape[0]
        dtype = normal.dtype
        reflected = torch.empty(n, 3, dtype=dtype)
        cos_incidence = torch.empty(n, 1, dtype=dtype)
        rough_out = torch.empty(n, dtype=dtype)
        material_out = torch.empty(n, 4, dtype=dtype)
        refl_out = torch.empty(n, 1, dtype=dtype)
        index = idx.detach().to(torch.int64).contiguous()
        inputs = (rays, normal, roughness, material, reflectance, alpha)
        kernels.specular_inputs_kernel(index.numpy(), *(_array(t) for t in inputs), reflected.numpy(),
                                       cos_incidence.numpy()[:, 0], rough_out.numpy(), material_out.numpy(),
                                       refl_out.numpy()[:, 0])
        ctx.save_for_backward(index, *(t.detach() for t in inputs))
        return reflected, cos_incidence, rough_out, material_out, refl_out

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, g_reflected, g_cos, g_rough, g_material, g_refl):
        kernels = load_numba_module("rtsplat.model.specular_inputs_kernels")
        index, rays, normal, roughness, material, reflectance, alpha = ctx.saved_tensors
        n = index.shape[0]
        dtype = normal.dtype

        def given(grad, *shape):
            return (torch.zeros(n, *shape, dtype=dtype) if grad is None else grad.to(dtype)).contiguous()

        grads = (given(g_reflected, 3), given(g_cos, 1)[:, 0], given(g_rough), given(g_material, 4),
                 given(g_refl, 1)[:, 0])
        d_normal = torch.zeros_like(normal, memory_format=torch.contiguous_format)
        d_rough = torch.zeros_like(roughness, memory_format=torch.contiguous_format)
        d_material = torch.zeros_like(material, memory_format=torch.contiguous_format)
        d_refl = torch.zeros_like(reflectance, memory_format=torch.contiguous_format)
        d_alpha = torch.zeros_like(alpha, memory_format=torch.contiguous_format)
        kernels.specular_inputs_grad_kernel(
            index.numpy(), *(_array(t) for t in (rays, normal, roughness, material, reflectance, alpha)),
            *(g.numpy() for g in grads), d_normal.numpy(), d_rough.numpy(), d_material.numpy(), d_refl.numpy(),
            d_alpha.numpy())
        return None, d_normal, d_rough, d_material, d_refl, d_alpha, None
