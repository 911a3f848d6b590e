"""Numba kernels of the ``cpu`` backend's frame around the compositing: surfel projection (forward
and backward) and tile binning (see :mod:`rtsplat.raster.cpu`).

They compute what :func:`rtsplat.raster.projection.project_surfels` and
:func:`rtsplat.raster.binning.bin_tiles` compute (those torch functions are their oracle), one pass
per surfel instead of some fifty tensor operations. Imported lazily, like
:mod:`rtsplat.raster.cpu_kernels`. All arithmetic is float64.

Projection inputs: ``means`` [N,3], ``quats`` [N,4] (w, x, y, z; normalised here as
``F.normalize(eps=1e-12)`` does), ``scales`` [N,2], ``probe`` [N,2] (the screen probe, pixels),
the camera's world-to-camera rotation ``R`` [3,3], translation ``t`` [3] and intrinsics ``K``
[3,3]. Per surfel, with ``r`` the surfel's rotation (columns: tangent u, tangent v, normal) and
``c = R mean + t``: ``M = K [R r_u s_u | R r_v s_v | c]`` with ``probe * c_z`` added to the first
two entries of its last column (row major, rows: x w, y w, w); ``centers`` = those two entries
over ``c_z``; ``depths`` = ``c_z``; ``normals`` = ``r_n`` flipped when ``(R r_n) . c > 0``.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

_JIT = dict(cache=True, nogil=True, error_model="numpy", fastmath=False)

QUAT_EPS = 1e-12  # F.normalize's eps
DEPTH_EPS = 1e-12  # centres divide by the depth only where |depth| is above this


@njit(inline="always", **_JIT)
def _rotation(qw, qx, qy, qz):
    """Rotation matrix (row major, 9 scalars) of the normalised quaternion (w, x, y, z)."""
    return (
        1.0 - 2.0 * (qy * qy + qz * qz), 2.0 * (qx * qy - qw * qz), 2.0 * (qx * qz + qw * qy),
        2.0 * (qx * qy + qw * qz), 1.0 - 2.0 * (qx * qx + qz * qz), 2.0 * (qy * qz - qw * qx),
        2.0 * (qx * qz - qw * qy), 2.0 * (qy * qz + qw * qx), 1.0 - 2.0 * (qx * qx + qy * qy),
    )


@njit(inline="always", **_JIT)
def _unit_quat(quats, n):
    """(w, x, y, z) / max(|q|, eps) and that divisor."""
    qw = quats[n, 0]
    qx = quats[n, 1]
    qy = quats[n, 2]
    qz = quats[n, 3]
    norm = math.sqrt(qw * qw + qx * qx + qy * qy + qz * qz)
    den = norm
    if den < QUAT_EPS:
        den = QUAT_EPS
    return qw / den, qx / den, qy / den, qz / den, den, norm


@njit(inline="always", **_JIT)
def _camera_centre(means, R, t, n):
    """Surfel ``n``'s centre in camera space, R mean + t."""
    p0 = means[n, 0]
    p1 = means[n, 1]
    p2 = means[n, 2]
    return (R[0, 0] * p0 + R[0, 1] * p1 + R[0, 2] * p2 + t[0], R[1, 0] * p0 + R[1, 1] * p1 + R[1, 2] * p2 + t[1],
            R[2, 0] * p0 + R[2, 1] * p1 + R[2, 2] * p2 + t[2])


@njit(inline="always", **_JIT)
def _rotate(R, a0, a1, a2):
    """R (a0, a1, a2): a surfel axis in camera space."""
    return (R[0, 0] * a0 + R[0, 1] * a1 + R[0, 2] * a2, R[1, 0] * a0 + R[1, 1] * a1 + R[1, 2] * a2,
            R[2, 0] * a0 + R[2, 1] * a1 + R[2, 2] * a2)


