"""Numba kernels of the specular pass's per-pixel inputs (:class:`rtsplat.model.specular_inputs.SpecularInputs`).

Imported lazily (through :func:`rtsplat.raster.numba_runtime.load_numba_module`), never by ``import rtsplat``. One
shaded pixel (row) per iteration, on the calling thread (a few thousand rows: less work than starting a parallel
loop), in float64. For the pixel ``p = idx[m]`` of row ``m``:

* the angle of incidence: ``d = i . n`` (``i`` the unit pixel ray, ``n`` the blended normal), ``|cos| = min(|d|, 1)``;
* the reflected direction ``normalize(i - 2 d n)``;
* the roughness and the reflectance, the blended channel over the surface alpha clamped to [0, 1];
* the material feature, normalised.

``normalize(x)`` is ``x / max(|x|, 1e-12)``, as ``torch.nn.functional.normalize``. The backward is the chain rule
of the same expressions, with torch's conventions where a function has a kink: a clamp passes the gradient where
its input lies within the bounds, ends included; ``|d|`` passes ``sign(d)`` (0 at 0); a norm at or below 1e-12
divides the gradient by 1e-12. A NaN input gives NaN outputs and gradients in its row only.
"""

from __future__ import annotations

import math

from numba import njit

_JIT = dict(cache=True, nogil=True, error_model="numpy", fastmath=False)

EPS = 1e-12  # torch.nn.functional.normalize's


@njit(inline="always", **_JIT)
def _clamp01(v):
    """v clamped to [0, 1]; NaN stays NaN."""
    if v < 0.0:
        return 0.0
    if v > 1.0:
        return 1.0
    return v


@njit(inline="always", **_JIT)
def _norm_or_eps(x0, x1, x2, x3, width):
    n = math.sqrt(x0 * x0 + x1 * x1 + x2 * x2 + (x3 * x3 if width == 4 else 0.0))
    return n if n > EPS or math.isnan(n) else EPS


@njit(**_JIT)
def specular_inputs_kernel(idx, rays, normal, rough, material, refl, alpha, reflected, cos_incidence, rough_out,
                           material_out, refl_out):
    """Rows m of ``idx`` [N] (pixels of the flattened image) from ``rays``, ``normal`` [P, 3], ``rough``,
    ``refl``, ``alpha`` [P] and ``material`` [P, 4]: ``reflected`` [N, 3], ``cos_incidence`` [N],
    ``rough_out``, ``refl_out`` [N] and ``material_out`` [N, 4]."""
    for m in range(idx.shape[0]):
        p = idx[m]
        i0, i1, i2 = float(rays[p, 0]), float(rays[p, 1]), float(rays[p, 2])
        n0, n1, n2 = float(normal[p, 0]), float(normal[p, 1]), float(normal[p, 2])
        d = i0 * n0 + i1 * n1 + i2 * n2
        cos_incidence[m] = min(abs(d), 1.0) if not math.isnan(d) else d
        r0, r1, r2 = i0 - 2.0 * d * n0, i1 - 2.0 * d * n1, i2 - 2.0 * d * n2
        length = _norm_or_eps(r0, r1, r2, 0.0, 3)
        reflected[m, 0] = r0 / length
        reflected[m, 1] = r1 / length
        reflected[m, 2] = r2 / length
        a = float(alpha[p])
        rough_out[m] = _clamp01(float(rough[p]) / a)
        refl_out[m] = _clamp01(float(refl[p]) / a)
        x0, x1, x2, x3 = float(material[p, 0]), float(material[p, 1]), float(material[p, 2]), float(material[p, 3])
        length = _norm_or_eps(x0, x1, x2, x3, 4)
        material_out[m, 0] = x0 / length
        material_out[m, 1] = x1 / length
        material_out[m, 2] = x2 / length
        material_out[m, 3] = x3 / length


@njit(inline="always", **_JIT)
def _ratio_grad(value, a, grad):
    """The gradients of ``value`` and ``a`` from ``grad``, that of ``clamp(value / a, 0, 1)``: the clamp passes it
    where the ratio lies in [0, 1], ends included (not at NaN), as torch's clamp does."""
    v = value / a
    g_v = grad if 0.0 <= v <= 1.0 else 0.0
    return g_v / a, -g_v * value / (a * a)


