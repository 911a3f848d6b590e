"""Triton rasterizer backend (``backend="triton"``, the default on CUDA tensors).

Same semantics as :mod:`rtsplat.raster.reference` (the oracle) and :mod:`rtsplat.raster.cpu`; only
the per-pixel compositing, the O(pixels x surfels) part, is a pair of Triton kernels
(:mod:`rtsplat.raster.triton_kernels`). Projection (:func:`project_surfels`) and tile binning with
the depth sort (:func:`bin_tiles`) are the reference's own torch code and run on the tensors'
device, so autograd carries gradients from the per-surfel projected quantities to
means/quats/scales and to the screen probe.

The compositing is one ``torch.autograd.Function`` (:class:`_Composite`):

* forward: one program per screen tile, one front-to-back walk of the tile's depth-sorted list by
  all of its pixels together; both weight sets accumulate in one walk, each stops on its own
  exactly as in the reference, and the walk ends once both sets of every pixel have stopped. It
  saves per pixel the final transmittances, the stop positions and the distortion sums;
* backward: hand written, walking each tile's list back to front (2DGS/3DGS): the transmittance
  before a surfel is recovered by dividing the saved final one, the suffix sums of the
  alpha gradients are running sums; per (tile, surfel) the pixel gradients are summed inside the
  program and added to the surfel's gradient row with one atomic add per value.

Arithmetic runs in float32, or float64 for float64 inputs; outputs and gradients come back in the
input dtype.

Devices: CUDA tensors run the compiled kernels (Triton compiles them on first use per tile size,
channel count and dtype, and caches them in ``$TRITON_CACHE_DIR``, default ``~/.triton/cache``).
CPU tensors run only in Triton's interpreter (``TRITON_INTERPRET=1`` in the environment before
triton is first imported): slow, meant for testing the kernels without a GPU
(``tests/test_raster_triton.py``); otherwise a ``ValueError`` says how to proceed.
"""

from __future__ import annotations

import contextlib
import importlib.util
import os

import torch
from torch import Tensor

from rtsplat.camera import Camera
from rtsplat.raster.binning import TileBins
from rtsplat.raster.reference import EDGE_ON_RATIO, rasterize_tiled
from rtsplat.raster.types import RasterOutput, RasterSettings, Surfels

__all__ = ["rasterize_triton", "triton_available", "kernels_interpreted"]


def triton_available() -> bool:
    """True when the ``triton`` package can be imported (without importing it)."""
    return importlib.util.find_spec("triton") is not None


def _kernels():
    if not triton_available():
        raise ValueError(
            "the 'triton' rasterizer backend needs the triton package; install it "
            "(pip install triton==3.9.0) or choose backend='cpu' / 'reference'"
        )
    from rtsplat.raster import triton_kernels

    return triton_kernels


def kernels_interpreted() -> bool:
    """True when the kernels, and the ``triton.language`` functions they call, were built for Triton's
    interpreter (``TRITON_INTERPRET=1`` when triton and the kernels were first imported)."""
    kernels = _kernels()
    import triton.language as tl
    from triton.runtime.interpreter import InterpretedFunction

    return isinstance(kernels.forward_kernel, InterpretedFunction) and isinstance(tl.zeros, InterpretedFunction)


def _check_device(device: torch.device) -> None:
    if device.type == "cuda":
        return
    if device.type == "cpu":
        if os.environ.get("TRITON_INTERPRET") == "1" and kernels_interpreted():
            return
        raise ValueError(
            "the 'triton' rasterizer backend runs on CUDA tensors; on CPU tensors it runs only in Triton's "
            "interpreter (set TRITON_INTERPRET=1 before triton is first imported in the process). "
            "For CPU rendering choose backend='cpu' (or 'auto')."
        )
    raise ValueError(f"the 'triton' rasterizer backend needs CUDA tensors, got {device}")


def _compute_dtype(dtype: torch.dtype) -> torch.dtype:
    return torch.float64 if dtype == torch.float64 else torch.float32


def _next_pow2(x: int) -> int:
    return 1 << max(int(x) - 1, 0).bit_length()


def kernel_constexprs(tile_size: int, fc: int, dtype: torch.dtype) -> dict:
    """The constexprs of both kernels: tile size, lanes (pixels rounded up to a power of two), surface
    channels rounded up to a power of two, and the Triton compute type of a torch compute dtype."""
    import triton.language as tl

    return dict(
        TILE=int(tile_size),
        PIX=_next_pow2(tile_size * tile_size),
        FCP=_next_pow2(max(fc, 1)),
        DTYPE=tl.float64 if dtype == torch.float64 else tl.float32,
    )


