"""Numba kernel of the learned background's lookup without autograd (:meth:`rtsplat.model.background.
BackgroundMap.forward` on CPU tensors under ``torch.no_grad``/``inference_mode``).

Imported lazily (through :func:`rtsplat.raster.numba_runtime.load_numba_module`), never by ``import rtsplat``.
One sample per parallel iteration; every operation is the one the torch lookup does, in the arrays'
float type and in the same order (no fused multiply-add: ``fastmath`` off), so the logits are the same
bits: per level the bilinear taps of :meth:`rtsplat.model.envmap.EnvironmentMap._bilinear_taps`
(x = u W - 0.5, y = v H - 0.5, floor, fractions, columns wrapped, rows clamped, weights (1 - fx)(1 - fy),
fx (1 - fy), (1 - fx) fy, fx fy), the four weighed taps added in turn
(:meth:`~rtsplat.model.envmap.EnvironmentMap.sample_level`), and the levels added in turn onto 0.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

_JIT = dict(cache=True, nogil=True, error_model="numpy", fastmath=False)


@njit(parallel=True, **_JIT)
def background_logits_kernel(table, first, sizes, u, v, consts, out):
    """``table`` [3, T]: every level's texels, channel-major, level after level; per level ``first`` [L]
    (int64: its first column in ``table``) and ``sizes`` [L, 2] (H, W in the samples' float type);
    ``u``, ``v`` [M]; ``consts`` [3] = (0, 0.5, 1) in that type. Writes the summed logits [M, 3] to ``out``."""
    n_levels = first.shape[0]
    zero = consts[0]
    half = consts[1]
    one = consts[2]
    for m in prange(u.shape[0]):
        um = u[m]
        vm = v[m]
        if not (np.isfinite(um) and np.isfinite(vm)):  # no texel to read: NaN, not an index out of the table
            out[m, 0] = np.nan
            out[m, 1] = np.nan
            out[m, 2] = np.nan
            continue
        a0 = zero
        a1 = zero
        a2 = zero
        for lev in range(n_levels):
            H = sizes[lev, 0]
            W = sizes[lev, 1]
            Hi = np.int64(H)
            Wi = np.int64(W)
            x = um * W - half
            y = vm * H - half
            x0 = np.floor(x)
            y0 = np.floor(y)
            fx = x - x0
            fy = y - y0
            xi = np.int64(x0)
            yi = np.int64(y0)
            ya = min(max(yi, 0), Hi - 1) * Wi
            yb = min(max(yi + 1, 0), Hi - 1) * Wi
            xa = xi % Wi
            xb = (xi + 1) % Wi
            base = first[lev]
            r0 = base + ya + xa
            r1 = base + ya + xb
            r2 = base + yb + xa
            r3 = base + yb + xb
            gx = one - fx
            gy = one - fy
            w0 = gx * gy
            w1 = fx * gy
            w2 = gx * fy
            w3 = fx * fy
            a0 = a0 + (((table[0, r0] * w0 + table[0, r1] * w1) + table[0, r2] * w2) + table[0, r3] * w3)
            a1 = a1 + (((table[1, r0] * w0 + table[1, r1] * w1) + table[1, r2] * w2) + table[1, r3] * w3)
            a2 = a2 + (((table[2, r0] * w0 + table[2, r1] * w1) + table[2, r2] * w2) + table[2, r3] * w3)
        out[m, 0] = a0
        out[m, 1] = a1
        out[m, 2] = a2
