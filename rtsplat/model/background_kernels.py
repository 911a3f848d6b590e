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
def background_logits_kernel(table, first, sizes, u, v, consts, out, taps, fractions):
    """``table`` [3, T]: every level's texels, channel-major, level after level; per level ``first`` [L]
    (int64: its first column in ``table``) and ``sizes`` [L, 2] (H, W in the samples' float type);
    ``u``, ``v`` [M]; ``consts`` [3] = (0, 0.5, 1) in that type. Writes the summed logits [M, 3] to ``out``.
    Unless ``taps`` is empty, keeps for the backward each sample's four table columns per level in ``taps``
    [M, L, 4] (-1 for a sample with a non-finite coordinate) and its fractions fx, fy in ``fractions`` [M, L, 2]."""
    n_levels = first.shape[0]
    zero = consts[0]
    half = consts[1]
    one = consts[2]
    keep = taps.shape[0] > 0
    for m in prange(u.shape[0]):
        um = u[m]
        vm = v[m]
        if not (np.isfinite(um) and np.isfinite(vm)):  # no texel to read: NaN, not an index out of the table
            out[m, 0] = np.nan
            out[m, 1] = np.nan
            out[m, 2] = np.nan
            if keep:
                taps[m, :, :] = -1
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
            if keep:
                taps[m, lev, 0] = r0
                taps[m, lev, 1] = r1
                taps[m, lev, 2] = r2
                taps[m, lev, 3] = r3
                fractions[m, lev, 0] = fx
                fractions[m, lev, 1] = fy
            a0 = a0 + (((table[0, r0] * w0 + table[0, r1] * w1) + table[0, r2] * w2) + table[0, r3] * w3)
            a1 = a1 + (((table[1, r0] * w0 + table[1, r1] * w1) + table[1, r2] * w2) + table[1, r3] * w3)
            a2 = a2 + (((table[2, r0] * w0 + table[2, r1] * w1) + table[2, r2] * w2) + table[2, r3] * w3)
        out[m, 0] = a0
        out[m, 1] = a1
        out[m, 2] = a2


@njit(parallel=True, **_JIT)
def background_sample_grad_kernel(table, sizes, taps, fractions, grad, g_u, g_v):
    """The gradients ``g_u``, ``g_v`` [M] (float64) of the summed logits' loss, whose gradient is ``grad`` [M, 3],
    with respect to each sample's u and v, from the ``taps`` and ``fractions`` the forward kept: per level
    d(logit)/dfx = (t1 - t0)(1 - fy) + (t3 - t2) fy, d(logit)/dfy = (t2 - t0)(1 - fx) + (t3 - t1) fx, with
    dfx/du = W and dfy/dv = H. NaN for a sample with a non-finite coordinate."""
    n_levels = sizes.shape[0]
    for m in prange(taps.shape[0]):
        if taps[m, 0, 0] < 0:
            g_u[m] = np.nan
            g_v[m] = np.nan
            continue
        su = 0.0
        sv = 0.0
        for lev in range(n_levels):
            r0 = taps[m, lev, 0]
            r1 = taps[m, lev, 1]
            r2 = taps[m, lev, 2]
            r3 = taps[m, lev, 3]
            fx = np.float64(fractions[m, lev, 0])
            fy = np.float64(fractions[m, lev, 1])
            d_fx = 0.0
            d_fy = 0.0
            for c in range(3):
                g = np.float64(grad[m, c])
                t0 = np.float64(table[c, r0])
                t1 = np.float64(table[c, r1])
                t2 = np.float64(table[c, r2])
                t3 = np.float64(table[c, r3])
                d_fx += g * ((t1 - t0) * (1.0 - fy) + (t3 - t2) * fy)
                d_fy += g * ((t2 - t0) * (1.0 - fx) + (t3 - t1) * fx)
            su += d_fx * np.float64(sizes[lev, 1])
            sv += d_fy * np.float64(sizes[lev, 0])
        g_u[m] = su
        g_v[m] = sv


@njit(parallel=True, **_JIT)
def background_table_grad_kernel(taps, fractions, grad, g_table):
    """The gradient ``g_table`` [3, T] (float64, zeros on entry) of the texel table: every kept tap's weight
    times the sample's gradient ``grad`` [M, 3], added to its column; one channel per parallel iteration,
    so that no two threads add to the same texel."""
    n_levels = taps.shape[1]
    for c in prange(3):
        for m in range(taps.shape[0]):
            if taps[m, 0, 0] < 0:
                continue
            g = np.float64(grad[m, c])
            for lev in range(n_levels):
                fx = np.float64(fractions[m, lev, 0])
                fy = np.float64(fractions[m, lev, 1])
                gx = 1.0 - fx
                gy = 1.0 - fy
                g_table[c, taps[m, lev, 0]] += g * (gx * gy)
                g_table[c, taps[m, lev, 1]] += g * (fx * gy)
                g_table[c, taps[m, lev, 2]] += g * (gx * fy)
                g_table[c, taps[m, lev, 3]] += g * (fx * fy)
