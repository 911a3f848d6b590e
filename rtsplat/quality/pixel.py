"""PSNR and SSIM of [H,W,C] images in [0,1] (METHOD.md section 7), optionally over a weighted region."""

from __future__ import annotations

import functools

import torch
import torch.nn.functional as F
from torch import Tensor


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


def psnr(a: Tensor, b: Tensor, weight: Tensor | None = None) -> Tensor:
    """``-10 log10(MSE)``; with ``weight`` [H,W,1] the MSE averages the weighted pixels (all channels)."""
    mse = masked_mean((a - b) ** 2, weight)
    return -10.0 * torch.log10(mse.clamp_min(1e-10))
