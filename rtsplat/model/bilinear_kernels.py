"""The bilinear cell of a sample in one level of a latitude-longitude texture, shared by the numba kernels of
the environment map (:mod:`rtsplat.model.envmap_kernels`) and of the learned background
(:mod:`rtsplat.model.background_kernels`).

Imported only by those modules (lazily, never by ``import rtsplat``). The arithmetic is that of
:meth:`rtsplat.model.envmap.EnvironmentMap._bilinear_taps`, in the float type of the arguments.
"""

from __future__ import annotations

import numpy as np
from numba import njit

_JIT = dict(cache=True, nogil=True, error_model="numpy", fastmath=False)


@njit(inline="always", **_JIT)
def bilinear_cell(u, v, h, w, hi, wi, half, one):
    """The four texels around (``u``, ``v``) in [0, 1]^2 of an ``hi`` x ``wi`` level (``h``, ``w``: the same
    sizes in the samples' float type; ``half``, ``one``: 0.5 and 1 in it): x = u w - 1/2, y = v h - 1/2, the
    columns wrapped, the rows clamped. Returns the row-major offsets of the taps (x0, y0), (x0 + 1, y0),
    (x0, y0 + 1), (x0 + 1, y0 + 1) within the level, the fractions fx, fy and 1 - fx, 1 - fy."""
    x = u * w - half
    y = v * h - half
    x0 = np.floor(x)
    y0 = np.floor(y)
    fx = x - x0
    fy = y - y0
    xi = np.int64(x0)
    yi = np.int64(y0)
    ya = min(max(yi, 0), hi - 1) * wi
    yb = min(max(yi + 1, 0), hi - 1) * wi
    xa = xi % wi
    xb = (xi + 1) % wi
    return ya + xa, ya + xb, yb + xa, yb + xb, fx, fy, one - fx, one - fy
