"""Numba kernels of the G-buffer's surface values (:class:`rtsplat.model.gbuffer.SurfaceValues`).

Imported lazily (through :func:`rtsplat.raster.numba_runtime.load_numba_module`), never by ``import rtsplat``. One
pixel per iteration, on the calling thread (an image's pixels are little work). The forward is torch's arithmetic in
the arrays' float type (so the same bits): each wanted channel of the blended ``features`` divided by the pixel's
surface alpha, clamped to [0, 1] where asked (NaN stays NaN). The backward is torch's expressions of the division's
and the clamp's gradients (the clamp passes it where the ratio lies in [0, 1], ends included), the alpha's summed
over the channels in float64 (torch sums in the float type).
"""

from __future__ import annotations

import numpy as np
from numba import njit

_JIT = dict(cache=True, nogil=True, error_model="numpy", fastmath=False)


@njit(**_JIT)
def values_kernel(features, alpha, columns, clamped, consts, out):
    """``out[p, j] = features[p, columns[j]] / alpha[p]``, clamped to [0, 1] where ``clamped[j]``; ``consts`` [2]:
    0 and 1 in the arrays' float type. Column by column, without branches (the loops vectorise)."""
    zero = consts[0]
    one = consts[1]
    for j in range(columns.shape[0]):
        c = columns[j]
        if clamped[j]:
            for p in range(features.shape[0]):
                v = features[p, c] / alpha[p]  # in the arrays' float type, as torch divides
                v = zero if v < zero else v
                out[p, j] = one if v > one else v
        else:
            for p in range(features.shape[0]):
                out[p, j] = features[p, c] / alpha[p]


@njit(**_JIT)
def values_grad_kernel(features, alpha, columns, clamped, consts, grad, d_features, d_alpha):
    """From ``grad`` [P, J], that of :func:`values_kernel`'s ``out``: ``d_features`` [P, F] (the wanted columns; the
    others left as they are) and ``d_alpha`` [P] (float64, summed over the columns in their order)."""
    zero = consts[0]
    one = consts[1]
    for p in range(features.shape[0]):
        d_alpha[p] = 0.0
    for j in range(columns.shape[0]):
        c = columns[j]
        clamp = clamped[j]
        for p in range(features.shape[0]):
            a = alpha[p]
            x = features[p, c]
            r = x / a
            g = grad[p, j]
            g = zero if clamp and not (zero <= r <= one) else g  # the clamp passes no gradient outside its bounds
            d_features[p, c] = g / a
            d_alpha[p] += np.float64(-g * (r / a))  # torch's gradient of the divisor, -g (x / a) / a
