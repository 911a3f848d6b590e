"""Trainable surfel parameters (raw, unconstrained) and their activations (METHOD.md section 1)."""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from rtsplat.model.sh import num_coefficients, rgb_to_sh_dc

# raw parameter names; this order is the order of the optimizer groups
PARAMETERS = (
    "means", "quats", "log_scales", "occupancy_logit", "opacity_logit", "sh_dc", "sh_rest",
    "scatter_logit", "transmissivity_logit", "roughness_logit", "material_raw", "reflectance_logit",
)


def logit(p: float) -> float:
    p = min(max(p, 1e-6), 1 - 1e-6)
    return math.log(p / (1 - p))


class SurfelParameters(nn.Module):
    """All per-surfel tensors as ``nn.Parameter`` rows (one row per surfel)."""

    def __init__(self, tensors: dict[str, Tensor]):
        super().__init__()
        missing = set(PARAMETERS) - set(tensors)
        if missing:
            raise ValueError(f"missing surfel parameters: {sorted(missing)}")
        for name in PARAMETERS:
            self.register_parameter(name, nn.Parameter(tensors[name].contiguous()))

    def __len__(self) -> int:
        return self.means.shape[0]

    @property
    def sh_degree(self) -> int:
        return int(round(math.sqrt(self.sh_rest.shape[1] + 1))) - 1

    # -- activations -------------------------------------------------------------------------
    @property
    def scales(self) -> Tensor:
        return torch.exp(self.log_scales)

    @property
    def occupancy(self) -> Tensor:
        return torch.sigmoid(self.occupancy_logit)

    @property
    def opacity(self) -> Tensor:
        return torch.sigmoid(self.opacity_logit)

    @property
    def scatter(self) -> Tensor:
        return torch.sigmoid(self.scatter_logit)

    @property
    def transmissivity(self) -> Tensor:
        return torch.sigmoid(self.transmissivity_logit)

    @property
    def roughness(self) -> Tensor:
        return torch.sigmoid(self.roughness_logit)

    @property
    def material(self) -> Tensor:
        return torch.tanh(self.material_raw)

    @property
    def reflectance(self) -> Tensor:
        return torch.sigmoid(self.reflectance_logit)

    @property
    def sh(self) -> Tensor:
        return torch.cat([self.sh_dc, self.sh_rest], 1)

    def tensors(self) -> dict[str, Tensor]:
        return {name: getattr(self, name) for name in PARAMETERS}


def nearest_neighbour_scale(points: Tensor, k: int = 3, chunk: int = 4096) -> Tensor:
    """RMS distance to the ``k`` nearest other points (the 3DGS initial scale), chunked."""
    n = points.shape[0]
    if n <= 1:
        return torch.full((n,), 0.01, dtype=points.dtype, device=points.device)
    k = min(k, n - 1)
    out = []
    for start in range(0, n, chunk):
        d2 = torch.cdist(points[start : start + chunk], points).square()
        d2[torch.arange(d2.shape[0]), torch.arange(start, start + d2.shape[0])] = float("inf")
        out.append(d2.topk(k, largest=False).values.mean(-1))
    return torch.cat(out).clamp_min(1e-7).sqrt()


def point_cloud_normals(points: Tensor, k: int = 16, chunk: int = 4096) -> Tensor:
    """Unit normals [N,3] of a point cloud [N,3]: per point, the direction of least spread of its ``k``
    nearest points (itself included), the smallest principal axis of their covariance. The sign is
    arbitrary (a surfel faces every camera). Fewer than 3 points: the z axis."""
    n = points.shape[0]
    if n < 3:
        return torch.tensor([0.0, 0.0, 1.0], dtype=points.dtype, device=points.device).expand(n, 3).clone()
    k = min(k, n)
    out = []
    for start in range(0, n, chunk):
        nearest = torch.cdist(points[start : start + chunk], points).topk(k, largest=False).indices
        neighbours = points[nearest]  # [c, k, 3]
        centred = neighbours - neighbours.mean(1, keepdim=True)
        covariance = centred.transpose(1, 2) @ centred
        out.append(torch.linalg.eigh(covariance.double()).eigenvectors[:, :, 0].to(points.dtype))
    return torch.cat(out)


