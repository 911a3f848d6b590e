"""Trainable surfel parameters (raw, unconstrained) and their activations (METHOD.md section 1)."""

from __future__ import annotations

import math

import numpy as np
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

    def tensors(self) -> dict[str, Tensor]:
        return {name: getattr(self, name) for name in PARAMETERS}


QUERY_CHUNK = 65_536  # query points per k-d tree query and per batch of covariance eigensolves


def _tree_workers() -> int:
    """Threads of the k-d tree queries: torch's (``OMP_NUM_THREADS``, which Snakemake sets to a job's threads)."""
    return max(1, torch.get_num_threads())


def nearest_neighbours(points: Tensor, k: int, queries: Tensor | None = None, chunk: int = QUERY_CHUNK
                       ) -> tuple[np.ndarray, np.ndarray]:
    """Distances and indices [M,k] (nearest first, float64 and int64 numpy arrays) of the ``k`` points of
    ``points`` [N,3] nearest to each of ``queries`` [M,3] (default: the points themselves, each its own
    nearest), found in a k-d tree (:class:`scipy.spatial.cKDTree`) in chunks of ``chunk`` queries:
    O((N + M k) log N) time, and memory for the tree and the results, O(N + M k). Among points at equal
    distance, which ones fill the last places is the tree's choice. Needs ``1 <= k <= N``."""
    from scipy.spatial import cKDTree

    xyz = points.detach().cpu().double().numpy()
    at = xyz if queries is None else queries.detach().cpu().double().numpy()
    tree = cKDTree(xyz)
    distances = np.empty((at.shape[0], k))
    indices = np.empty((at.shape[0], k), dtype=np.int64)
    for start in range(0, at.shape[0], chunk):
        d, i = tree.query(at[start:start + chunk], k=[*range(1, k + 1)], workers=_tree_workers())
        distances[start:start + chunk], indices[start:start + chunk] = d, i
    return distances, indices


def nearest_neighbour_scale(points: Tensor, k: int = 3) -> Tensor:
    """RMS distance to the ``k`` nearest other points (the 3DGS initial scale): coincident points count
    (at distance 0), at least sqrt(1e-7). One point: 0.01."""
    n = points.shape[0]
    if n <= 1:
        return torch.full((n,), 0.01, dtype=points.dtype, device=points.device)
    k = min(k, n - 1)
    # each point is among its own k + 1 nearest at distance 0 (a coincident one may be listed in its
    # place: the distances are the same), so the first column is the point itself
    distances, _ = nearest_neighbours(points, k + 1)
    mean_square = np.square(distances[:, 1:]).mean(1)
    return torch.from_numpy(mean_square).clamp_min(1e-7).sqrt().to(dtype=points.dtype, device=points.device)


def point_cloud_normals(points: Tensor, k: int = 16, queries: Tensor | None = None, chunk: int = QUERY_CHUNK
                        ) -> Tensor:
    """Unit normals [M,3] at ``queries`` [M,3] (default: at the points) of the point cloud ``points``
    [N,3]: per query, the direction of least spread of its ``k`` nearest points of the cloud (a point
    itself included), the smallest principal axis of their covariance. The sign is arbitrary (a
    surfel faces every camera). Fewer than 3 points: the z axis. Neighbours from
    :func:`nearest_neighbours`; the eigensolves run ``chunk`` at a time."""
    at = points if queries is None else queries
    n = points.shape[0]
    if n < 3:
        return torch.tensor([0.0, 0.0, 1.0], dtype=at.dtype, device=at.device).expand(at.shape[0], 3).clone()
    k = min(k, n)
    _, nearest = nearest_neighbours(points, k, queries, chunk)
    xyz = points.detach().cpu().double()
    out = []
    for start in range(0, nearest.shape[0], chunk):
        neighbours = xyz[torch.from_numpy(nearest[start:start + chunk])]  # [c, k, 3]
        centred = neighbours - neighbours.mean(1, keepdim=True)
        covariance = centred.transpose(1, 2) @ centred
        out.append(torch.linalg.eigh(covariance).eigenvectors[:, :, 0])
    normals = torch.cat(out) if out else torch.zeros(0, 3, dtype=torch.float64)
    return normals.to(dtype=at.dtype, device=at.device)


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
    generator: torch.Generator | None = None, normals: Tensor | None = None, scale_factor: float = 1.0,
) -> SurfelParameters:
    """Surfels at the SfM points: colours from the points, scales from neighbour distances (times
    ``scale_factor``).

    ``rgb`` in [0,1]. Rotations turn each surfel's normal onto ``normals`` [N,3], or are random (as in
    2DGS) without them; the random rotations are drawn either way, so that ``generator`` gives the same
    later draws. The material feature starts small and random so that the specular network sees
    distinct inputs.
    """
    n = xyz.shape[0]
    dtype = torch.float32
    xyz = xyz.to(dtype)
    scale = nearest_neighbour_scale(xyz) * scale_factor
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
