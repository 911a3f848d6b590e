"""A small RT-Splatting model and random G-buffer inputs for tests of the specular branch (``RTModel._specular``)."""

from __future__ import annotations

import torch

from rtsplat.camera import Camera
from rtsplat.model.rtmodel import ActiveEffects, RTModel
from rtsplat.model.settings import ModelSettings
from rtsplat.model.surfels import init_from_points


def small_specular_model(seed: int = 3) -> RTModel:
    """Twenty surfels, an 8x16 environment map of random features and a 16-wide specular network."""
    g = torch.Generator().manual_seed(seed)
    surfels = init_from_points(torch.randn(20, 3, generator=g), torch.rand(20, 3, generator=g), generator=g)
    model = RTModel(surfels, effects=ActiveEffects(), settings=ModelSettings(env_height=8, env_width=16,
                                                                            env_levels=3, mlp_width=16))
    with torch.no_grad():
        model.env.features.copy_(torch.randn(model.env.features.shape, generator=g))  # in logical order
    return model


def specular_inputs(height: int, width: int, seed: int = 5):
    """A camera, a blended normal [H,W,3], alpha [H,W,1], a G-buffer (roughness, material, reflectance) that
    require gradients, and the shaded pixels [H,W,1] (about 60%)."""
    g = torch.Generator().manual_seed(seed)
    K = torch.tensor([[30.0, 0, width / 2], [0, 30.0, height / 2], [0, 0, 1]])
    camera = Camera(K, torch.eye(4), width, height)
    normal = torch.nn.functional.normalize(torch.randn(height, width, 3, generator=g), dim=-1).requires_grad_()
    alpha = torch.rand(height, width, 1, generator=g) + 0.1
    gbuf = {"roughness": (torch.rand(height, width, 1, generator=g) * alpha).requires_grad_(),
            "material": torch.randn(height, width, 4, generator=g).requires_grad_(),
            "reflectance": (torch.rand(height, width, 1, generator=g) * alpha).requires_grad_()}
    shade = torch.rand(height, width, 1, generator=g) > 0.4
    return camera, normal, alpha, gbuf, shade