@njit(**_JIT)
def specular_inputs_grad_kernel(idx, rays, normal, rough, material, refl, alpha, g_reflected, g_cos, g_rough,
                                g_material, g_refl, d_normal, d_rough, d_material, d_refl, d_alpha):
    """The gradients of :func:`specular_inputs_kernel`'s inputs from those of its outputs (``g_*``, per row), written
    to the pixel rows of ``d_normal`` [P, 3], ``d_rough``, ``d_refl``, ``d_alpha`` [P] and ``d_material`` [P, 4]
    (the rows of ``idx`` are distinct; the other rows are left as they are)."""
    for m in range(idx.shape[0]):
        p = idx[m]
        i0, i1, i2 = float(rays[p, 0]), float(rays[p, 1]), float(rays[p, 2])
        n0, n1, n2 = float(normal[p, 0]), float(normal[p, 1]), float(normal[p, 2])
        d = i0 * n0 + i1 * n1 + i2 * n2
        r0, r1, r2 = i0 - 2.0 * d * n0, i1 - 2.0 * d * n1, i2 - 2.0 * d * n2
        length = math.sqrt(r0 * r0 + r1 * r1 + r2 * r2)
        g0, g1, g2 = float(g_reflected[m, 0]), float(g_reflected[m, 1]), float(g_reflected[m, 2])
        if length > EPS or math.isnan(length):  # y = r / |r|: dr = (g - y (y . g)) / |r|
            y0, y1, y2 = r0 / length, r1 / length, r2 / length
            yg = y0 * g0 + y1 * g1 + y2 * g2
            h0, h1, h2 = (g0 - y0 * yg) / length, (g1 - y1 * yg) / length, (g2 - y2 * yg) / length
        else:  # y = r / eps
            h0, h1, h2 = g0 / EPS, g1 / EPS, g2 / EPS
        # r = i - 2 d n: dn = -2 d h, dd = -2 h . n
        g_d = -2.0 * (h0 * n0 + h1 * n1 + h2 * n2)
        a_d = abs(d)
        if a_d <= 1.0 or math.isnan(d):  # |cos| = min(|d|, 1)
            sign = 1.0 if d > 0.0 else (-1.0 if d < 0.0 else (0.0 if d == 0.0 else d))
            g_d += float(g_cos[m]) * sign
        # d = i . n
        d_normal[p, 0] = -2.0 * d * h0 + g_d * i0
        d_normal[p, 1] = -2.0 * d * h1 + g_d * i1
        d_normal[p, 2] = -2.0 * d * h2 + g_d * i2
        a = float(alpha[p])
        d_rough[p], g_a = _ratio_grad(float(rough[p]), a, float(g_rough[m]))
        d_refl[p], g_b = _ratio_grad(float(refl[p]), a, float(g_refl[m]))
        d_alpha[p] = g_a + g_b
        x0, x1, x2, x3 = float(material[p, 0]), float(material[p, 1]), float(material[p, 2]), float(material[p, 3])
        length = math.sqrt(x0 * x0 + x1 * x1 + x2 * x2 + x3 * x3)
        q0, q1, q2, q3 = (float(g_material[m, 0]), float(g_material[m, 1]), float(g_material[m, 2]),
                          float(g_material[m, 3]))
        if length > EPS or math.isnan(length):
            y0, y1, y2, y3 = x0 / length, x1 / length, x2 / length, x3 / length
            yg = y0 * q0 + y1 * q1 + y2 * q2 + y3 * q3
            d_material[p, 0] = (q0 - y0 * yg) / length
            d_material[p, 1] = (q1 - y1 * yg) / length
            d_material[p, 2] = (q2 - y2 * yg) / length
            d_material[p, 3] = (q3 - y3 * yg) / length
        else:
            d_material[p, 0] = q0 / EPS
            d_material[p, 1] = q1 / EPS
            d_material[p, 2] = q2 / EPS
            d_material[p, 3] = q3 / EPS
