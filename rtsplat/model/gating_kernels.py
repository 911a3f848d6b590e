"""Numba kernel of the gating factor (:func:`rtsplat.model.gating.gate_factor` on CPU tensors).

Imported lazily (through :func:`rtsplat.raster.numba_runtime.load_numba_module`), never by ``import rtsplat``. The 3x3
windows with reflect padding (row -1 is row 1, row H is row H - 2, columns alike) are summed in float64 as separable
box sums of every pixel's w, w x and w x^2, without the unfolded [C, 9, H, W] copies of the torch version. The
measures are those of :func:`rtsplat.model.gating.specular_complexity`: the plain variance over the window, or the
standard deviation weighted by ``max(1 - alpha, 0)`` of each window pixel (the total weight at least 1e-8), here as
E[w x^2] / E[w] - mean^2, clamped at 0; a NaN anywhere in a window gives a NaN factor, as in the torch version.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

_JIT = dict(cache=True, nogil=True, error_model="numpy", fastmath=False)


@njit(inline="always", **_JIT)
def _reflect(i, n):
    """Index ``i`` in [-1, n] reflected into [0, n): -1 -> 1, n -> n - 2."""
    if i < 0:
        return -i
    if i >= n:
        return 2 * n - 2 - i
    return i


@njit(inline="always", **_JIT)
def _weight(a, weighted):
    """The window weight of a pixel of surface alpha ``a``: 1 - a clamped below at 0 (NaN stays NaN), or 1."""
    if not weighted:
        return 1.0
    w = 1.0 - float(a)
    if w < 0.0:
        w = 0.0
    return w


@njit(**_JIT)
def gate_factor_kernel(spec, alpha, k, weighted, out):
    """``spec`` [H, W, C], ``alpha`` [H, W] (the surface alpha; read only when ``weighted``), ``k`` the gating
    strength -> ``out`` [H, W, C] = exp(-k s) with s the window's weighted standard deviation (``weighted``) or
    plain variance per channel. H and W are at least 2 (reflect padding). Every pixel's w, w x and w x^2 are
    summed over the windows in float64, a row pass then a column pass."""
    H, W, C = spec.shape
    n = 1 + 2 * C
    terms = np.empty((H, W, n), dtype=np.float64)
    for y in range(H):
        for x in range(W):
            w = _weight(alpha[y, x], weighted)
            terms[y, x, 0] = w
            for ch in range(C):
                v = float(spec[y, x, ch])
                terms[y, x, 1 + ch] = w * v
                terms[y, x, 1 + C + ch] = w * v * v
    rows = np.empty((H, W, n), dtype=np.float64)
    for y in range(H):
        for x in range(W):
            left = _reflect(x - 1, W)
            right = _reflect(x + 1, W)
            for j in range(n):
                rows[y, x, j] = terms[y, left, j] + terms[y, x, j] + terms[y, right, j]
    for y in range(H):
        up = _reflect(y - 1, H)
        down = _reflect(y + 1, H)
        for x in range(W):
            total = rows[up, x, 0] + rows[y, x, 0] + rows[down, x, 0]
            if total < 1e-8:  # NaN stays NaN
                total = 1e-8
            for ch in range(C):
                mean = (rows[up, x, 1 + ch] + rows[y, x, 1 + ch] + rows[down, x, 1 + ch]) / total
                j = 1 + C + ch
                var = (rows[up, x, j] + rows[y, x, j] + rows[down, x, j]) / total - mean * mean
                if var < 0.0:  # rounding; NaN stays NaN
                    var = 0.0
                s = math.sqrt(var) if weighted else var
                out[y, x, ch] = math.exp(-k * s)
