"""Training losses (METHOD.md section 5). Images are [H,W,C] tensors in [0,1]."""

from __future__ import annotations

import functools

import torch
import torch.nn.functional as F
from torch import Tensor

from rtsplat.camera import Camera


@functools.lru_cache(maxsize=8)
def _gaussian_taps(size: int, sigma: float, device: str, dtype: torch.dtype) -> Tensor:
    """Normalised 1D Gaussian [size]; the 2D SSIM window is its outer product."""
    x = torch.arange(size, dtype=torch.float64) - (size - 1) / 2
    g = torch.exp(-(x * x) / (2 * sigma * sigma))
    return (g / g.sum()).to(device=device, dtype=dtype)


def ssim_map(a: Tensor, b: Tensor, window: int = 11, sigma: float = 1.5) -> Tensor:
    """Per-pixel SSIM [H,W,C] of the 3DGS loss: Gaussian window 11 / 1.5, C1 = 0.01^2, C2 = 0.03^2,
    zero padding ("same" convolution), data range 1.

    The five local moments (means of a, b, a^2, b^2, ab) are one batched separable blur: a column
    pass then a row pass of the 1D Gaussian, which equals the 2D window with zero padding (the
    window is the outer product of the 1D taps and the padding is zero in both passes)."""
    C = a.shape[-1]
    g = _gaussian_taps(window, sigma, str(a.device), a.dtype)
    x, y = a.permute(2, 0, 1), b.permute(2, 0, 1)
    stack = torch.cat([x, y, x * x, y * y, x * y])[None]  # [1, 5C, H, W]
    k = stack.shape[1]
    pad = window // 2
    blurred = F.conv2d(stack, g.reshape(1, 1, window, 1).expand(k, 1, window, 1), padding=(pad, 0), groups=k)
    blurred = F.conv2d(blurred, g.reshape(1, 1, 1, window).expand(k, 1, 1, window), padding=(0, pad), groups=k)
    mu_x, mu_y, exx, eyy, exy = blurred[0].split(C)
    sxx = exx - mu_x * mu_x
    syy = eyy - mu_y * mu_y
    sxy = exy - mu_x * mu_y
    c1, c2 = 0.01**2, 0.03**2
    value = ((2 * mu_x * mu_y + c1) * (2 * sxy + c2)) / ((mu_x**2 + mu_y**2 + c1) * (sxx + syy + c2))
    return value.permute(1, 2, 0)


def ssim(a: Tensor, b: Tensor) -> Tensor:
    return ssim_map(a, b).mean()


def masked_mean(value: Tensor, weight: Tensor | None) -> Tensor:
    """Mean of ``value`` [H,W,C] weighted by ``weight`` [H,W,1] (plain mean when None)."""
    if weight is None:
        return value.mean()
    w = weight.expand_as(value)
    return (value * w).sum() / w.sum().clamp_min(1e-8)


def image_loss(render: Tensor, target: Tensor, ssim_weight: float = 0.2, weight: Tensor | None = None) -> Tensor:
    """(1 - w) L1 + w (1 - SSIM), optionally restricted to pixels where ``weight`` is 1."""
    l1 = masked_mean((render - target).abs(), weight)
    d_ssim = masked_mean(1.0 - ssim_map(render, target), weight)
    return (1.0 - ssim_weight) * l1 + ssim_weight * d_ssim


def psnr(a: Tensor, b: Tensor, weight: Tensor | None = None) -> Tensor:
    mse = masked_mean((a - b) ** 2, weight)
    return -10.0 * torch.log10(mse.clamp_min(1e-10))


def depth_to_points(depth: Tensor, camera: Camera) -> Tensor:
    """World points [H,W,3] of a camera-z depth map [H,W,1] (pixel centres at +0.5)."""
    H, W = depth.shape[:2]
    dtype, device = depth.dtype, depth.device
    ys = torch.arange(H, dtype=dtype, device=device) + 0.5
    xs = torch.arange(W, dtype=dtype, device=device) + 0.5
    yy, xx = torch.meshgrid(ys, xs, indexing="ij")
    pix = torch.stack([xx, yy, torch.ones_like(xx)], -1)
    cam = (pix @ torch.linalg.inv(camera.K.to(dtype)).T) * depth
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


def transparent_mask_loss(blended_opacity: Tensor, mask: Tensor) -> Tensor:
    """BCE(blended opacity, 1 - M): see-through pixels (M = 1) want a clear first surface."""
    p = blended_opacity.clamp(1e-6, 1 - 1e-6)
    return F.binary_cross_entropy(p, 1.0 - mask.to(p.dtype))
