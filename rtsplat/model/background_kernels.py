"""Numba kernels of the learned background's lookup on the CPU (:class:`rtsplat.model.background.BackgroundLookup`):
the summed logits, with or without what the backward reads, and the gradients of the levels and of the samples.

Imported lazily (through :func:`rtsplat.raster.numba_runtime.load_numba_module`), never by ``import rtsplat``. The
kernels read the map's levels where they are (a tuple of [3, H*W] views), so a lookup copies no texel. One sample
per parallel iteration; every operation of the logits is the one the torch lookup does, in the arrays' float type
and in the same order (no fused multiply-add: ``fastmath`` off), so the logits are the same bits: per level the
bilinear taps of :meth:`rtsplat.model.envmap.EnvironmentMap._bilinear_taps`
(:func:`rtsplat.model.bilinear_kernels.bilinear_cell`: x = u W - 0.5, y = v H - 0.5, floor, fractions, columns
wrapped, rows clamped; weights (1 - fx)(1 - fy), fx (1 - fy), (1 - fx) fy, fx fy), the four weighed taps added in
turn (:meth:`~rtsplat.model.envmap.EnvironmentMap.sample_level`), and the levels added in turn onto 0.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from rtsplat.model.bilinear_kernels import bilinear_cell

_JIT = dict(cache=True, nogil=True, error_model="numpy", fastmath=False)


@njit(parallel=True, **_JIT)
def background_logits_kernel(levels, sizes, u, v, consts, out, taps, fractions, jacobian):
    """``levels``: a tuple of L texel arrays [3, H*W] (each level channel-major, rows of W texels), ``sizes`` [L, 2]
    their (H, W) in the samples' float type; ``u``, ``v`` [M]; ``consts`` [3] = (0, 0.5, 1) in that type. Writes the
    summed logits [M, 3] to ``out``. Unless ``taps`` is empty, keeps for the backward each sample's four texels per
    level in ``taps`` [M, L, 4] (-1 for a sample with a non-finite coordinate) and its fractions fx, fy in
    ``fractions`` [M, L, 2]; unless ``jacobian`` is empty, the logits' derivatives [M, 6] (float64) with respect to u
    (three channels) and v (three), NaN for a sample with a non-finite coordinate: per level
    d(logit)/dfx = (t1 - t0)(1 - fy) + (t3 - t2) fy and d(logit)/dfy = (t2 - t0)(1 - fx) + (t3 - t1) fx, with
    dfx/du = W and dfy/dv = H, summed over the levels."""
    n_levels = sizes.shape[0]
    zero = consts[0]
    half = consts[1]
    one = consts[2]
    keep = taps.shape[0] > 0
    derive = jacobian.shape[0] > 0
    for m in prange(u.shape[0]):
        um = u[m]
        vm = v[m]
        if not (np.isfinite(um) and np.isfinite(vm)):  # no texel to read: NaN, not an index out of a level
            out[m, 0] = np.nan
            out[m, 1] = np.nan
            out[m, 2] = np.nan
            if keep:
                taps[m, :, :] = -1
            if derive:
                jacobian[m, :] = np.nan
            continue
        a0 = zero
        a1 = zero
        a2 = zero
        if derive:
            jacobian[m, :] = 0.0
        for lev in range(n_levels):
            level = levels[lev]
            r0, r1, r2, r3, fx, fy, gx, gy = bilinear_cell(
                um, vm, sizes[lev, 0], sizes[lev, 1], np.int64(sizes[lev, 0]), np.int64(sizes[lev, 1]), half, one
            )
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
            a0 = a0 + (((level[0, r0] * w0 + level[0, r1] * w1) + level[0, r2] * w2) + level[0, r3] * w3)
            a1 = a1 + (((level[1, r0] * w0 + level[1, r1] * w1) + level[1, r2] * w2) + level[1, r3] * w3)
            a2 = a2 + (((level[2, r0] * w0 + level[2, r1] * w1) + level[2, r2] * w2) + level[2, r3] * w3)
            if derive:
                fx64 = np.float64(fx)
                fy64 = np.float64(fy)
                width = np.float64(sizes[lev, 1])
                height = np.float64(sizes[lev, 0])
                for c in range(3):
                    t0 = np.float64(level[c, r0])
                    t1 = np.float64(level[c, r1])
                    t2 = np.float64(level[c, r2])
                    t3 = np.float64(level[c, r3])
                    jacobian[m, c] += ((t1 - t0) * (1.0 - fy64) + (t3 - t2) * fy64) * width
                    jacobian[m, 3 + c] += ((t2 - t0) * (1.0 - fx64) + (t3 - t1) * fx64) * height
        out[m, 0] = a0
        out[m, 1] = a1
        out[m, 2] = a2


@njit(parallel=True, **_JIT)
def background_sample_grad_kernel(jacobian, grad, g_u, g_v):
    """The gradients ``g_u``, ``g_v`` [M] (float64) of the summed logits' loss, whose gradient is ``grad`` [M, 3],
    with respect to each sample's u and v, from the ``jacobian`` [M, 6] the forward kept."""
    for m in prange(jacobian.shape[0]):
        su = 0.0
        sv = 0.0
        for c in range(3):
            g = np.float64(grad[m, c])
            su += g * jacobian[m, c]
            sv += g * jacobian[m, 3 + c]
        g_u[m] = su
        g_v[m] = sv


@njit(parallel=True, **_JIT)
def background_level_grad_kernel(taps, fractions, grad, g_levels):
    """The gradients ``g_levels`` (a tuple of L arrays [3, H*W] in the levels' float type, zeros on entry) of the
    levels: every kept tap's weight times the sample's gradient ``grad`` [M, 3], added to its texel in the samples'
    order; one level per parallel iteration (each sample has four taps in every level, so the levels are equal
    work), so that no two threads add to the same texel."""
    n_levels = taps.shape[1]
    for lev in prange(n_levels):
        g_level = g_levels[lev]
        for m in range(taps.shape[0]):
            if taps[m, 0, 0] < 0:
                continue
            fx = np.float64(fractions[m, lev, 0])
            fy = np.float64(fractions[m, lev, 1])
            gx = 1.0 - fx
            gy = 1.0 - fy
            w0 = gx * gy
            w1 = fx * gy
            w2 = gx * fy
            w3 = fx * fy
            r0 = taps[m, lev, 0]
            r1 = taps[m, lev, 1]
            r2 = taps[m, lev, 2]
            r3 = taps[m, lev, 3]
            for c in range(3):
                g = np.float64(grad[m, c])
                g_level[c, r0] += g * w0
                g_level[c, r1] += g * w1
                g_level[c, r2] += g * w2
                g_level[c, r3] += g * w3
