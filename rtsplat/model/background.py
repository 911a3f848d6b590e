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

import torch
from torch import Tensor, nn

from rtsplat.model.envmap import EnvironmentMap
from rtsplat.raster.numba_runtime import SURFEL_CHUNK, load_numba_module, numba_threads

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
        """RGB [..., 3] in (0, 1) at unit ``directions`` [..., 3]. Without autograd, on CPU tensors of one
        float type, the levels are sampled and summed by one numba kernel
        (:mod:`rtsplat.model.background_kernels`: the same operations, so the same bits, in a fraction
        of the time of the torch ops' passes over every sample); elsewhere, or without numba, by torch."""
        flat = directions.reshape(-1, 3)
        u, v = EnvironmentMap.direction_to_uv(flat)
        logits = None if torch.is_grad_enabled() else self._logits_by_kernel(u, v)
        if logits is None:
            logits = sum(EnvironmentMap.sample_level(level, u, v) for level in self.maps)
        return torch.sigmoid(logits).reshape(*directions.shape[:-1], 3)

    def _logits_by_kernel(self, u: Tensor, v: Tensor) -> Tensor | None:
        """The summed logits [M, 3] at (u, v) from the numba kernel; None where it does not apply."""
        dtype = self.maps[0].dtype
        if (u.device.type != "cpu" or u.dtype != dtype or dtype not in (torch.float32, torch.float64)
                or any(level.dtype != dtype or level.device.type != "cpu" for level in self.maps)):
            return None
        kernels = load_numba_module("rtsplat.model.background_kernels")
        if kernels is None:
            return None
        table, first, sizes = self._texel_table()
        out = torch.empty(u.shape[0], 3, dtype=dtype)
        consts = torch.tensor([0.0, 0.5, 1.0], dtype=dtype)
        with numba_threads(SURFEL_CHUNK):
            kernels.background_logits_kernel(table.numpy(), first.numpy(), sizes.numpy(), u.contiguous().numpy(),
                                             v.contiguous().numpy(), consts.numpy(), out.numpy())
        return out

    def _texel_table(self) -> tuple[Tensor, Tensor, Tensor]:
        """Every level's texels [3, T] (channel-major, level after level), each level's first column [L] and
        its (H, W) [L, 2]. Built on every call (~2 MB for the default levels, well under a millisecond):
        a kept table could not tell when the maps change, since the trainer's fused Adam step updates them
        without moving their version counters."""
        columns = [level.detach()[0].reshape(3, -1) for level in self.maps]
        starts = torch.tensor([0] + [c.shape[1] for c in columns[:-1]], dtype=torch.int64).cumsum(0)
        sizes = torch.tensor([list(level.shape[-2:]) for level in self.maps], dtype=self.maps[0].dtype)
        return torch.cat(columns, 1).contiguous(), starts, sizes
