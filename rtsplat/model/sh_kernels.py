"""Numba kernels of the spherical-harmonics colour (:func:`rtsplat.model.sh.eval_sh` on CPU tensors).

Imported lazily (through :func:`rtsplat.raster.numba_runtime.load_numba_module`, which sets up the compile cache),
never by ``import rtsplat``. One surfel per parallel iteration, computed in float64 and stored in the
arrays' float type. The basis is :func:`rtsplat.model.sh.sh_basis`'s, with x, y, z the direction's
components taken as independent variables (the caller normalises the direction, and autograd carries
the gradient through that). Colour = basis . coefficients + 0.5, clamped at 0 (the gradient passes
where the sum is >= 0, as ``torch.clamp_min``'s does).
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from rtsplat.model.sh import C0, C1, C2, C3

_JIT = dict(cache=True, nogil=True, error_model="numpy", fastmath=False)


@njit(inline="always", **_JIT)
def _basis(x, y, z, degree, b):
    """Basis values at (x, y, z) into ``b[:(degree + 1)^2]``, in the order of ``sh_basis``."""
    b[0] = C0
    if degree >= 1:
        b[1] = -C1 * y
        b[2] = C1 * z
        b[3] = -C1 * x
    if degree >= 2:
        xx, yy, zz = x * x, y * y, z * z
        xy, yz, xz = x * y, y * z, x * z
        b[4] = C2[0] * xy
        b[5] = C2[1] * yz
        b[6] = C2[2] * (2.0 * zz - xx - yy)
        b[7] = C2[3] * xz
        b[8] = C2[4] * (xx - yy)
        if degree >= 3:
            b[9] = C3[0] * y * (3.0 * xx - yy)
            b[10] = C3[1] * xy * z
            b[11] = C3[2] * y * (4.0 * zz - xx - yy)
            b[12] = C3[3] * z * (2.0 * zz - 3.0 * xx - 3.0 * yy)
            b[13] = C3[4] * x * (4.0 * zz - xx - yy)
            b[14] = C3[5] * z * (xx - yy)
            b[15] = C3[6] * x * (xx - 3.0 * yy)


@njit(inline="always", **_JIT)
def _basis_gradient(x, y, z, degree, s):
    """sum_k s[k] d(basis_k)/d(x, y, z) (``s``: the colour gradient's dot product with each
    coefficient)."""
    gx = 0.0
    gy = 0.0
    gz = 0.0
    if degree >= 1:
        gy -= C1 * s[1]
        gz += C1 * s[2]
        gx -= C1 * s[3]
    if degree >= 2:
        xx, yy, zz = x * x, y * y, z * z
        xy, yz, xz = x * y, y * z, x * z
        gx += C2[0] * y * s[4]
        gy += C2[0] * x * s[4]
        gy += C2[1] * z * s[5]
        gz += C2[1] * y * s[5]
        gx -= 2.0 * C2[2] * x * s[6]
        gy -= 2.0 * C2[2] * y * s[6]
        gz += 4.0 * C2[2] * z * s[6]
        gx += C2[3] * z * s[7]
        gz += C2[3] * x * s[7]
        gx += 2.0 * C2[4] * x * s[8]
        gy -= 2.0 * C2[4] * y * s[8]
        if degree >= 3:
            gx += 6.0 * C3[0] * xy * s[9]
            gy += 3.0 * C3[0] * (xx - yy) * s[9]
            gx += C3[1] * yz * s[10]
            gy += C3[1] * xz * s[10]
            gz += C3[1] * xy * s[10]
            gx -= 2.0 * C3[2] * xy * s[11]
            gy += C3[2] * (4.0 * zz - xx - 3.0 * yy) * s[11]
            gz += 8.0 * C3[2] * yz * s[11]
            gx -= 6.0 * C3[3] * xz * s[12]
            gy -= 6.0 * C3[3] * yz * s[12]
            gz += C3[3] * (6.0 * zz - 3.0 * xx - 3.0 * yy) * s[12]
            gx += C3[4] * (4.0 * zz - 3.0 * xx - yy) * s[13]
            gy -= 2.0 * C3[4] * xy * s[13]
            gz += 8.0 * C3[4] * xz * s[13]
            gx += 2.0 * C3[5] * xz * s[14]
            gy -= 2.0 * C3[5] * yz * s[14]
            gz += C3[5] * (xx - yy) * s[14]
            gx += 3.0 * C3[6] * (xx - yy) * s[15]
            gy -= 6.0 * C3[6] * xy * s[15]
    return gx, gy, gz


@njit(parallel=True, **_JIT)
def sh_forward_kernel(dc, rest, directions, degree, rgb, basis):
    """``rgb[n]`` = max(basis(directions[n]) . coefficients[n, :k] + 0.5, 0), k = (degree + 1)^2, the
    coefficients being ``dc[n]`` [1, 3] then ``rest[n]`` [15, 3]; the basis values into ``basis[n, :k]``
    (float64 [N, 16], kept for the backward)."""
    k = (degree + 1) * (degree + 1)
    for n in prange(dc.shape[0]):
        b = basis[n]
        _basis(np.float64(directions[n, 0]), np.float64(directions[n, 1]), np.float64(directions[n, 2]), degree, b)
        for c in range(3):
            acc = 0.0 + b[0] * dc[n, 0, c]
            for j in range(1, k):
                acc += b[j] * rest[n, j - 1, c]
            value = acc + 0.5
            rgb[n, c] = value if value > 0.0 else 0.0


@njit(parallel=True, **_JIT)
def sh_backward_kernel(dc, rest, directions, degree, rgb, basis, grad_rgb, grad_dc, grad_rest, grad_directions,
                       scratch):
    """Gradients of the colour with respect to the coefficients (``grad_dc``, ``grad_rest``; zero beyond the
    degree's k) and to the direction components; ``rgb`` and ``basis`` are the forward's (the clamp passes the
    gradient where the sum is >= 0, so where the output is > 0 or the sum is exactly 0: recomputed here);
    ``scratch``: float64 [N, 16]."""
    k = (degree + 1) * (degree + 1)
    for n in prange(dc.shape[0]):
        b = basis[n]
        s = scratch[n]
        for j in range(k):
            s[j] = 0.0
        for c in range(3):
            gc = np.float64(grad_rgb[n, c])
            if rgb[n, c] <= 0.0:
                acc = 0.0 + b[0] * dc[n, 0, c]
                for j in range(1, k):
                    acc += b[j] * rest[n, j - 1, c]
                if acc + 0.5 < 0.0:
                    gc = 0.0
            grad_dc[n, 0, c] = b[0] * gc
            s[0] += gc * dc[n, 0, c]
            for j in range(1, k):
                grad_rest[n, j - 1, c] = b[j] * gc
                s[j] += gc * rest[n, j - 1, c]
            for j in range(max(k, 1) - 1, rest.shape[1]):
                grad_rest[n, j, c] = 0.0
        gx, gy, gz = _basis_gradient(
            np.float64(directions[n, 0]), np.float64(directions[n, 1]), np.float64(directions[n, 2]), degree, s
        )
        grad_directions[n, 0] = gx
        grad_directions[n, 1] = gy
        grad_directions[n, 2] = gz
