"""A small RT-Splatting model and random G-buffer inputs for tests of the specular branch (``RTModel._specular``),
and a toy trainer whose training renders are recorded."""

from __future__ import annotations

from pathlib import Path

import torch

from rtsplat.bench.toy_scene import write_scene
from rtsplat.camera import Camera
from rtsplat.model.rtmodel import ActiveEffects, RTModel
from rtsplat.model.settings import ModelSettings
from rtsplat.model.surfels import init_from_points
from rtsplat.train.trainer import Trainer
from rtsplat.train_config import TrainConfig


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


def recorded_toy_training(tmp_path: Path, iterations: int, schedule: dict) -> tuple[Trainer, list[dict], dict]:
    """A toy glass scene trained ``iterations`` iterations (the full stage from iteration 3) with the extra
    ``schedule`` settings; returns the trainer, the keyword arguments of every render made with autograd (the
    training renders, in order) and the run's summary."""
    scene = write_scene(tmp_path / "scene", views=6, width=32, height=24)
    cfg = TrainConfig.from_dict({
        "schedule": {"iterations": iterations, "volume_until": 1, "specular_from": 2, "densify_from": 100,
                     "reset_every": 0, "log_every": 5, "checkpoint_every": 0, **schedule},
        "model": {"env_height": 16, "env_width": 32, "env_levels": 3, "mlp_width": 32},
    })
    trainer = Trainer(scene, cfg, tmp_path / "run", progress=False, log=lambda m: None)
    calls, render = [], trainer.model.render

    def recording(camera, **kwargs):
        if torch.is_grad_enabled():
            calls.append(kwargs)
        return render(camera, **kwargs)

    trainer.model.render = recording
    return trainer, calls, trainer.train()
