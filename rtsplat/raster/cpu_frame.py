"""Projection and tile binning of the ``cpu`` backend, in numba.

:func:`project_surfels` and :func:`bin_tiles` have the signatures and results of
:func:`rtsplat.raster.projection.project_surfels` and :func:`rtsplat.raster.binning.bin_tiles`
(the torch oracle, tested against them in ``tests/test_raster_cpu_frame.py``), computed by one numba pass
per surfel (:mod:`rtsplat.raster.cpu_frame_kernels`) instead of some fifty tensor operations, with
a hand-written backward (one autograd node instead of a graph of them). At the demo's settings
(30k surfels) the torch projection forward, its backward and the binning take about 14, 14 and
12 ms per iteration on 2 cores (``docs/performance.md``).

Both fall back to the torch code when numba is missing or on a non-CPU device; the projection also
when the camera's intrinsics need a gradient (the kernels return gradients for the surfels, the screen
probe and the camera's rotation and translation, which pose refinement learns).
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from rtsplat.camera import Camera
from rtsplat.raster import binning, projection
from rtsplat.raster.binning import TileBins
from rtsplat.raster.numba_runtime import SURFEL_CHUNK, load_numba_module, numba_threads, to_float64_array
from rtsplat.raster.projection import Projection
from rtsplat.raster.types import RasterSettings, Surfels

__all__ = ["project_surfels", "bin_tiles"]


def _kernels():
    return load_numba_module("rtsplat.raster.cpu_frame_kernels")


def _np64_or_zeros(x: Tensor | None, shape: tuple[int, ...]) -> np.ndarray:
    return np.zeros(shape, dtype=np.float64) if x is None else to_float64_array(x)


class _Project(torch.autograd.Function):
    """Per-surfel projection; differentiable outputs: ray transforms, centres, depths, normals."""

    @staticmethod
    def forward(ctx, means, quats, scales, probe, rotation, translation, K, geometry):
        kernels = _kernels()
        settings, width, height = geometry
        n = means.shape[0]
        inputs = (*map(to_float64_array, (means, quats, scales)), _np64_or_zeros(probe, (n, 2)),
                  *map(to_float64_array, (rotation, translation, K)))
        M = np.empty((n, 9))
        centers = np.empty((n, 2))
        depths = np.empty(n)
        normals = np.empty((n, 3))
        bbox_min = np.empty((n, 2))
        bbox_max = np.empty((n, 2))
        radii = np.empty((n, 2), dtype=np.int32)
        valid = np.empty(n, dtype=np.bool_)
        flip = np.empty(n, dtype=np.bool_)
        with numba_threads(SURFEL_CHUNK):
            kernels.project_forward_kernel(*inputs, float(settings.extent_sigma), float(settings.lowpass_radius),
                                           float(settings.near), int(width), int(height), M, centers, depths,
                                           normals, bbox_min, bbox_max, radii, valid, flip)
        ctx.saved = (inputs, flip)
        ctx.dtype = means.dtype

        def out(a):
            return torch.from_numpy(a).to(means.dtype)

        result = (out(M).reshape(n, 3, 3), out(centers), out(depths), out(normals), out(bbox_min), out(bbox_max),
                  torch.from_numpy(radii), torch.from_numpy(valid))
        ctx.mark_non_differentiable(*result[4:])
        return result

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, g_M, g_centers, g_depths, g_normals, *_):
        inputs, flip = ctx.saved
        n = flip.shape[0]
        grads = (_np64_or_zeros(g_M, (n, 3, 3)).reshape(n, 9), _np64_or_zeros(g_centers, (n, 2)),
                 _np64_or_zeros(g_depths, (n,)), _np64_or_zeros(g_normals, (n, 3)))
        g_means = np.empty((n, 3))
        g_quats = np.empty((n, 4))
        g_scales = np.empty((n, 2))
        g_probe = np.empty((n, 2))
        g_camera = np.empty((n, 12))
        with numba_threads(SURFEL_CHUNK):
            _kernels().project_backward_kernel(*inputs, flip, *grads, g_means, g_quats, g_scales, g_probe,
                                               g_camera)
        dtype = ctx.dtype
        camera = torch.from_numpy(g_camera).sum(0).to(dtype)
        grads = (torch.from_numpy(g_means).to(dtype), torch.from_numpy(g_quats).to(dtype),
                 torch.from_numpy(g_scales).to(dtype), torch.from_numpy(g_probe).to(dtype),
                 camera[:9].reshape(3, 3), camera[9:])
        # None where the input needs none (a probe may be absent altogether)
        return (*(g if needed else None for g, needed in zip(grads, ctx.needs_input_grad, strict=False)), None, None)


def project_surfels(surfels: Surfels, camera: Camera, settings: RasterSettings,
                    screen_probe: Tensor | None = None) -> Projection:
    """:func:`rtsplat.raster.projection.project_surfels`, computed by the numba kernels."""
    if surfels.device.type != "cpu" or camera.K.requires_grad or _kernels() is None:
        return projection.project_surfels(surfels, camera, settings, screen_probe)
    M, centers, depths, normals, bbox_min, bbox_max, radii, valid = _Project.apply(
        surfels.means, surfels.quats, surfels.scales, screen_probe, camera.rotation, camera.translation, camera.K,
        (settings, int(camera.width), int(camera.height)),
    )
    return Projection(M, centers, depths, normals, bbox_min, bbox_max, radii, valid)


@torch.no_grad()
def bin_tiles(bbox_min: Tensor, bbox_max: Tensor, depths: Tensor, valid: Tensor, width: int, height: int,
              tile_size: int) -> TileBins:
    """:func:`rtsplat.raster.binning.bin_tiles` as one counting sort in numba (the same lists)."""
    kernels = _kernels()
    if depths.device.type != "cpu" or kernels is None:
        return binning.bin_tiles(bbox_min, bbox_max, depths, valid, width, height, tile_size)
    tiles_x = (width + tile_size - 1) // tile_size
    tiles_y = (height + tile_size - 1) // tile_size
    order = kernels.depth_order_kernel(to_float64_array(depths), valid.numpy())
    tile_count = np.empty(tiles_x * tiles_y, dtype=np.int64)
    tile_start = np.empty(tiles_x * tiles_y, dtype=np.int64)
    ids = kernels.bin_tiles_kernel(order, to_float64_array(bbox_min), to_float64_array(bbox_max), int(tile_size),
                                   tiles_x, tiles_y, tile_count, tile_start)
    return TileBins(tiles_x, tiles_y, tile_size, torch.from_numpy(ids), torch.from_numpy(tile_start),
                    torch.from_numpy(tile_count), width, height)
