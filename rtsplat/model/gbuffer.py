"""The G-buffer's surface values: a blended channel of the surface pass (``sum_i p_i a_i``) divided by the pixel's
surface alpha (``sum_i p_i``) is the value of the surface the pixel shows, e.g. its region-of-interest membership,
optical opacity, transmissivity or scatter colour.

:func:`surface_values` computes several at once: on the CPU in numba kernels with a hand-written backward
(:class:`SurfaceValues`, :mod:`rtsplat.model.gbuffer_kernels`), one pass over the pixels each way instead of a
division, a clamp and a column of the G-buffer (and their gradients) per value; elsewhere, and as its oracle,
:func:`surface_values_reference` in torch.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from rtsplat.raster.numba_runtime import kernels_take, load_numba_module


def surface_values(features: Tensor, alpha: Tensor, layout: dict[str, slice], names: tuple[str, ...],
                   clamped: frozenset[str] | set[str]) -> dict[str, Tensor]:
    """``{name: features[..., layout[name]] / alpha}`` [H,W,width] for each of ``names``, clamped to [0, 1] for those
    in ``clamped``: ``features`` [H,W,F] the blended channels, ``alpha`` [H,W,1] the surface alpha (at least 1e-6)."""
    if names and kernels_take("rtsplat.model.gbuffer_kernels", features, alpha):
        spans = [range(features.shape[-1])[layout[name]] for name in names]  # each value's feature columns
        columns = tuple(c for span in spans for c in span)
        flags = tuple(name in clamped for name, span in zip(names, spans, strict=True) for _ in span)
        values = SurfaceValues.apply(features, alpha, columns, flags)
        return dict(zip(names, values.split([len(span) for span in spans], -1), strict=True))
    return surface_values_reference(features, alpha, layout, names, clamped)


def surface_values_reference(features: Tensor, alpha: Tensor, layout: dict[str, slice], names: tuple[str, ...],
                             clamped: frozenset[str] | set[str]) -> dict[str, Tensor]:
    """:func:`surface_values` in torch's operations, on any device."""
    values = {}
    for name in names:
        value = features[..., layout[name]] / alpha
        values[name] = value.clamp(0, 1) if name in clamped else value
    return values


class SurfaceValues(torch.autograd.Function):
    """:func:`surface_values` on the CPU: ``apply(features [H,W,F], alpha [H,W,1], columns, clamped)`` -> [H,W,J],
    column j the feature column ``columns[j]`` over the alpha, clamped to [0, 1] where ``clamped[j]``. The values
    are torch's bit for bit; the gradients are torch's expressions, the alpha's summed over the columns in float64
    (torch sums in the float type)."""

    @staticmethod
    def forward(ctx, features: Tensor, alpha: Tensor, columns: tuple[int, ...], clamped: tuple[bool, ...]):
        kernels = load_numba_module("rtsplat.model.gbuffer_kernels")
        flat, a = features.detach().reshape(-1, features.shape[-1]), alpha.detach().reshape(-1).contiguous()
        out = torch.empty(flat.shape[0], len(columns), dtype=features.dtype)
        kernels.values_kernel(flat.numpy(), a.numpy(), *_constants(columns, clamped, flat.dtype), out.numpy())
        ctx.save_for_backward(flat, a)
        ctx.layout = (columns, clamped, features.shape, alpha.shape)
        return out.reshape(*features.shape[:-1], len(columns))

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad: Tensor):
        kernels = load_numba_module("rtsplat.model.gbuffer_kernels")
        flat, a = ctx.saved_tensors
        columns, clamped, features_shape, alpha_shape = ctx.layout
        d_features = torch.zeros(flat.shape, dtype=flat.dtype)
        d_alpha = torch.empty(flat.shape[0], dtype=torch.float64)
        kernels.values_grad_kernel(flat.numpy(), a.numpy(), *_constants(columns, clamped, flat.dtype),
                                   grad.to(flat.dtype).reshape(flat.shape[0], -1).contiguous().numpy(),
                                   d_features.numpy(), d_alpha.numpy())
        return d_features.reshape(features_shape), d_alpha.to(flat.dtype).reshape(alpha_shape), None, None


def _constants(columns: tuple[int, ...], clamped: tuple[bool, ...], dtype: torch.dtype) -> tuple[np.ndarray, ...]:
    """The kernels' column indices, clamp flags and (0, 1) in the values' float type."""
    return (np.asarray(columns, dtype=np.int64), np.asarray(clamped, dtype=np.bool_),
            torch.tensor([0.0, 1.0], dtype=dtype).numpy())
