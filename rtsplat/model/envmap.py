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
    def _sample_level(level: Tensor, u: Tensor, v: Tensor) -> Tensor:
        """Bilinear sample [M,C] of one level with longitude wrap-around."""
        _, C, H, W = level.shape
        padded = torch.cat([level[..., -1:], level, level[..., :1]], -1)  # one column each side
        # texel centres of the unpadded map are at (j + 0.5) / W; in the padded map at (j + 1.5)/(W + 2)
        gx = ((u * W + 1.0) / (W + 2)) * 2 - 1
        gy = v * 2 - 1
        grid = torch.stack([gx, gy], -1).reshape(1, 1, -1, 2)
        out = F.grid_sample(padded, grid, mode="bilinear", padding_mode="border", align_corners=False)
        return out.reshape(C, -1).T

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
                out = out + w * self._sample_level(tex, u, v)
        return out
