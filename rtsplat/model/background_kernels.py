"""Numba kernel of the learned background's lookup without autograd (:meth:`rtsplat.model.background.
BackgroundMap.forward` on CPU tensors under ``torch.no_grad``/``inference_mode``).

Imported lazily (through :func:`rtsplat.raster.numba_runtime.load_numba_module`), never by ``import rtsplat``. One
sample per parallel iteration; every operation is the one the torch lookup does, in the arrays' float type and in the
same order (no fused multiply-add: ``fastmath`` off), so the logits are the same bits: per level the bilinear taps of
:meth:`rtsplat.model.envmap.EnvironmentMap._bilinear_taps` (:func:`rtsplat.model.bilinear_kernels.bilinear_cell`:
x = u W - 0.5, y = v H - 0.5, floor, fractions, columns wrapped, rows clamped; weights (1 - fx)(1 - fy),
fx (1 - fy), (1 - fx) fy, fx fy), the four weighed taps added in turn
(:meth:`~rtsplat.model.envmap.EnvironmentMap.sample_level`), and the levels added in turn onto 0.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from rtsplat.model.bilinear_kernels import bilinear_cell

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
            base = first[lev]
            o0, o1, o2, o3, fx, fy, gx, gy = bilinear_cell(
                um, vm, sizes[lev, 0], sizes[lev, 1], np.int64(sizes[lev, 0]), np.int64(sizes[lev, 1]), half, one
            )
            r0 = base + o0
            r1 = base + o1
            r2 = base + o2
            r3 = base + o3
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
