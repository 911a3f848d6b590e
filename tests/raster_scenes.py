"""Scene builders shared by the rasterizer tests (plain module, imported by the test files)."""

from __future__ import annotations

import math

import torch

from rtsplat.camera import Camera, camera_from_fov
from rtsplat.raster import Surfels

SURFEL_FIELDS = ("means", "quats", "scales", "occupancy", "opacity", "features", "colors")


def small_camera(width: int = 24, height: int = 18, dtype=torch.float64, eye=(0.3, -3.0, 0.8)) -> Camera:
    return camera_from_fov(eye, (0.0, 0.0, 0.0), width=width, height=height, fov_x_deg=50.0, dtype=dtype)


def random_surfels(
    n: int,
    seed: int = 0,
    *,
    dtype=torch.float64,
    n_features: int = 2,
    spread: float = 0.6,
    scale_range: tuple[float, float] = (0.08, 0.3),
    occupancy_range: tuple[float, float] = (0.2, 0.8),
    opacity_range: tuple[float, float] = (0.2, 0.9),
) -> Surfels:
    g = torch.Generator().manual_seed(seed)

    def uniform(lo, hi, *shape):
        return lo + (hi - lo) * torch.rand(*shape, generator=g, dtype=dtype)

    return Surfels(
        means=uniform(-spread, spread, n, 3),
        quats=torch.randn(n, 4, generator=g, dtype=dtype),
        scales=uniform(*scale_range, n, 2),
        occupancy=uniform(*occupancy_range, n),
        opacity=uniform(*opacity_range, n),
        features=uniform(0.0, 1.0, n, n_features),
        colors=uniform(0.0, 1.0, n, 3),
    )


def with_grad(surfels: Surfels) -> Surfels:
    return Surfels(*[getattr(surfels, f).detach().clone().requires_grad_(True) for f in SURFEL_FIELDS])


def replace(surfels: Surfels, **changes) -> Surfels:
    values = {f: getattr(surfels, f) for f in SURFEL_FIELDS}
    values.update(changes)
    return Surfels(**values)


def facing_quat(normal, dtype=torch.float64) -> torch.Tensor:
    """A (w,x,y,z) quaternion rotating +z onto ``normal``."""
    z = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
    n = torch.as_tensor(normal, dtype=torch.float64)
    n = n / n.norm()
    axis = torch.linalg.cross(z, n)
    s = axis.norm()
    c = float(z @ n)
    if s < 1e-12:
        return torch.tensor([1.0, 0, 0, 0] if c > 0 else [0.0, 1.0, 0, 0], dtype=dtype)
    angle = math.atan2(float(s), c)
    axis = axis / s
    return torch.cat([torch.tensor([math.cos(angle / 2)]), axis * math.sin(angle / 2)]).to(dtype)
