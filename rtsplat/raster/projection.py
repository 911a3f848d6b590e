"""Per-surfel projection of 2D Gaussian surfels (2DGS, Huang et al. 2024).

A surfel with centre p, rotation R = [t_u, t_v, n] and scales (s_u, s_v) maps its local plane
coordinates (u, v) to the world point p + u s_u t_u + v s_v t_v. Composed with the camera
(K [R_cw | t_cw]) this is a 3x3 projective map, the *ray transform* M:

    [x w, y w, w]^T = M [u, v, 1]^T,   M = K [R_cw s_u t_u | R_cw s_v t_v | R_cw p + t_cw]

(columns: image of the two tangent axes and of the centre, in homogeneous pixel coordinates).
The rows of M are therefore "image x", "image y" and "camera depth" as linear functions of
(u, v, 1). gsplat's ``ray_transforms`` are the same matrices.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor

from rtsplat.camera import Camera
from rtsplat.raster.types import RasterSettings, Surfels


def quat_to_rotmat(quats: Tensor) -> Tensor:
    """(w, x, y, z) quaternions [N,4] -> rotation matrices [N,3,3]; normalised first."""
    w, x, y, z = F.normalize(quats, dim=-1, eps=1e-12).unbind(-1)
    return torch.stack(
        [
            1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
        ],
        dim=-1,
    ).reshape(quats.shape[:-1] + (3, 3))


@dataclass
class Projection:
    ray_transform: Tensor  # [N,3,3] M as in the module docstring (rows: x w, y w, w)
    centers: Tensor  # [N,2] projected centres in pixels (screen probe included)
    depths: Tensor  # [N] camera-space z of the centres
    normals: Tensor  # [N,3] world-space normals, flipped to face the camera
    bbox_min: Tensor  # [N,2] screen-space box (px, corner origin), no grad
    bbox_max: Tensor  # [N,2]
    radii: Tensor  # [N,2] int32 half extents of the box, 0 when culled
    valid: Tensor  # [N] bool: centre beyond the near plane and box overlaps the image


def ellipse_screen_box(ray_transform: Tensor, cutoff: float) -> tuple[Tensor, Tensor, Tensor]:
    """Tight screen-space box of the projected ellipse u^2 + v^2 = cutoff^2 (2DGS ``compute_aabb``).

    Returns (box centre [N,2], half extent [N,2], bounded [N]). ``bounded`` is False when the
    ellipse reaches the camera plane (w <= 0), where its projection is unbounded.
    The tangent lines x = c of the projected conic solve a quadratic whose coefficients are
    entries of the dual conic M diag(c^2, c^2, -1) M^T.
    """
    f = ray_transform.new_tensor([cutoff * cutoff, cutoff * cutoff, -1.0])
    row_x, row_y, row_w = ray_transform.unbind(-2)
    d = (f * row_w * row_w).sum(-1)  # dual conic (w, w)
    bounded = d < 0
    d_safe = torch.where(bounded, d, torch.full_like(d, -1.0))
    center = torch.stack([(f * row_x * row_w).sum(-1), (f * row_y * row_w).sum(-1)], -1) / d_safe[:, None]
    second = torch.stack([(f * row_x * row_x).sum(-1), (f * row_y * row_y).sum(-1)], -1) / d_safe[:, None]
    extent = torch.sqrt((center * center - second).clamp_min(1e-4))
    return center, extent, bounded


def project_surfels(
    surfels: Surfels, camera: Camera, settings: RasterSettings, screen_probe: Tensor | None = None
) -> Projection:
    R_cw, t_cw, K = camera.rotation, camera.translation, camera.K
    rot = quat_to_rotmat(surfels.quats)  # columns: t_u, t_v, n (world)
    means_cam = surfels.means @ R_cw.T + t_cw
    axes_cam = R_cw @ rot  # [N,3,3]
    tangent_u = axes_cam[..., 0] * surfels.scales[:, :1]
    tangent_v = axes_cam[..., 1] * surfels.scales[:, 1:2]
    center_h = means_cam @ K.T  # (x w, y w, w) of the centre
    depths = means_cam[:, 2]
    if screen_probe is not None:
        # shift the projected centre by the probe (in pixels): d(x w) = dx * w
        center_h = center_h + torch.cat([screen_probe * depths[:, None], torch.zeros_like(depths[:, None])], 1)
    M = torch.stack([tangent_u @ K.T, tangent_v @ K.T, center_h], dim=-1)  # columns

    depth_safe = torch.where(depths.abs() > 1e-12, depths, torch.ones_like(depths))
    centers = center_h[:, :2] / depth_safe[:, None]

    normals_world = rot[..., 2]
    facing_away = (axes_cam[..., 2] * means_cam).sum(-1) > 0
    normals = torch.where(facing_away[:, None], -normals_world, normals_world)

    with torch.no_grad():
        box_center, extent, bounded = ellipse_screen_box(M.detach(), settings.extent_sigma)
        extent = extent.clamp_min(settings.lowpass_radius)
        W, H = camera.width, camera.height
        full_min = box_center.new_tensor([0.0, 0.0]).expand_as(box_center)
        full_max = box_center.new_tensor([float(W), float(H)]).expand_as(box_center)
        bbox_min = torch.where(bounded[:, None], box_center - extent, full_min)
        bbox_max = torch.where(bounded[:, None], box_center + extent, full_max)
        finite = torch.isfinite(bbox_min).all(-1) & torch.isfinite(bbox_max).all(-1)
        overlaps = (bbox_max[:, 0] > 0) & (bbox_min[:, 0] < W) & (bbox_max[:, 1] > 0) & (bbox_min[:, 1] < H)
        valid = (depths.detach() > settings.near) & finite & overlaps
        radii = torch.where(
            bounded[:, None], torch.ceil(extent), extent.new_tensor([float(W), float(H)]).expand_as(extent)
        )
        radii = torch.where(valid[:, None], radii, torch.zeros_like(radii)).to(torch.int32)
    return Projection(M, centers, depths, normals, bbox_min, bbox_max, radii, valid)
