"""Learnable equirectangular environment *feature* map with mip levels (Ref-GS "Sph-Mip").

Sampled at a direction with trilinear filtering: bilinear inside two adjacent mip levels,
linear between them; the mip level is ``roughness * levels``. Longitude wraps around (the map
is padded circularly before sampling); latitude is clamped at the poles. Written in torch
(``grid_sample``) instead of nvdiffrast.

Direction convention: world z is up; longitude phi = atan2(y, x) maps to the map's columns,
colatitude theta = acos(z) to its rows (row 0 = +z).
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import Tensor, nn


class EnvironmentMap(nn.Module):
    def __init__(self, channels: int = 16, height: int = 512, width: int = 1024, levels: int = 9):
        super().__init__()
        self.levels = int(levels)
        self.features = nn.Parameter(torch.zeros(1, channels, height, width))

    @property
    def channels(self) -> int:
        return self.features.shape[1]

    def pyramid(self) -> list[Tensor]:
        """Mip levels, each half the previous size (2x2 average), at least 1x2."""
        levels = [self.features]
        for _ in range(self.levels - 1):
            top = levels[-1]
            if top.shape[-2] < 2 or top.shape[-1] < 4:
                levels.append(top)
                continue
            levels.append(F.avg_pool2d(top, 2, ceil_mode=True))
        return levels

    @staticmethod
    def direction_to_uv(directions: Tensor) -> tuple[Tensor, Tensor]:
        """Unit directions [M,3] -> (u in [0,1) longitude, v in [0,1] colatitude)."""
        x, y, z = directions.unbind(-1)
        phi = torch.atan2(y, x)  # (-pi, pi]
        u = (phi + math.pi) / (2 * math.pi)
        v = torch.acos(z.clamp(-1 + 1e-6, 1 - 1e-6)) / math.pi
        return u, v

    @staticmethod
    def sample_level(level: Tensor, u: Tensor, v: Tensor) -> Tensor:
        """Bilinear sample [M,C] of one level; longitude wraps around, colatitude clamps at the poles.

        Texel (i, j) has its centre at (u, v) = ((j + 0.5) / W, (i + 0.5) / H). Written as four
        gathers with wrapped column indices rather than ``grid_sample`` on a circularly padded copy:
        the padded copy (and its backward) costs a full pass over the map per level and iteration,
        which dominated the training step at the paper's 512x1024 map on a CPU.
        """
        _, C, H, W = level.shape
        flat = level.reshape(C, H * W)
        x = u * W - 0.5
        y = v * H - 0.5
        x0 = torch.floor(x)
        y0 = torch.floor(y)
        fx = (x - x0)[None]
        fy = (y - y0)[None]
        x0 = x0.long()
        y0 = y0.long()
        xa, xb = torch.remainder(x0, W), torch.remainder(x0 + 1, W)
        ya, yb = y0.clamp(0, H - 1), (y0 + 1).clamp(0, H - 1)

        # one gather for the four corners: its backward allocates one map-sized gradient, not four
        index = torch.cat([ya * W + xa, ya * W + xb, yb * W + xa, yb * W + xb])
        c00, c01, c10, c11 = flat.index_select(1, index).reshape(C, 4, -1).unbind(1)
        top = c00 * (1 - fx) + c01 * fx
        bottom = c10 * (1 - fx) + c11 * fx
        return (top * (1 - fy) + bottom * fy).T

    def forward(self, directions: Tensor, roughness: Tensor) -> Tensor:
        """Features [M,C] at unit ``directions`` [M,3]; ``roughness`` [M] in [0,1] picks the level."""
        u, v = self.direction_to_uv(directions)
        levels = self.pyramid()
        level = (roughness.clamp(0, 1) * (self.levels - 1)).reshape(-1)
        lo = level.floor().clamp(0, self.levels - 1)
        frac = (level - lo)[:, None]
        lo_i = lo.long()[:, None]
        out = torch.zeros(directions.shape[0], self.channels, device=directions.device, dtype=directions.dtype)
        for i, tex in enumerate(levels):
            w = torch.where(lo_i == i, 1 - frac, torch.zeros_like(frac)) + torch.where(
                lo_i + 1 == i, frac, torch.zeros_like(frac)
            )
            if bool((w > 0).any()):
                out = out + w * self.sample_level(tex, u, v)
        return out
