"""The rasterizer's kernels made ready before a training run's clock starts.

The ``cpu`` backend's numba kernels compile on their first call in a process (tens of seconds on the 2-core
development machine) or load from numba's cache (about a second); Triton kernels compile on a GPU's first
call. Without a warm-up that time lands in the first training step, so the run's ``seconds`` and
``cpu_seconds`` would count it, a time budget (``schedule.seconds``) would lose it, and the first of two runs
trained side by side in a fresh checkout would look dearer or cheaper than it is. :func:`warm_up_kernels`
renders a small throwaway model of the run's settings through every stage, forward and backward, so that
every kernel a training step calls is ready; the trainer's model, optimizer and random generators are not
touched (torch's global generator is forked), so a run trains the same model with or without it.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import TYPE_CHECKING

import torch

from rtsplat.camera import pixel_rays
from rtsplat.model.rtmodel import STAGES
from rtsplat.model.surfels import init_from_points

if TYPE_CHECKING:
    from rtsplat.camera import Camera
    from rtsplat.model.surfels import SurfelParameters
    from rtsplat.train.trainer import Trainer

WARM_UP_SIDE = 32  # pixels on the long side of the warm-up camera
WARM_UP_GRID = 4  # surfels per side of each of the warm-up's two layers


@dataclass(frozen=True)
class WarmUp:
    seconds: float  # wall seconds of the warm-up
    drawn: dict[str, int]  # per stage: how many surfels the warm-up render drew (every stage draws some)


def warm_up_kernels(trainer: Trainer) -> WarmUp:
    """Render a throwaway model with ``trainer``'s settings (effects, model settings, raster settings, backend,
    device) in every stage from a small copy of its first training camera, and run the backward of every
    output, so that every kernel of a training step is compiled or loaded; returns how long it took and how
    many surfels each stage's render drew."""
    start = time.perf_counter()
    devices = [trainer.device] if trainer.device.type == "cuda" else []
    drawn = {}
    with torch.random.fork_rng(devices=devices):
        camera = trainer.train_views.cameras[0]
        camera = camera.scaled(max(1.0, max(camera.width, camera.height) / WARM_UP_SIDE))
        model = trainer.new_model(_surfels_in_view(camera, trainer.points[0], trainer.cfg.raster.near))
        for stage in STAGES:
            result = model.render(camera, stage=stage, raster_settings=trainer.cfg.raster,
                                  backend=trainer.cfg.backend)
            outputs = [result.color, *result.layers.values(), result.raster.distortion, result.raster.depth_median]
            sum(t.float().sum() for t in outputs if t.requires_grad).backward()
            drawn[stage] = int(result.raster.visible.sum())
    return WarmUp(time.perf_counter() - start, drawn)


def _surfels_in_view(camera: Camera, points: torch.Tensor, near: float) -> SurfelParameters:
    """Two layers of :data:`WARM_UP_GRID` x :data:`WARM_UP_GRID` camera-facing surfels across ``camera``'s
    image, at the median distance of the scene's ``points`` from it (and half again behind), past ``near``."""
    camera = camera.to("cpu")
    side = torch.arange(WARM_UP_GRID, dtype=torch.float32) + 0.5
    v, u = torch.meshgrid(side / WARM_UP_GRID * camera.height, side / WARM_UP_GRID * camera.width, indexing="ij")
    centre, rays = pixel_rays(camera, u.flatten(), v.flatten())
    distance = max(float((points - centre).norm(dim=-1).median()), 4.0 * near)
    xyz = torch.cat([centre + distance * rays, centre + 1.5 * distance * rays])
    normals = -torch.cat([rays, rays])
    colours = torch.linspace(0.1, 0.9, xyz.shape[0])[:, None].repeat(1, 3)
    return init_from_points(xyz, colours, occupancy=0.5, opacity=0.5, normals=normals,
                            generator=torch.Generator().manual_seed(0))