@njit(parallel=True, **_JIT)
def project_forward_kernel(means, quats, scales, probe, R, t, K, cutoff, lowpass_radius, near, width, height,
                           M, centers, depths, normals, bbox_min, bbox_max, radii, valid, flip):
    """Per surfel: the ray transform, centre, depth, camera-facing normal, screen box (the dual-conic
    box of :func:`rtsplat.raster.projection.ellipse_screen_box` widened to ``lowpass_radius``; the
    whole image when unbounded), radii (0 when not valid), validity and whether the normal was
    flipped (``flip``, read by the backward)."""
    c2 = cutoff * cutoff
    for n in prange(means.shape[0]):
        qw, qx, qy, qz, den, norm = _unit_quat(quats, n)
        r00, r01, r02, r10, r11, r12, r20, r21, r22 = _rotation(qw, qx, qy, qz)
        c0, c1, d = _camera_centre(means, R, t, n)
        su = scales[n, 0]
        sv = scales[n, 1]
        # camera-space tangents (scaled) and normal
        au0, au1, au2 = _rotate(R, r00, r10, r20)
        av0, av1, av2 = _rotate(R, r01, r11, r21)
        a0, a1, a2 = _rotate(R, r02, r12, r22)
        u0 = au0 * su
        u1 = au1 * su
        u2 = au2 * su
        v0 = av0 * sv
        v1 = av1 * sv
        v2 = av2 * sv
        for row in range(3):
            M[n, 3 * row] = K[row, 0] * u0 + K[row, 1] * u1 + K[row, 2] * u2
            M[n, 3 * row + 1] = K[row, 0] * v0 + K[row, 1] * v1 + K[row, 2] * v2
            M[n, 3 * row + 2] = K[row, 0] * c0 + K[row, 1] * c1 + K[row, 2] * d
        M[n, 2] += probe[n, 0] * d
        M[n, 5] += probe[n, 1] * d
        depths[n] = d
        ds = d if abs(d) > DEPTH_EPS else 1.0
        centers[n, 0] = M[n, 2] / ds
        centers[n, 1] = M[n, 5] / ds
        away = a0 * c0 + a1 * c1 + a2 * d > 0.0
        flip[n] = away
        sign = -1.0 if away else 1.0
        normals[n, 0] = sign * r02
        normals[n, 1] = sign * r12
        normals[n, 2] = sign * r22
        # screen box of the ellipse u^2 + v^2 = cutoff^2 (dual conic M diag(c2, c2, -1) M^T)
        w0 = M[n, 6]
        w1 = M[n, 7]
        w2 = M[n, 8]
        dw = c2 * w0 * w0 + c2 * w1 * w1 - w2 * w2
        bounded = dw < 0.0
        dd = dw if bounded else -1.0
        inside = d > near
        all_finite = True
        for axis in range(2):
            x0 = M[n, 3 * axis]
            x1 = M[n, 3 * axis + 1]
            x2 = M[n, 3 * axis + 2]
            center = (c2 * x0 * w0 + c2 * x1 * w1 - x2 * w2) / dd
            second = (c2 * x0 * x0 + c2 * x1 * x1 - x2 * x2) / dd
            ext = center * center - second
            if ext < 1e-4:
                ext = 1e-4
            ext = math.sqrt(ext)
            if ext < lowpass_radius:
                ext = lowpass_radius
            size = width if axis == 0 else height
            if bounded:
                lo = center - ext
                hi = center + ext
                rad = np.ceil(ext) if ext - ext == 0.0 else 0.0
            else:
                lo = 0.0
                hi = float(size)
                rad = float(size)
            bbox_min[n, axis] = lo
            bbox_max[n, axis] = hi
            all_finite = all_finite and lo - lo == 0.0 and hi - hi == 0.0
            inside = inside and hi > 0.0 and lo < size
            radii[n, axis] = int(min(rad, 2147483647.0))
        ok = inside and all_finite
        valid[n] = ok
        if not ok:
            radii[n, 0] = 0
            radii[n, 1] = 0


