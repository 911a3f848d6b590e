"""Fast CPU rasterizer backend (``backend="cpu"``, the default on CPU).

Same semantics as :mod:`rtsplat.raster.reference` (the oracle, still selectable with
``backend="reference"``). The per-pixel compositing, the O(pixels x surfels) part, is replaced by
the kernels below; projection and tile binning by :mod:`rtsplat.raster.cpu_frame` (numba versions
of the reference's torch :func:`~rtsplat.raster.projection.project_surfels` and
:func:`~rtsplat.raster.binning.bin_tiles`, with their own backward: gradients reach
means/quats/scales, the screen probe and the camera's pose).

The compositing is one ``torch.autograd.Function`` (:class:`_Composite`):

* a first pass computes per surfel the rho cut-off and the pixel box outside which it cannot
  contribute, a second per tile the entries whose box meets the tile;
* forward: one front-to-back traversal per pixel accumulates both weight sets (surface set from
  occupancy, volume set from occupancy x opacity); each set stops on its own exactly as in the
  reference, and the traversal of a pixel ends as soon as *both* sets have stopped. One tile is
  one work unit: its kept entries are gathered once into a packed per-tile table (box, ray
  transform, centre, cut-off, occupancies; read sequentially afterwards) and listed per 4x4 block
  in one pass. The pixels of a block are traversed together, entry by entry: a division-free test
  over the block's 16 pixel slots (one loop that LLVM vectorises to 256-bit AVX) finds the still
  traversing pixels that may be in the entry's reach (a superset of the exact test's, by a relative
  margin of 1e-12), the entry is skipped when there are none (on the dome's 320x240 frame: 2/3 of
  the 1.58M entry-block visits; 25.3M pixel geometries become 5.0M, all of them in reach), and
  only those pixels get the exact geometry (two divisions) and composite it, so the outputs are
  those of the exact test alone, bit for bit;
* backward: hand written, no autograd graph over pixel x surfel pairs. It replays each pixel's
  traversal front to back (again tile by tile, the tile's entries packed and listed per block as in the
  forward, and block by block; the pixel's image gradient and totals copied into the block's scratch
  once) and uses the forward totals to get the suffix
  sums (dL/da_i = q_i T_i - (Q - prefix_i) / (1 - a_i)); the gradient of one entry is summed over
  the block's pixels, then added to one per-surfel buffer per thread (threads never race), and the
  buffers are summed over threads at the end;
* all kernels run in parallel (numba ``prange``: the forward and the backward over tiles in chunks of
  ``TILE_CHUNK``, the tiles' entry lists in chunks of ``CHUNK`` tiles, over surfels in chunks
  of ``SURFEL_CHUNK``, all in :mod:`rtsplat.raster.numba_runtime`,
  with the compile cache and the kernel-module import: with chunks of 4, scheduling cost the
  per-surfel kernels more than their work), with as many threads as ``torch.get_num_threads()``; all arithmetic is
  float64 (per-surfel inputs of any float dtype are converted; the image gradient is read as
  float32 or float64 as it comes; outputs and gradients are returned in the input dtype).
  numba's ``workqueue`` threading layer (the one :mod:`rtsplat.raster.numba_runtime` picks) does not
  hand out chunks on demand: it splits a loop's chunks into one contiguous run per thread. So the
  forward and the backward visit the tiles in a spread order (:func:`~rtsplat.raster.cpu_kernels.spread_order`:
  with 2 threads one takes the even tiles, the other the odd ones) instead of row by row, where the
  thread with the lower half of the dome's 320x240 frame had 60-64% of the work; each tile writes only
  its own pixels, so the outputs do not depend on the order;

Technology choice (measured on the 2-core development machine):

* numba ``@njit(parallel=True, cache=True)``: no compiler toolchain or torch headers at run time,
  pip-installable wheels (numba, llvmlite); the first use compiles the kernels in ~28 s (loaded
  machine; once per machine, and once more for the backward when the image gradient is float64),
  later processes load them from the cache in ~1 s.
  ``python -m rtsplat.bench.raster``: forward+backward at 20k surfels, 160x120 takes 0.04-0.07x
  the reference's time (0.6-1.3 s against 20-31 s, 2 threads) and ~2% of its peak memory;
* the forward composites the candidate pixels of an entry in a scalar loop. A variant that
  composited all 16 slots of the block in one branch-free loop (selects instead of branches, the
  block's state in one flat array, a polynomial ``exp`` in place of libm's so that LLVM vectorises
  it) was 1.33x slower on the dome's 320x240 frame (one thread, alternating runs, minimum CPU
  time 325 against 244 ms; loaded machine): a block has ~10 candidates of 16 slots on average, and
  the state goes through memory on every entry. Where the forward's 263 ms go on that frame (one
  thread, minimum CPU time, loaded machine, from variants that leave parts out): packing and block
  lists ~16 ms, the reach tests of the 1.58M entry-block visits ~50 ms, the exact geometry of the
  5.0M in-reach pairs ~35 ms, their compositing (libm's ``exp``, both weight sets, 15 feature
  channels) ~160 ms;
* a ``torch.utils.cpp_extension`` C++/OpenMP extension was the alternative: a one-function
  extension including ``torch/extension.h`` already took 64 s to build on this machine (ninja +
  g++ -O3), it needs a matching compiler at run time on every install, and the compiled kernel
  would do the same scalar loop;
* ``torch.compile`` cannot express per-pixel early termination or a hand-written backward over
  ragged per-tile lists: it would only fuse the dense [tiles, pixels, surfels] tensors of the
  reference, which is what makes the reference slow and memory hungry.

Compile caches: numba writes to ``$NUMBA_CACHE_DIR`` when set, otherwise to
``$XDG_CACHE_HOME/rtsplat/numba`` (default ``~/.cache/rtsplat/numba``), never into the repository.
Neither ``import rtsplat`` nor ``import rtsplat.raster`` (nor this module) imports numba; the
kernels are imported and compiled on the first rasterization. Without numba this backend warns
once and falls back to the reference.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from rtsplat.camera import Camera
from rtsplat.raster.binning import TileBins
from rtsplat.raster.cpu_frame import bin_tiles, project_surfels
from rtsplat.raster.numba_runtime import (
    SURFEL_CHUNK,
    TILE_CHUNK,
    cache_dir,
    load_numba_module,
    numba_threads,
    to_float64_array,
)
from rtsplat.raster.reference import EDGE_ON_RATIO, rasterize_reference, rasterize_tiled
from rtsplat.raster.types import RasterOutput, RasterSettings, Surfels

__all__ = ["rasterize_cpu", "cache_dir", "kernels_available", "load_numba_module", "numba_threads"]

_kernels = None


def _load_kernels():
    """The rasterizer's numba kernels (:mod:`rtsplat.raster.cpu_kernels`); None when numba is missing."""
    global _kernels
    _kernels = load_numba_module("rtsplat.raster.cpu_kernels")
    return _kernels


