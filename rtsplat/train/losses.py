"""Training losses (METHOD.md section 5). Images are [H,W,C] tensors in [0,1]; PSNR and SSIM come
from :mod:`rtsplat.quality`."""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

from rtsplat.camera import Camera
from rtsplat.quality import masked_mean, ssim_map


def image_loss(render: Tensor, target: Tensor, ssim_weight: float = 0.2, weight: Tensor | None = None) -> Tensor:
    """(1 - w) L1 + w (1 - SSIM), optionally restricted to pixels where ``weight`` is 1."""
    l1 = masked_mean((render - target).abs(), weight)
    d_ssim = masked_mean(1.0 - ssim_map(render, target), weight)
    return (1.0 - ssim_weight) * l1 + ssim_weight * d_ssim


def depth_to_points(depth: Tensor, camera: Camera) -> Tensor:
    """World points [H,W,3] of a camera-z depth map [H,W,1] (pixel centres at +0.5)."""
    H, W = depth.shape[:2]
    dtype, device = depth.dtype, depth.device
    ys = torch.arange(H, dtype=dtype, device=device) + 0.5
    xs = torch.arange(W, dtype=dtype, device=device) + 0.5
    yy, xx = torch.meshgrid(ys, xs, indexing="ij")
    pix = torch.stack([xx, yy, torch.ones_like(xx)], -1)
    cam = (pix @ torch.linalg.inv_ex(camera.K.to(dtype)).inverse.T) * depth  # inv_ex: no read of the device
    R, t = camera.rotation.to(dtype), camera.translation.to(dtype)
    return (cam - t) @ R  # R^T (x - t)


def depth_normals(depth: Tensor, camera: Camera) -> Tensor:
    """Normals [H,W,3] from central differences of the unprojected depth (2DGS), facing the
    camera; zero on the one-pixel border."""
    points = depth_to_points(depth, camera)
    dx = points[1:-1, 2:] - points[1:-1, :-2]
    dy = points[2:, 1:-1] - points[:-2, 1:-1]
    n = F.normalize(torch.linalg.cross(dx, dy, dim=-1), dim=-1)
    view = points[1:-1, 1:-1] - camera.center.to(depth.dtype)
    n = torch.where(((n * view).sum(-1, keepdim=True) > 0), -n, n)
    return F.pad(n.permute(2, 0, 1), (1, 1, 1, 1)).permute(1, 2, 0)


def normal_consistency(surface_normal: Tensor, depth: Tensor, alpha: Tensor, camera: Camera) -> Tensor:
    """mean((1 - n_surface . n_depth) * alpha): both normals receive gradients, as in 2DGS."""
    n_depth = depth_normals(depth, camera)
    n_surf = F.normalize(surface_normal, dim=-1)
    return ((1.0 - (n_surf * n_depth).sum(-1, keepdim=True)) * alpha.detach()).mean()


def transparent_mask_loss(blended_opacity: Tensor, mask: Tensor, surface_alpha: Tensor | None = None) -> Tensor:
    """BCE(blended opacity, target): see-through pixels (M = 1) want a clear first surface (target 0). The
    other pixels want an opaque one: target 1, or, given ``surface_alpha`` (the surface weight set's alpha,
    read without gradient), that alpha, so that a pixel which sees the background is not asked to grow a
    surface."""
    p = blended_opacity.clamp(1e-6, 1 - 1e-6)
    opaque = torch.ones_like(p) if surface_alpha is None else surface_alpha.detach().to(p.dtype).clamp(0, 1)
    return F.binary_cross_entropy(p, (1.0 - mask.to(p.dtype)) * opaque)


def mask_coverage_loss(surface_alpha: Tensor, mask: Tensor) -> Tensor:
    """Mean over the image of M * BCE(surface alpha, 1): a pixel the transparent mask marks (M = 1) is covered by
    a surface (the glass), whatever that surface lets through; 0 without marked pixels."""
    alpha = surface_alpha.clamp(1e-6, 1 - 1e-6)  # no pull on a pixel that is covered already
    return (mask.to(alpha.dtype) * -torch.log(alpha)).mean()


def shading_smoothness(shading: Tensor, alpha: Tensor, mask: Tensor) -> Tensor:
    """Mean absolute difference of the surface's shading parameters between horizontally and vertically
    neighbouring pixels that both lie in the transparent ``mask`` [H,W,1]. ``shading`` [H,W,C] is the
    alpha-weighted G-buffer (the surface pass's ``sum p f``), divided by ``alpha`` [H,W,1] here. Each pair
    weighs the smaller alpha of its two pixels (no gradient through the weight): a pixel with almost no
    surface has no shading to hold, and the gradient through the division stays bounded by 1 per pair.
    0 where no pair of neighbours is in the mask."""
    values = shading / alpha.clamp_min(1e-6)
    weight = mask.to(values.dtype) * alpha.detach().to(values.dtype).clamp(0, 1)
    pairs_x = torch.minimum(weight[:, 1:], weight[:, :-1])
    pairs_y = torch.minimum(weight[1:], weight[:-1])
    diff_x = (values[:, 1:] - values[:, :-1]).abs() * pairs_x
    diff_y = (values[1:] - values[:-1]).abs() * pairs_y
    total = (pairs_x.sum() + pairs_y.sum()) * values.shape[-1]
    return (diff_x.sum() + diff_y.sum()) / total.clamp_min(1e-6)
