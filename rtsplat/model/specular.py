"""Specular shading network (Ref-GS style): environment feature x material feature -> C_spec, beta."""

from __future__ import annotations

import math

import torch
from torch import Tensor, nn

LOG_HALF = math.log(0.5)
MAX_LOG_SPECULAR = 8.0  # exp() argument cap: keeps C_spec finite under any learning rate


class SpecularNetwork(nn.Module):
    """Input: outer product of the env feature (C) and the blended material feature (4), flattened,
    concatenated with the env feature: C*4 + C (= 80 for C = 16). MLP 80 -> 256 -> 256 -> 4.
    The model may append channels to the env feature (:class:`rtsplat.model.settings.ModelSettings`:
    the angle of incidence, the background at the reflected direction); C counts them."""

    def __init__(self, env_channels: int = 16, material_channels: int = 4, width: int = 256):
        super().__init__()
        in_dim = env_channels * material_channels + env_channels
        self.mlp = nn.Sequential(
            nn.Linear(in_dim, width), nn.ReLU(), nn.Linear(width, width), nn.ReLU(), nn.Linear(width, 4)
        )

    def forward(self, env_features: Tensor, material: Tensor, reflectance: Tensor) -> tuple[Tensor, Tensor]:
        """[M,C], [M,4] (unit), [M,1] -> (C_spec [M,3], beta [M,1])."""
        outer = (env_features[:, :, None] * material[:, None, :]).flatten(1)
        out = self.mlp(torch.cat([outer, env_features], -1))
        specular = torch.exp((out[:, :3] + LOG_HALF).clamp_max(MAX_LOG_SPECULAR)) * reflectance
        beta = torch.sigmoid(out[:, 3:4])
        return specular, beta