def kernels_available() -> bool:
    return _load_kernels() is not None


def _np_float(x: Tensor) -> np.ndarray:
    """float32 and float64 as they are (the kernels read either into float64 arithmetic, exactly),
    other dtypes as float64."""
    x = x.detach().to(device="cpu")
    if x.dtype not in (torch.float32, torch.float64):
        x = x.to(torch.float64)
    return np.ascontiguousarray(x.numpy())


def _np_i64(x: Tensor) -> np.ndarray:
    return np.ascontiguousarray(x.detach().to(device="cpu", dtype=torch.int64).numpy())


class _Composite(torch.autograd.Function):
    """Per-pixel compositing of both weight sets; inputs are per-surfel projected tensors."""

    @staticmethod
    def forward(ctx, M, centers, occupancy, opacity, feats, colors, bins: TileBins, geometry):
        kernels = _kernels
        width, height, settings = geometry
        n = M.shape[0]
        fc = feats.shape[1]
        n_channels = fc + 9
        arrays = (
            to_float64_array(M.reshape(n, 9)),
            to_float64_array(centers),
            to_float64_array(occupancy),
            to_float64_array(opacity),
            to_float64_array(feats),
            to_float64_array(colors),
            _np_i64(bins.surfel_ids),
            _np_i64(bins.tile_start),
            _np_i64(bins.tile_count),
        )
        scalars = (
            int(bins.tiles_x),
            int(bins.tile_size),
            int(width),
            int(height),
            float(settings.near),
            float(settings.far),
            float(settings.alpha_max),
            float(settings.alpha_min),
            float(settings.transmittance_min),
            float(settings.lowpass_inv_var),
            float(EDGE_ON_RATIO),
        )
        cut = np.empty(n, dtype=np.float64)
        boxes = np.empty((n, 4), dtype=np.float64)
        n_pix = width * height
        out = np.zeros((n_pix, n_channels), dtype=np.float64)
        stats = np.zeros((n_pix, 2), dtype=np.float64)
        n_done = np.zeros(n_pix, dtype=np.int64)
        median_k = np.full(n_pix, -1, dtype=np.int64)
        used = np.zeros(arrays[6].shape[0], dtype=np.uint8)
        keep = np.empty(arrays[6].shape[0], dtype=np.int64)
        n_keep = np.zeros(arrays[8].shape[0], dtype=np.int64)
        lists = (cut, boxes, keep, n_keep)
        with numba_threads(SURFEL_CHUNK):
            kernels.surfel_bounds_kernel(*arrays[:4], scalars[7], scalars[9], cut, boxes)
        with numba_threads():
            kernels.tile_entries_kernel(arrays[6], boxes, arrays[7], arrays[8], scalars[0], scalars[1], keep, n_keep)
        with numba_threads(TILE_CHUNK):
            kernels.forward_kernel(*arrays, *scalars, *lists, out, stats, n_done, median_k, used)
        ctx.saved = (arrays, scalars, lists, out, stats, n_done, median_k)
        ctx.meta = (n, fc, width, height, M.dtype)
        visible = torch.zeros(n, dtype=torch.bool)
        if used.size:
            visible[torch.from_numpy(arrays[6][used.astype(bool)])] = True
        ctx.mark_non_differentiable(visible)
        image = torch.from_numpy(out).to(M.dtype).reshape(height, width, n_channels)
        return image, visible

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad_image, grad_visible):
        arrays, scalars, lists, out, stats, n_done, median_k = ctx.saved
        n, fc, width, height, dtype = ctx.meta
        if grad_image is None or not any(ctx.needs_input_grad[:6]):
            return (None,) * 8
        grad = _np_float(grad_image.reshape(width * height, fc + 9))
        with numba_threads(TILE_CHUNK) as threads:
            acc = np.zeros((threads, n, 16 + fc), dtype=np.float64)
            _kernels.backward_kernel(*arrays, *scalars, *lists, out, stats, n_done, median_k, grad, acc)
        if threads > 1:
            with numba_threads(SURFEL_CHUNK):
                _kernels.sum_threads_kernel(acc)
        per_surfel = torch.from_numpy(acc[0])
        per_surfel = per_surfel.to(dtype)
        k = _kernels
        return (
            per_surfel[:, k.G_M : k.G_M + 9].reshape(n, 3, 3),
            per_surfel[:, k.G_CENTER : k.G_CENTER + 2],
            per_surfel[:, k.G_OCC],
            per_surfel[:, k.G_OPA],
            per_surfel[:, k.G_FEAT : k.G_FEAT + fc],
            per_surfel[:, k.G_COLOR : k.G_COLOR + 3],
            None,
            None,
        )


def rasterize_cpu(
    surfels: Surfels, camera: Camera, settings: RasterSettings, screen_probe: Tensor | None = None
) -> RasterOutput:
    """The ``cpu`` backend: same signature, outputs and gradients as ``rasterize_reference``."""
    if surfels.device.type != "cpu":
        raise ValueError(f"the 'cpu' rasterizer backend needs CPU tensors, got {surfels.device}")
    if _load_kernels() is None:
        return rasterize_reference(surfels, camera, settings, screen_probe)
    return rasterize_tiled(_Composite.apply, surfels, camera, settings, screen_probe, project_surfels, bin_tiles)