def scatter_points(xyz: Tensor, rgb: Tensor, copies: int, generator: torch.Generator | None = None
                   ) -> tuple[Tensor, Tensor]:
    """Each point [N,3] followed by ``copies - 1`` more drawn around it: offsets from a normal
    distribution of standard deviation half the point's :func:`nearest_neighbour_scale`, colours copied.
    Returns ([N * copies, 3], [N * copies, 3]); ``copies`` 1 returns the points unchanged."""
    if copies <= 1 or xyz.shape[0] == 0:
        return xyz, rgb
    sigma = 0.5 * nearest_neighbour_scale(xyz)
    offsets = torch.randn(copies - 1, *xyz.shape, generator=generator, dtype=xyz.dtype) * sigma[:, None]
    extra = (xyz[None] + offsets.to(xyz.device)).reshape(-1, 3)
    return torch.cat([xyz, extra]), torch.cat([rgb, rgb.repeat(copies - 1, 1)])


def quats_with_normal(normals: Tensor) -> Tensor:
    """Unit quaternions (wxyz) of the rotations that take the z axis, the surfel normal, to ``normals``
    [N,3] (the shortest such rotation; a half turn about x for ``-z``)."""
    n = F.normalize(normals, dim=-1)
    q = torch.stack([1.0 + n[:, 2], -n[:, 1], n[:, 0], torch.zeros_like(n[:, 0])], -1)
    flipped = q[:, 0] < 1e-6
    q[flipped] = torch.tensor([0.0, 1.0, 0.0, 0.0], dtype=q.dtype)
    return F.normalize(q, dim=-1)


def concat_surfels(parts: list[SurfelParameters]) -> SurfelParameters:
    """One parameter set with the rows of ``parts`` in order."""
    return SurfelParameters({name: torch.cat([getattr(p, name).detach() for p in parts]) for name in PARAMETERS})


def init_from_points(
    xyz: Tensor, rgb: Tensor, *, sh_degree: int = 3, occupancy: float = 0.1, opacity: float = 0.5,
    transmissivity: float = 0.5, roughness: float = 0.1, reflectance: float = 0.5,
    generator: torch.Generator | None = None, normals: Tensor | None = None,
) -> SurfelParameters:
    """Surfels at the SfM points: colours from the points, scales from neighbour distances.

    ``rgb`` in [0,1]. Rotations turn each surfel's normal onto ``normals`` [N,3], or are random (as in
    2DGS) without them; the random rotations are drawn either way, so that ``generator`` gives the same
    later draws. The material feature starts small and random so that the specular network sees
    distinct inputs.
    """
    n = xyz.shape[0]
    dtype = torch.float32
    xyz = xyz.to(dtype)
    scale = nearest_neighbour_scale(xyz)
    quats = F.normalize(torch.rand(n, 4, generator=generator, dtype=dtype), dim=-1)
    if normals is not None:
        quats = quats_with_normal(normals.to(dtype))
    full = lambda value, *shape: torch.full((n, *shape), value, dtype=dtype)  # noqa: E731
    tensors = {
        "means": xyz.clone(),
        "quats": quats,
        "log_scales": torch.log(scale)[:, None].repeat(1, 2),
        "occupancy_logit": full(logit(occupancy)),
        "opacity_logit": full(logit(opacity)),
        "sh_dc": rgb_to_sh_dc(rgb.to(dtype).clamp(0, 1))[:, None, :],
        "sh_rest": torch.zeros(n, num_coefficients(sh_degree) - 1, 3, dtype=dtype),
        "scatter_logit": torch.logit(rgb.to(dtype).clamp(0.02, 0.98)),
        "transmissivity_logit": full(logit(transmissivity)),
        "roughness_logit": full(logit(roughness)),
        "material_raw": 0.1 * torch.randn(n, 4, generator=generator, dtype=dtype),
        "reflectance_logit": full(logit(reflectance)),
    }
    return SurfelParameters(tensors)