def compile_options(tile_size: int) -> dict:
    """Launch/compile options of both kernels.

    One warp per 32 lanes (up to 8), so that a 16x16 tile gives every thread one pixel (sm_90, float32:
    98 registers in the forward, 128 in the backward, no spills, per ptxas). No fused multiply-add:
    the backward recomputes each pair's alphas and tests with the forward's exact rounding, so it
    replays the forward's decisions (which pairs hit, where each set stopped) bit for bit.
    """
    lanes = _next_pow2(tile_size * tile_size)
    return dict(num_warps=max(1, min(8, lanes // 32)), enable_fp_fusion=False)


def _on(device: torch.device):
    """Launch on the tensors' GPU (Triton launches on the current CUDA device)."""
    return torch.cuda.device(device) if device.type == "cuda" else contextlib.nullcontext()


class _Composite(torch.autograd.Function):
    """Per-pixel compositing of both weight sets; inputs are per-surfel projected tensors."""

    @staticmethod
    def forward(ctx, M, centers, occupancy, opacity, feats, colors, bins: TileBins, geometry):
        k = _kernels()
        width, height, settings = geometry
        n, fc = M.shape[0], feats.shape[1]
        device = M.device
        cdt = _compute_dtype(M.dtype)
        inputs = tuple(
            x.detach().to(cdt).contiguous()
            for x in (M.reshape(n, 9), centers, occupancy, opacity, feats, colors)
        )
        if bins.surfel_ids.shape[0] >= 2**31 or width * height * (fc + 9) >= 2**31:
            raise ValueError("the 'triton' rasterizer backend indexes with int32: too many pairs or pixels")
        lists = tuple(
            x.to(device=device, dtype=torch.int32).contiguous()
            for x in (bins.surfel_ids, bins.tile_start, bins.tile_count)
        )
        params = torch.tensor(
            [settings.near, settings.far, settings.alpha_max, settings.alpha_min, settings.transmittance_min,
             settings.lowpass_inv_var, EDGE_ON_RATIO],
            dtype=cdt, device=device,
        )
        n_pix = width * height
        out = torch.zeros(n_pix, fc + 9, dtype=cdt, device=device)
        aux = torch.zeros(n_pix, 4, dtype=cdt, device=device)
        stops = torch.zeros(n_pix, 3, dtype=torch.int32, device=device)
        used = torch.zeros(lists[0].shape[0], dtype=torch.int8, device=device)
        shape = dict(kernel_constexprs(bins.tile_size, fc, cdt), **compile_options(bins.tile_size))
        has_pairs = lists[0].shape[0] > 0
        if has_pairs:
            with _on(device):
                k.forward_kernel[(bins.num_tiles,)](
                    *inputs, *lists, params, out, aux, stops, used, bins.tiles_x, width, height, fc, **shape
                )
        ctx.save_for_backward(*inputs, *lists, params, out, aux, stops)
        ctx.meta = (n, fc, width, height, M.dtype, bins.tiles_x, bins.num_tiles, shape, has_pairs)
        visible = torch.zeros(n, dtype=torch.bool, device=device)
        visible[lists[0][used.bool()].long()] = True
        ctx.mark_non_differentiable(visible)
        image = out.to(M.dtype).reshape(height, width, fc + 9)
        return image, visible

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad_image, grad_visible):
        n, fc, width, height, dtype, tiles_x, num_tiles, shape, has_pairs = ctx.meta
        if grad_image is None or not any(ctx.needs_input_grad[:6]):
            return (None,) * 8
        saved = ctx.saved_tensors
        inputs, lists, params, out, aux, stops = saved[:6], saved[6:9], saved[9], saved[10], saved[11], saved[12]
        cdt = out.dtype
        k = _kernels()
        grad = torch.zeros(n, int(k.G_FEAT) + fc, dtype=cdt, device=out.device)
        if has_pairs:
            grad_out = grad_image.reshape(width * height, fc + 9).to(cdt).contiguous()
            with _on(out.device):
                k.backward_kernel[(num_tiles,)](
                    *inputs, *lists, params, out, aux, stops, grad_out, grad, tiles_x, width, height, fc, **shape
                )
        grad = grad.to(dtype)
        g_m, g_center, g_occ, g_opa, g_color, g_feat = (
            int(x) for x in (k.G_M, k.G_CENTER, k.G_OCC, k.G_OPA, k.G_COLOR, k.G_FEAT)
        )
        return (
            grad[:, g_m : g_m + 9].reshape(n, 3, 3),
            grad[:, g_center : g_center + 2],
            grad[:, g_occ],
            grad[:, g_opa],
            grad[:, g_feat : g_feat + fc],
            grad[:, g_color : g_color + 3],
            None,
            None,
        )


def rasterize_triton(
    surfels: Surfels, camera: Camera, settings: RasterSettings, screen_probe: Tensor | None = None
) -> RasterOutput:
    """The ``triton`` backend: same signature, outputs and gradients as ``rasterize_reference``."""
    _check_device(surfels.device)
    return rasterize_tiled(_Composite.apply, surfels, camera, settings, screen_probe)