@njit(parallel=True, **_JIT)
def project_backward_kernel(means, quats, scales, probe, R, t, K, flip, g_M, g_centers, g_depths, g_normals,
                            g_means, g_quats, g_scales, g_probe, g_camera):
    """Gradients of :func:`project_forward_kernel`'s differentiable outputs (M, centres, depths,
    normals) with respect to means, quats, scales and the probe, and per surfel its share of the
    camera's (``g_camera`` [N,12]: dL/dR row major, then dL/dt; the caller sums the rows)."""
    for n in prange(means.shape[0]):
        qw, qx, qy, qz, den, norm = _unit_quat(quats, n)
        r00, r01, r02, r10, r11, r12, r20, r21, r22 = _rotation(qw, qx, qy, qz)
        c0, c1, d = _camera_centre(means, R, t, n)
        p0 = means[n, 0]
        p1 = means[n, 1]
        p2 = means[n, 2]
        su = scales[n, 0]
        sv = scales[n, 1]
        # homogeneous centre after the probe: the centre's gradient needs it
        hx = K[0, 0] * c0 + K[0, 1] * c1 + K[0, 2] * d + probe[n, 0] * d
        hy = K[1, 0] * c0 + K[1, 1] * c1 + K[1, 2] * d + probe[n, 1] * d
        # gradient of the homogeneous centre (M's last column) and of the depth
        gh0 = g_M[n, 2]
        gh1 = g_M[n, 5]
        gh2 = g_M[n, 8]
        gd = g_depths[n]
        if abs(d) > DEPTH_EPS:
            gh0 += g_centers[n, 0] / d
            gh1 += g_centers[n, 1] / d
            gd -= (g_centers[n, 0] * hx + g_centers[n, 1] * hy) / (d * d)
        else:
            gh0 += g_centers[n, 0]
            gh1 += g_centers[n, 1]
        g_probe[n, 0] = gh0 * d
        g_probe[n, 1] = gh1 * d
        gd += gh0 * probe[n, 0] + gh1 * probe[n, 1]
        # c = R p + t, K c = (first two entries before the probe, last entry)
        gc0 = K[0, 0] * gh0 + K[1, 0] * gh1 + K[2, 0] * gh2
        gc1 = K[0, 1] * gh0 + K[1, 1] * gh1 + K[2, 1] * gh2
        gc2 = K[0, 2] * gh0 + K[1, 2] * gh1 + K[2, 2] * gh2 + gd
        g_means[n, 0] = R[0, 0] * gc0 + R[1, 0] * gc1 + R[2, 0] * gc2
        g_means[n, 1] = R[0, 1] * gc0 + R[1, 1] * gc1 + R[2, 1] * gc2
        g_means[n, 2] = R[0, 2] * gc0 + R[1, 2] * gc1 + R[2, 2] * gc2
        # tangents: M[:, 0] = K (R r_u) s_u, M[:, 1] = K (R r_v) s_v
        gtu0 = K[0, 0] * g_M[n, 0] + K[1, 0] * g_M[n, 3] + K[2, 0] * g_M[n, 6]
        gtu1 = K[0, 1] * g_M[n, 0] + K[1, 1] * g_M[n, 3] + K[2, 1] * g_M[n, 6]
        gtu2 = K[0, 2] * g_M[n, 0] + K[1, 2] * g_M[n, 3] + K[2, 2] * g_M[n, 6]
        gtv0 = K[0, 0] * g_M[n, 1] + K[1, 0] * g_M[n, 4] + K[2, 0] * g_M[n, 7]
        gtv1 = K[0, 1] * g_M[n, 1] + K[1, 1] * g_M[n, 4] + K[2, 1] * g_M[n, 7]
        gtv2 = K[0, 2] * g_M[n, 1] + K[1, 2] * g_M[n, 4] + K[2, 2] * g_M[n, 7]
        au0, au1, au2 = _rotate(R, r00, r10, r20)
        av0, av1, av2 = _rotate(R, r01, r11, r21)
        g_scales[n, 0] = au0 * gtu0 + au1 * gtu1 + au2 * gtu2
        g_scales[n, 1] = av0 * gtv0 + av1 * gtv1 + av2 * gtv2
        gau0 = gtu0 * su
        gau1 = gtu1 * su
        gau2 = gtu2 * su
        gav0 = gtv0 * sv
        gav1 = gtv1 * sv
        gav2 = gtv2 * sv
        # the camera: c = R p + t, a_u = R r_u, a_v = R r_v
        for a in range(3):
            ga_c = gc0 if a == 0 else (gc1 if a == 1 else gc2)
            ga_u = gau0 if a == 0 else (gau1 if a == 1 else gau2)
            ga_v = gav0 if a == 0 else (gav1 if a == 1 else gav2)
            g_camera[n, 3 * a] = ga_c * p0 + ga_u * r00 + ga_v * r01
            g_camera[n, 3 * a + 1] = ga_c * p1 + ga_u * r10 + ga_v * r11
            g_camera[n, 3 * a + 2] = ga_c * p2 + ga_u * r20 + ga_v * r21
        g_camera[n, 9] = gc0
        g_camera[n, 10] = gc1
        g_camera[n, 11] = gc2
        # the surfel's rotation r (row major g_rij): columns u and v from the tangents, n from the normals
        g00 = R[0, 0] * gau0 + R[1, 0] * gau1 + R[2, 0] * gau2
        g10 = R[0, 1] * gau0 + R[1, 1] * gau1 + R[2, 1] * gau2
        g20 = R[0, 2] * gau0 + R[1, 2] * gau1 + R[2, 2] * gau2
        g01 = R[0, 0] * gav0 + R[1, 0] * gav1 + R[2, 0] * gav2
        g11 = R[0, 1] * gav0 + R[1, 1] * gav1 + R[2, 1] * gav2
        g21 = R[0, 2] * gav0 + R[1, 2] * gav1 + R[2, 2] * gav2
        sign = -1.0 if flip[n] else 1.0
        g02 = sign * g_normals[n, 0]
        g12 = sign * g_normals[n, 1]
        g22 = sign * g_normals[n, 2]
        # through the rotation matrix of the unit quaternion
        gw = 2.0 * (-qz * g01 + qy * g02 + qz * g10 - qx * g12 - qy * g20 + qx * g21)
        gx = 2.0 * (qy * g01 + qz * g02 + qy * g10 - 2.0 * qx * g11 - qw * g12 + qz * g20 + qw * g21
                    - 2.0 * qx * g22)
        gy = 2.0 * (-2.0 * qy * g00 + qx * g01 + qw * g02 + qx * g10 + qz * g12 - qw * g20 + qz * g21
                    - 2.0 * qy * g22)
        gz = 2.0 * (-2.0 * qz * g00 - qw * g01 + qx * g02 + qw * g10 - 2.0 * qz * g11 + qy * g12 + qx * g20
                    + qy * g21)
        # through the normalisation q / max(|q|, eps)
        if norm < QUAT_EPS:
            g_quats[n, 0] = gw / den
            g_quats[n, 1] = gx / den
            g_quats[n, 2] = gy / den
            g_quats[n, 3] = gz / den
        else:
            dot = qw * gw + qx * gx + qy * gy + qz * gz
            g_quats[n, 0] = (gw - qw * dot) / den
            g_quats[n, 1] = (gx - qx * dot) / den
            g_quats[n, 2] = (gy - qy * dot) / den
            g_quats[n, 3] = (gz - qz * dot) / den


