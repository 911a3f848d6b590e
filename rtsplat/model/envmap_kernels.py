"""Numba kernels of the environment map's trilinear lookup on the CPU (:class:`rtsplat.model.envmap.TrilinearLookup`).

Imported lazily (through :func:`rtsplat.raster.numba_runtime.load_numba_module`), never by ``import rtsplat``. The
lookup is :meth:`rtsplat.model.envmap.EnvironmentMap.lookup_reference`'s, sample by sample: the mip level ``l``
(roughness x (levels - 1)) picks levels ``lo = floor(l)`` (clamped to the last) and ``lo + 1`` (weight 0 past the
last), blended by ``l - lo``; in each level the bilinear taps of
:meth:`~rtsplat.model.envmap.EnvironmentMap._bilinear_taps` (:func:`rtsplat.model.bilinear_kernels.bilinear_cell`:
x = u W - 0.5, y = v H - 0.5, columns wrapped, rows clamped). The arithmetic is float64 (the inputs read exactly),
the output in the table's type.

Per sample the forward keeps the eight taps' table rows, weights and the weights' derivatives with respect to
u, v and l, from which the backward gives the gradients of the samples (one sample per parallel iteration)
and of the table (one pass over the samples: the taps of different samples share table rows). The texel table
comes in two parts, its first level and the coarser ones, so that the first level can be a view of the map
(:class:`rtsplat.model.envmap.MipLookup`) and its gradient the map's.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from rtsplat.model.bilinear_kernels import bilinear_cell

_JIT = dict(cache=True, nogil=True, error_model="numpy", fastmath=False)
TAPS = 8  # four bilinear taps in each of two levels


@njit(inline="always", **_JIT)
def _level_taps(layout, index, u, v, blend, dblend, m, slot, rows, weights, d_u, d_v, d_level):
    """The four bilinear taps of sample ``m`` in level ``index`` (``layout`` row: first table row, H, W),
    weighed by ``blend`` (whose derivative in the mip level is ``dblend``), into slots ``slot..slot + 3``."""
    first = layout[index, 0]
    h = layout[index, 1]
    w = layout[index, 2]
    o0, o1, o2, o3, fx, fy, gx, gy = bilinear_cell(u, v, np.float64(h), np.float64(w), h, w, 0.5, 1.0)
    rows[m, slot] = first + o0
    rows[m, slot + 1] = first + o1
    rows[m, slot + 2] = first + o2
    rows[m, slot + 3] = first + o3
    bil0 = gx * gy
    bil1 = fx * gy
    bil2 = gx * fy
    bil3 = fx * fy
    weights[m, slot] = bil0 * blend
    weights[m, slot + 1] = bil1 * blend
    weights[m, slot + 2] = bil2 * blend
    weights[m, slot + 3] = bil3 * blend
    bu = w * blend
    d_u[m, slot] = -gy * bu
    d_u[m, slot + 1] = gy * bu
    d_u[m, slot + 2] = -fy * bu
    d_u[m, slot + 3] = fy * bu
    bv = h * blend
    d_v[m, slot] = -gx * bv
    d_v[m, slot + 1] = -fx * bv
    d_v[m, slot + 2] = gx * bv
    d_v[m, slot + 3] = fx * bv
    d_level[m, slot] = bil0 * dblend
    d_level[m, slot + 1] = bil1 * dblend
    d_level[m, slot + 2] = bil2 * dblend
    d_level[m, slot + 3] = bil3 * dblend


@njit(inline="always", **_JIT)
def _texel(fine, coarse, split, r, c):
    """Channel ``c`` of row ``r`` of the texel table held in two parts: rows below ``split`` in ``fine``, the others
    in ``coarse`` (from its row 0)."""
    return fine[r, c] if r < split else coarse[r - split, c]


@njit(parallel=True, **_JIT)
def lookup_forward_kernel(fine, coarse, split, layout, u, v, level, rows, weights, d_u, d_v, d_level, out):
    """``out`` [M, C] = sum over the eight taps of the texel table's rows times weights, at (``u``, ``v``,
    ``level``) [M] (``layout`` [L, 3]: first row, H, W of each level). The table [T, C] is held in two parts,
    ``fine`` (its first ``split`` rows) and ``coarse`` (the rest; a caller with one table passes it whole and an
    empty second part). Keeps each tap's row, weight and the weight's derivatives in ``rows``, ``weights``,
    ``d_u``, ``d_v``, ``d_level`` [M, 8]. A sample with a non-finite coordinate reads no texel: NaN, and taps of
    weight 0 on row 0."""
    n_levels = layout.shape[0]
    channels = fine.shape[1]
    for m in prange(u.shape[0]):
        um = np.float64(u[m])
        vm = np.float64(v[m])
        lm = np.float64(level[m])
        if not (np.isfinite(um) and np.isfinite(vm) and np.isfinite(lm)):
            for k in range(TAPS):
                rows[m, k] = 0
                weights[m, k] = 0.0
                d_u[m, k] = 0.0
                d_v[m, k] = 0.0
                d_level[m, k] = 0.0
            for c in range(channels):
                out[m, c] = np.nan
            continue
        lo = min(max(math.floor(lm), 0.0), n_levels - 1.0)
        frac = lm - lo
        lo_i = np.int64(lo)
        if lo_i + 1 < n_levels:
            hi_i = lo_i + 1
            hi_blend = frac
            hi_dblend = 1.0
        else:
            hi_i = lo_i
            hi_blend = 0.0
            hi_dblend = 0.0
        _level_taps(layout, lo_i, um, vm, 1.0 - frac, -1.0, m, 0, rows, weights, d_u, d_v, d_level)
        _level_taps(layout, hi_i, um, vm, hi_blend, hi_dblend, m, 4, rows, weights, d_u, d_v, d_level)
        for c in range(channels):
            total = 0.0
            for k in range(TAPS):
                total += np.float64(_texel(fine, coarse, split, rows[m, k], c)) * weights[m, k]
            out[m, c] = total


@njit(parallel=True, **_JIT)
def lookup_sample_grad_kernel(fine, coarse, split, grad, rows, d_u, d_v, d_level, g_u, g_v, g_level):
    """Per sample, the gradients ``g_u``, ``g_v``, ``g_level`` [M] of the loss whose gradient in the lookup
    is ``grad`` [M, C]: each tap's texel (the table in two parts, as :func:`lookup_forward_kernel` reads it)
    dotted with ``grad``, times the weight's derivatives."""
    channels = fine.shape[1]
    for m in prange(grad.shape[0]):
        su = 0.0
        sv = 0.0
        sl = 0.0
        for k in range(TAPS):
            r = rows[m, k]
            dot = 0.0
            for c in range(channels):
                dot += np.float64(grad[m, c]) * np.float64(_texel(fine, coarse, split, r, c))
            su += dot * d_u[m, k]
            sv += dot * d_v[m, k]
            sl += dot * d_level[m, k]
        g_u[m] = su
        g_v[m] = sv
        g_level[m] = sl


@njit(**_JIT)
def lookup_table_grad_kernel(grad, rows, weights, g_fine, g_coarse, split):
    """The table's gradient (the table's type, in two parts as :func:`lookup_forward_kernel` reads it: rows below
    ``split`` in ``g_fine``, the others in ``g_coarse``) += each sample's ``grad`` [M, C] times its taps' weights,
    on their rows, in one pass (samples share rows). Taps of weight 0 (the level past the last, a level blended at
    0) add nothing, whatever the gradient."""
    channels = grad.shape[1]
    for m in range(grad.shape[0]):
        for k in range(TAPS):
            w = weights[m, k]
            if w == 0.0:
                continue
            r = rows[m, k]
            if r < split:
                for c in range(channels):
                    g_fine[r, c] += np.float64(grad[m, c]) * w
            else:
                for c in range(channels):
                    g_coarse[r - split, c] += np.float64(grad[m, c]) * w
