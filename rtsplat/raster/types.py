"""Data types of the rasterizer API: surfels in, G-buffers and volume buffers out."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import torch
from torch import Tensor

from rtsplat.schema import setting


@dataclass
class Surfels:
    """2D Gaussian surfels, already *activated* (no sigmoid/exp is applied by the rasterizer).

    means [N,3] world centres; quats [N,4] rotations (w, x, y, z; normalised internally);
    scales [N,2] extents along the two tangent axes (>= 0); occupancy [N] in [0,1] (probability a
    ray hits the surfel); opacity [N] in [0,1] (probability a hit absorbs); features [N,F] per-surfel
    surface attributes blended with the surface weights (any F, may be 0); colors [N,3] volume
    radiance blended with the volume weights.
    """

    means: Tensor
    quats: Tensor
    scales: Tensor
    occupancy: Tensor
    opacity: Tensor
    features: Tensor
    colors: Tensor

    def __post_init__(self) -> None:
        n = self.means.shape[0]
        expect = {
            "means": (n, 3), "quats": (n, 4), "scales": (n, 2), "occupancy": (n,), "opacity": (n,),
            "colors": (n, 3),
        }
        for name, shape in expect.items():
            got = tuple(getattr(self, name).shape)
            if got != shape:
                raise ValueError(f"Surfels.{name} must have shape {shape}, got {got}")
        if self.features.dim() != 2 or self.features.shape[0] != n:
            raise ValueError(f"Surfels.features must have shape (N={n}, F), got {tuple(self.features.shape)}")

    def __len__(self) -> int:
        return self.means.shape[0]

    @property
    def device(self) -> torch.device:
        return self.means.device

    @property
    def dtype(self) -> torch.dtype:
        return self.means.dtype


@dataclass(frozen=True)
class RasterSettings:
    """Constants of the 2DGS rasterizer (METHOD.md section 2). Defaults follow 2DGS."""

    tile_size: int = setting(16, help="tile edge in pixels (binning)", minimum=1)
    near: float = setting(0.2, help="near plane: per-pixel depth test and centre culling", exclusiveMinimum=0.0)
    far: float = setting(100.0, help="far plane: only maps depth to [0,1] for the distortion term",
                         exclusiveMinimum=0.0)
    alpha_max: float = setting(0.99, help="per-surfel alpha clamp", exclusiveMinimum=0.0, maximum=1.0)
    alpha_min: float = setting(1.0 / 255.0, help="contributions below this alpha are skipped", minimum=0.0,
                               exclusiveMaximum=1.0)
    transmittance_min: float = setting(
        1e-4, help="a weight set stops when its transmittance would drop below this", minimum=0.0, exclusiveMaximum=1.0
    )
    extent_sigma: float = setting(
        3.0, help="screen-space extent used for tile binning, in kernel sigmas", exclusiveMinimum=0.0
    )
    lowpass_inv_var: float = setting(
        2.0, help="low-pass filter: rho_2d = lowpass_inv_var * |centre - pixel|^2 (filter sqrt(2)/2 px)",
        exclusiveMinimum=0.0,
    )
    max_pairs_per_chunk: int = setting(
        4_000_000, help="reference backend: pixel x surfel pairs evaluated at once", minimum=1
    )

    @property
    def lowpass_radius(self) -> float:
        """Screen radius (px) that the low-pass filter alone covers at ``extent_sigma``."""
        return self.extent_sigma / math.sqrt(self.lowpass_inv_var)


@dataclass
class RasterOutput:
    """What one rasterization returns. Images are [H, W, C], channel last.

    Surface set (weights p_i = occupancy_i G_i prod_{j<i}(1 - occupancy_j G_j)):
      features [H,W,F] sum p f; normal [H,W,3] sum p n (world space, facing the camera, not
      renormalised); depth [H,W,1] expected depth sum p z / sum p; depth_median [H,W,1] depth of
      the surfel where the surface transmittance crosses 0.5; alpha [H,W,1] = sum p;
      distortion [H,W,1] 2DGS depth distortion sum_{i>j} p_i p_j (m_i - m_j)^2 (m = NDC depth).
    Volume set (weights w_i = occupancy_i opacity_i G_i prod_{j<i}(1 - occupancy_j opacity_j G_j)):
      color [H,W,3] sum w c; volume_alpha [H,W,1] = sum w; volume_depth [H,W,1] sum w z / sum w.
    Per surfel, for density control:
      means2d [N,2] projected centres (px); radii [N,2] integer screen half-extent (0 = culled);
      visible [N] bool, contributed to at least one pixel with either weight set;
      screen_probe [N,2] zero tensor added to the projected centres: after backward its ``.grad``
      is dL/d(centre in px); :meth:`densification_grad` turns it into the 2DGS signal.
    """

    features: Tensor
    normal: Tensor
    depth: Tensor
    depth_median: Tensor
    alpha: Tensor
    distortion: Tensor
    color: Tensor
    volume_alpha: Tensor
    volume_depth: Tensor
    means2d: Tensor
    radii: Tensor
    visible: Tensor
    screen_probe: Tensor | None = None
    width: int = 0
    height: int = 0
    extras: dict = field(default_factory=dict)

    def densification_grad(self) -> Tensor | None:
        """2DGS densification signal [N,2]: screen-space centre gradient in NDC units.

        2DGS scales the pixel gradient of the projected centre by (W/2, H/2); its gradient
        threshold (2e-4) is calibrated for that. None before backward or without a probe.
        """
        if self.screen_probe is None or self.screen_probe.grad is None:
            return None
        scale = self.screen_probe.new_tensor([self.width * 0.5, self.height * 0.5])
        return self.screen_probe.grad * scale
