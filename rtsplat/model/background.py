"""Radiance from beyond the surfels: what a camera ray sees where the volume transmittance is left.

    C_trans = sum_i w_i c_i + (1 - volume_alpha) * B(d)

``B(d)`` depends only on the ray direction ``d`` (light from infinitely far away: a sky, distant
buildings). It is seen directly where no surfel covers a pixel and through see-through surfaces,
since it is attenuated by the volume weights like any radiance behind them.

:class:`BackgroundMap` is the learned ``B``: an RGB equirectangular map with the environment map's
direction convention and bilinear sampling (:class:`rtsplat.model.envmap.EnvironmentMap`), stored as
a sum of maps at ``levels`` resolutions, each half the previous one, passed through a sigmoid. A ray
updates one texel neighbourhood per level, so the coarse levels fill the directions that few training
pixels see with the average colour around them while the finest level holds the detail.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor, nn

from rtsplat.model.envmap import EnvironmentMap
from rtsplat.raster.numba_runtime import SURFEL_CHUNK, kernels_take, load_numba_module, numba_threads

BACKGROUND_MODES = ("learned", "black", "white", "random")


class BackgroundMap(nn.Module):
    def __init__(self, height: int = 128, width: int = 256, levels: int = 4):
        super().__init__()
        if height < 2 or width < 2 or levels < 1:
            raise ValueError(f"background map needs height, width >= 2 and levels >= 1, got {height}x{width}x{levels}")
        sizes = [(max(height >> i, 2), max(width >> i, 2)) for i in range(levels)]
        # logit 0 everywhere: mid grey until the training views say otherwise
        self.maps = nn.ParameterList([nn.Parameter(torch.zeros(1, 3, h, w)) for h, w in sizes])

    def forward(self, directions: Tensor) -> Tensor:
        """RGB [..., 3] in (0, 1) at unit ``directions`` [..., 3]. On CPU tensors of one float type the levels
        are sampled and summed by numba kernels (:mod:`rtsplat.model.background_kernels`, through
        :class:`BackgroundLookup` with autograd), which read the levels where they are: the operations of
        :meth:`logits_reference`, in its order, so the same logits, in a fraction of the time of the torch ops'
        passes over every sample; elsewhere, or without numba, by :meth:`logits_reference`."""
        flat = directions.reshape(-1, 3)
        u, v = EnvironmentMap.direction_to_uv(flat)
        logits = self._logits_by_kernel(u, v)
        if logits is None:
            logits = self.logits_reference(u, v)
        return torch.sigmoid(logits).reshape(*directions.shape[:-1], 3)

    def logits_reference(self, u: Tensor, v: Tensor) -> Tensor:
        """The summed logits [M, 3] at (u, v) [M] in torch: each level's bilinear sample
        (:meth:`EnvironmentMap.sample_level`), the levels added in turn. The kernels' oracle."""
        return sum(EnvironmentMap.sample_level(level, u, v) for level in self.maps)

    def _logits_by_kernel(self, u: Tensor, v: Tensor) -> Tensor | None:
        """The summed logits [M, 3] at (u, v) from the numba kernels; None where they do not apply: unless the
        samples and the maps are CPU tensors of one float type, float32 or float64, and numba is installed."""
        if not kernels_take("rtsplat.model.background_kernels", u, v, *self.maps):
            return None
        if torch.is_grad_enabled() and (u.requires_grad or v.requires_grad or any(m.requires_grad for m in self.maps)):
            return BackgroundLookup.apply(u, v, *self.maps)
        return BackgroundLookup.logits(u, v, list(self.maps))