@njit(**_JIT)
def depth_order_kernel(depths, valid):
    """The valid surfels sorted by depth, ties in index order (a stable LSD radix sort of the depths'
    float64 bit patterns, 8 bits per pass; passes whose digit is the same for every key are skipped).
    Valid depths are positive (beyond the near plane), whose bit patterns order as the numbers do."""
    bits = depths.view(np.uint64)
    n = 0
    for s in range(depths.shape[0]):
        if valid[s]:
            n += 1
    ids = np.empty(n, dtype=np.int64)
    keys = np.empty(n, dtype=np.uint64)
    j = 0
    for s in range(depths.shape[0]):
        if valid[s]:
            ids[j] = s
            keys[j] = bits[s]
            j += 1
    ids_tmp = np.empty(n, dtype=np.int64)
    keys_tmp = np.empty(n, dtype=np.uint64)
    count = np.zeros(257, dtype=np.int64)
    for shift in range(0, 64, 8):
        count[:] = 0
        for j in range(n):
            count[((keys[j] >> np.uint64(shift)) & np.uint64(255)) + 1] += 1
        if n == 0 or np.max(count) == n:
            continue
        for b in range(256):
            count[b + 1] += count[b]
        for j in range(n):
            b = (keys[j] >> np.uint64(shift)) & np.uint64(255)
            at = count[b]
            count[b] = at + 1
            keys_tmp[at] = keys[j]
            ids_tmp[at] = ids[j]
        keys, keys_tmp = keys_tmp, keys
        ids, ids_tmp = ids_tmp, ids
    return ids


@njit(**_JIT)
def bin_tiles_kernel(order, bbox_min, bbox_max, tile_size, tiles_x, tiles_y, tile_count, tile_start):
    """The surfels of ``order`` (valid, sorted by depth) in each tile their box touches, tiles in
    order and each tile's surfels in the order of ``order``: a counting sort, the same lists as
    :func:`rtsplat.raster.binning.bin_tiles`. Fills ``tile_count``/``tile_start``; returns the ids."""
    n = order.shape[0]
    lo_x = np.empty(n, dtype=np.int64)
    hi_x = np.empty(n, dtype=np.int64)
    lo_y = np.empty(n, dtype=np.int64)
    hi_y = np.empty(n, dtype=np.int64)
    tile_count[:] = 0
    for j in range(n):
        s = order[j]
        lo_x[j] = _tile_index(bbox_min[s, 0], tile_size, tiles_x)
        hi_x[j] = _tile_index(bbox_max[s, 0], tile_size, tiles_x)
        lo_y[j] = _tile_index(bbox_min[s, 1], tile_size, tiles_y)
        hi_y[j] = _tile_index(bbox_max[s, 1], tile_size, tiles_y)
        for ty in range(lo_y[j], hi_y[j] + 1):
            for tx in range(lo_x[j], hi_x[j] + 1):
                tile_count[ty * tiles_x + tx] += 1
    total = 0
    for k in range(tile_count.shape[0]):
        tile_start[k] = total
        total += tile_count[k]
    cursor = tile_start.copy()
    ids = np.empty(total, dtype=np.int64)
    for j in range(n):
        s = order[j]
        for ty in range(lo_y[j], hi_y[j] + 1):
            for tx in range(lo_x[j], hi_x[j] + 1):
                k = ty * tiles_x + tx
                ids[cursor[k]] = s
                cursor[k] += 1
    return ids


@njit(inline="always", **_JIT)
def _tile_index(x, tile_size, tiles):
    """floor(x / tile_size) clamped to [0, tiles - 1] (clamped before the integer conversion)."""
    f = np.floor(x / tile_size)
    if f < 0.0:
        return 0
    if f > tiles - 1:
        return tiles - 1
    return int(f)
