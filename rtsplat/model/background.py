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
        """RGB [..., 3] in (0, 1) at unit ``directions`` [..., 3]."""
        flat = directions.reshape(-1, 3)
        u, v = EnvironmentMap.direction_to_uv(flat)
        logits = sum(EnvironmentMap.sample_level(level, u, v) for level in self.maps)
        return torch.sigmoid(logits).reshape(*directions.shape[:-1], 3)