class BackgroundLookup(torch.autograd.Function):
    """The learned background's summed logits [M, 3] on the CPU: ``apply(u, v, *levels)`` with samples at (``u``,
    ``v``) [M] and the map's ``levels`` [1, 3, H, W] (each half the size of the one before, as
    :class:`BackgroundMap` holds them). The values are those of :meth:`BackgroundMap.logits_reference`, bit for bit;
    the gradients of the levels, u and v are its gradients up to rounding (the levels' summed in their own float
    type, sample after sample; u's and v's in float64). A sample with a non-finite coordinate gives NaN, a NaN
    gradient of its u and v, and reads no texel."""

    @staticmethod
    def logits(u: Tensor, v: Tensor, levels: list[Tensor], taps: np.ndarray | None = None,
               fractions: np.ndarray | None = None, jacobian: np.ndarray | None = None) -> Tensor:
        """The forward kernel's logits; ``taps``, ``fractions`` and ``jacobian`` (when given) receive what the
        backward reads (for the levels' gradients, for the samples')."""
        kernels = load_numba_module("rtsplat.model.background_kernels")
        dtype = levels[0].dtype
        out = torch.empty(u.shape[0], 3, dtype=dtype)
        consts = torch.tensor([0.0, 0.5, 1.0], dtype=dtype)
        if taps is None:
            taps = np.empty((0, 0, 4), dtype=np.int64)
            fractions = np.empty((0, 0, 2), dtype=np.float64)
        if jacobian is None:
            jacobian = np.empty((0, 6), dtype=np.float64)
        with numba_threads(SURFEL_CHUNK):
            kernels.background_logits_kernel(_texels(levels), _sizes(levels).numpy(), u.detach().contiguous().numpy(),
                                             v.detach().contiguous().numpy(), consts.numpy(), out.numpy(), taps,
                                             fractions, jacobian)
        return out

    @staticmethod
    def forward(ctx, u: Tensor, v: Tensor, *levels: Tensor) -> Tensor:
        m = u.shape[0]
        taps = np.empty((m, len(levels), 4), dtype=np.int64)
        fractions = np.empty((m, len(levels), 2), dtype=np.float64)
        jacobian = np.empty((m if u.requires_grad or v.requires_grad else 0, 6), dtype=np.float64)
        out = BackgroundLookup.logits(u, v, [level.detach() for level in levels], taps, fractions, jacobian)
        ctx.taps = (taps, fractions, jacobian)
        ctx.level_sizes = [tuple(level.shape[-2:]) for level in levels]
        ctx.sample_dtypes = (u.dtype, v.dtype)
        return out

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad: Tensor):
        kernels = load_numba_module("rtsplat.model.background_kernels")
        taps, fractions, jacobian = ctx.taps
        g = grad.contiguous().numpy()
        g_u = g_v = None
        g_levels = [None] * taps.shape[1]
        if any(ctx.needs_input_grad[2:]):
            g_levels = [torch.zeros(1, 3, h, w, dtype=grad.dtype) for h, w in ctx.level_sizes]
            with numba_threads(1):  # one level per chunk, so that the levels spread over the threads
                kernels.background_level_grad_kernel(taps, fractions, g, _texels(g_levels))
        if ctx.needs_input_grad[0] or ctx.needs_input_grad[1]:
            su = np.empty(taps.shape[0], dtype=np.float64)
            sv = np.empty(taps.shape[0], dtype=np.float64)
            with numba_threads(SURFEL_CHUNK):
                kernels.background_sample_grad_kernel(jacobian, g, su, sv)
            g_u = torch.from_numpy(su).to(ctx.sample_dtypes[0])
            g_v = torch.from_numpy(sv).to(ctx.sample_dtypes[1])
        return g_u, g_v, *g_levels


def _texels(levels) -> tuple[np.ndarray, ...]:
    """Each level [1, 3, H, W] as the kernels' texel array [3, H*W] (a view of a contiguous level)."""
    return tuple(level.detach().contiguous().reshape(3, -1).numpy() for level in levels)


def _sizes(levels) -> Tensor:
    """Each level's (H, W) [L, 2] in the levels' float type."""
    return torch.tensor([list(level.shape[-2:]) for level in levels], dtype=levels[0].dtype)
