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

    def forward(self, directions: Tensor, table: Tensor | None = None) -> Tensor:
        """RGB [..., 3] in (0, 1) at unit ``directions`` [..., 3]. On CPU tensors of one float type the levels
        are sampled and summed by numba kernels (:mod:`rtsplat.model.background_kernels`, through
        :class:`BackgroundLookup` with autograd): the operations of :meth:`logits_reference`, in its order,
        so the same logits, in a fraction of the time of the torch ops' passes over every sample; elsewhere,
        or without numba, by :meth:`logits_reference`. ``table``: the kernels' :meth:`texel_table` when the
        caller shares one between lookups of the same maps (a render's own rays and its reflected directions);
        its gradient, if any, is the caller's."""
        flat = directions.reshape(-1, 3)
        u, v = EnvironmentMap.direction_to_uv(flat)
        logits = self._logits_by_kernel(u, v, table)
        if logits is None:
            logits = self.logits_reference(u, v)
        return torch.sigmoid(logits).reshape(*directions.shape[:-1], 3)

    def logits_reference(self, u: Tensor, v: Tensor) -> Tensor:
        """The summed logits [M, 3] at (u, v) [M] in torch: each level's bilinear sample
        (:meth:`EnvironmentMap.sample_level`), the levels added in turn. The kernels' oracle."""
        return sum(EnvironmentMap.sample_level(level, u, v) for level in self.maps)

    def _logits_by_kernel(self, u: Tensor, v: Tensor, table: Tensor | None = None) -> Tensor | None:
        """The summed logits [M, 3] at (u, v) from the numba kernels (from ``table``, or a texel table built
        here); None where they do not apply."""
        if v.dtype != u.dtype or not self._kernels_apply(u):
            return None
        first, sizes = self._layout()
        table = self.texel_table() if table is None else table
        if table.requires_grad or u.requires_grad or v.requires_grad:
            return BackgroundLookup.apply(table, u, v, first, sizes)
        return BackgroundLookup.logits(table, u, v, first, sizes)

    def shared_table(self, directions: Tensor) -> Tensor | None:
        """The :meth:`texel_table` that lookups at ``directions`` (their device and float type) would read, for a
        caller to hand to several of them; None where the kernels do not apply (the lookups read the maps)."""
        return self.texel_table() if self._kernels_apply(directions) else None

    def _kernels_apply(self, samples: Tensor) -> bool:
        """Whether the numba kernels look up samples like ``samples``: CPU tensors of the maps' float type, float32
        or float64, numba installed."""
        return kernels_take("rtsplat.model.background_kernels", samples, *self.maps)

    def texel_table(self) -> Tensor:
        """Every level's texels [3, T] (channel-major, level after level), differentiable where autograd is on:
        what the kernels read. Built on every lookup that is not handed one (~2 MB for the default levels, a few
        tenths of a millisecond): a kept table could not tell when the maps change, since the trainer's fused
        Adam step updates them without moving their version counters."""
        return torch.cat([level[0].reshape(3, -1) for level in self.maps], 1)

    def _layout(self) -> tuple[Tensor, Tensor]:
        """Each level's first column in the texel table [L] and its (H, W) [L, 2] in the maps' float type."""
        counts = [level.shape[-2] * level.shape[-1] for level in self.maps]
        first = torch.tensor([0] + counts[:-1], dtype=torch.int64).cumsum(0)
        sizes = torch.tensor([list(level.shape[-2:]) for level in self.maps], dtype=self.maps[0].dtype)
        return first, sizes


class BackgroundLookup(torch.autograd.Function):
    """The learned background's summed logits [M, 3] on the CPU: ``table`` [3, T] (every level's texels,
    channel-major, level after level), samples at (``u``, ``v``) [M], ``first`` [L] and ``sizes`` [L, 2] as
    :meth:`BackgroundMap._layout` gives them. The values are those of :meth:`BackgroundMap.logits_reference`,
    bit for bit; the gradients of the table, u and v are its gradients up to rounding (summed in float64 here).
    A sample with a non-finite coordinate gives NaN, a NaN gradient of its u and v, and reads no texel."""

    @staticmethod
    def logits(table: Tensor, u: Tensor, v: Tensor, first: Tensor, sizes: Tensor,
               taps: np.ndarray | None = None, fractions: np.ndarray | None = None) -> Tensor:
        """The forward kernel's logits; ``taps`` and ``fractions`` (when given) receive what the backward reads."""
        kernels = load_numba_module("rtsplat.model.background_kernels")
        dtype = table.dtype
        out = torch.empty(u.shape[0], 3, dtype=dtype)
        consts = torch.tensor([0.0, 0.5, 1.0], dtype=dtype)
        if taps is None:
            taps = np.empty((0, 0, 4), dtype=np.int64)
            fractions = np.empty((0, 0, 2), dtype=np.float64)
        with numba_threads(SURFEL_CHUNK):
            kernels.background_logits_kernel(table.detach().contiguous().numpy(), first.numpy(), sizes.numpy(),
                                             u.detach().contiguous().numpy(), v.detach().contiguous().numpy(),
                                             consts.numpy(), out.numpy(), taps, fractions)
        return out

    @staticmethod
    def forward(ctx, table: Tensor, u: Tensor, v: Tensor, first: Tensor, sizes: Tensor) -> Tensor:
        m, n_levels = u.shape[0], first.shape[0]
        taps = np.empty((m, n_levels, 4), dtype=np.int64)
        fractions = np.empty((m, n_levels, 2), dtype=np.float64)
        data = table.detach().contiguous()
        out = BackgroundLookup.logits(data, u, v, first, sizes, taps, fractions)
        ctx.save_for_backward(data, sizes)
        ctx.taps = (taps, fractions)
        ctx.sample_dtypes = (u.dtype, v.dtype)
        return out

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad: Tensor):
        kernels = load_numba_module("rtsplat.model.background_kernels")
        table, sizes = ctx.saved_tensors
        taps, fractions = ctx.taps
        g = grad.contiguous().numpy()
        g_table = g_u = g_v = None
        if ctx.needs_input_grad[0]:
            summed = np.zeros(table.shape, dtype=np.float64)
            with numba_threads(1):  # one channel per chunk, so that the three spread over the threads
                kernels.background_table_grad_kernel(taps, fractions, g, summed)
            g_table = torch.from_numpy(summed).to(table.dtype)
        with numba_threads(SURFEL_CHUNK):
            if ctx.needs_input_grad[1] or ctx.needs_input_grad[2]:
                su = np.empty(taps.shape[0], dtype=np.float64)
                sv = np.empty(taps.shape[0], dtype=np.float64)
                kernels.background_sample_grad_kernel(table.numpy(), sizes.numpy(), taps, fractions, g, su, sv)
                g_u = torch.from_numpy(su).to(ctx.sample_dtypes[0])
                g_v = torch.from_numpy(sv).to(ctx.sample_dtypes[1])
        return g_table, g_u, g_v, None, None
