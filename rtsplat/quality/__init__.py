"""Image quality: PSNR and SSIM (:mod:`rtsplat.quality.pixel`) and LPIPS-VGG
(:mod:`rtsplat.quality.lpips`). The trainer's losses and ``rtsplat metrics`` both use these; the
package imports nothing else from rtsplat."""

from rtsplat.quality.pixel import masked_mean, psnr, ssim, ssim_map

__all__ = ["masked_mean", "psnr", "ssim", "ssim_map"]
