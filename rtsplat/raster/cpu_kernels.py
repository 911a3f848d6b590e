"""Numba kernels of the ``cpu`` rasterizer backend (see :mod:`rtsplat.raster.cpu`).

Imported lazily by :mod:`rtsplat.raster.cpu` on the first rasterization, never by ``import
rtsplat``: importing numba costs ~0.5 s and the first call compiles (or loads from the cache).

All arithmetic is float64. Per-surfel inputs (projected by :mod:`rtsplat.raster.projection`):

* ``M`` [N,9]: ray transform, row major (rows: x w, y w, w);
* ``centers`` [N,2]: projected centres (px); ``occ``/``opa`` [N]: occupancy / opacity;
* ``feats`` [N,Fc]: surface attributes (features, then camera-facing normals);
* ``colors`` [N,3]: volume radiance;
* ``rho_cut`` [N]: pairs with rho above it cannot reach ``alpha_min`` in either weight set (see
  :func:`rtsplat.raster.cpu.rho_cutoff`); they are skipped before the exponential;
* ``boxes`` [N,4]: pixel boxes outside which rho > ``rho_cut`` (see
  :func:`rtsplat.raster.cpu.contribution_boxes`); :func:`tile_entries_kernel` keeps per tile the
  entries whose box meets it (``keep``/``n_keep``), then each 4x4 pixel block of the tile the
  entries whose box meets the block (``n_done`` counts positions in that block list), and each
  pixel skips entries whose box it is outside of. The parallel work unit is one 4x4 block.

Per pixel output row (``out`` [H*W, Fc+9]), the layout of the reference backend:
``feats (Fc) | alpha | depth_sum | depth_median | distortion | color (3) | volume_alpha | volume_depth_sum``.

Per-surfel gradient row layout (``acc`` [threads, N, 16+Fc], one slice per thread indexed by
``numba.get_thread_id()`` so that threads never write the same memory, summed over threads by
:func:`sum_threads_kernel`): ``M (9) | centers (2) | occ | opa | colors (3) | feats (Fc)``.
"""

from __future__ import annotations

import math

import numpy as np
from numba import get_thread_id, njit, prange

G_M, G_CENTER, G_OCC, G_OPA, G_COLOR, G_FEAT = 0, 9, 11, 12, 13, 16

_JIT = dict(cache=True, nogil=True, error_model="numpy", fastmath=False)


@njit(inline="always", **_JIT)
def _eval_pair(M, centers, i, px, py, lowpass, edge_on_ratio):
    """Ray-splat intersection of surfel ``i`` at pixel centre (px, py): reference semantics."""
    m0 = M[i, 0]
    m1 = M[i, 1]
    m2 = M[i, 2]
    m3 = M[i, 3]
    m4 = M[i, 4]
    m5 = M[i, 5]
    m6 = M[i, 6]
    m7 = M[i, 7]
    m8 = M[i, 8]
    hx0 = m0 - px * m6
    hx1 = m1 - px * m7
    hx2 = m2 - px * m8
    hy0 = m3 - py * m6
    hy1 = m4 - py * m7
    hy2 = m5 - py * m8
    p0 = hx1 * hy2 - hx2 * hy1
    p1 = hx2 * hy0 - hx0 * hy2
    p2 = hx0 * hy1 - hx1 * hy0
    plane_ok = abs(p2) > edge_on_ratio * max(abs(p0), abs(p1))
    if plane_ok:
        u = p0 / p2
        v = p1 / p2
        rho3 = u * u + v * v
    else:
        u = 0.0
        v = 0.0
        rho3 = np.inf
    dx = centers[i, 0] - px
    dy = centers[i, 1] - py
    rho2 = lowpass * (dx * dx + dy * dy)
    use_plane = rho3 <= rho2
    if use_plane:
        rho = rho3
        z = u * m6 + v * m7 + m8
    else:
        rho = rho2
        z = m8
    return z, rho, use_plane, plane_ok, u, v, p2, dx, dy, hx0, hx1, hx2, hy0, hy1, hy2


@njit(parallel=True, **_JIT)
def tile_entries_kernel(ids, boxes, tile_start, tile_count, tiles_x, tile_size, keep, n_keep):
    """Per tile: the list positions (relative to the tile's start, depth order kept) of the surfels whose
    box meets the tile, written to ``keep[start:start + n_keep[t]]``."""
    for t in prange(tile_count.shape[0]):
        cnt = tile_count[t]
        start = tile_start[t]
        tx0 = (t % tiles_x) * tile_size
        ty0 = (t // tiles_x) * tile_size
        lo_x = tx0 + 0.5
        hi_x = tx0 + tile_size - 0.5
        lo_y = ty0 + 0.5
        hi_y = ty0 + tile_size - 0.5
        n = 0
        for k in range(cnt):
            i = ids[start + k]
            if boxes[i, 1] >= lo_x and boxes[i, 0] <= hi_x and boxes[i, 3] >= lo_y and boxes[i, 2] <= hi_y:
                keep[start + n] = k
                n += 1
        n_keep[t] = n


BLOCK = 4  # pixels per side of the sub-tile blocks whose entry lists each pixel scans


@njit(inline="always", **_JIT)
def _block_list(ids, boxes, start, keep, nk, tx0, ty0, tile_size, bx, by):
    """The tile entries (list positions relative to ``start``, depth order kept) whose box meets pixel
    block (bx, by) of the tile, and their count. A pixel scans only its block's list, so the long lists of
    small tiles full of small surfels are not walked once per pixel."""
    lo_y = ty0 + by * BLOCK + 0.5
    hi_y = ty0 + min((by + 1) * BLOCK, tile_size) - 0.5
    lo_x = tx0 + bx * BLOCK + 0.5
    hi_x = tx0 + min((bx + 1) * BLOCK, tile_size) - 0.5
    lst = np.empty(max(nk, 1), dtype=np.int64)
    n = 0
    for j in range(nk):
        k = keep[start + j]
        i = ids[start + k]
        if boxes[i, 1] >= lo_x and boxes[i, 0] <= hi_x and boxes[i, 3] >= lo_y and boxes[i, 2] <= hi_y:
            lst[n] = k
            n += 1
    return lst, n


@njit(parallel=True, **_JIT)
def forward_kernel(
    M,
    centers,
    occ,
    opa,
    feats,
    colors,
    ids,
    tile_start,
    tile_count,
    tiles_x,
    tile_size,
    width,
    height,
    near,
    far,
    alpha_max,
    alpha_min,
    t_min,
    lowpass,
    edge_on_ratio,
    rho_cut,
    boxes,
    keep,
    n_keep,
    out,
    stats,
    n_done,
    median_k,
    used,
):
    n_tiles = tile_count.shape[0]
    fc = feats.shape[1]
    ndc_scale = far / (far - near)
    nbx = (tile_size + BLOCK - 1) // BLOCK
    nb2 = nbx * nbx
    for unit in prange(n_tiles * nb2):
        t = unit // nb2
        nk = n_keep[t]
        if nk == 0:
            continue
        start = tile_start[t]
        tx0 = (t % tiles_x) * tile_size
        ty0 = (t // tiles_x) * tile_size
        by = (unit - t * nb2) // nbx
        bx = (unit - t * nb2) - by * nbx
        lst, n_scan = _block_list(ids, boxes, start, keep, nk, tx0, ty0, tile_size, bx, by)
        for ly in range(by * BLOCK, min((by + 1) * BLOCK, tile_size)):
            yi = ty0 + ly
            if yi >= height:
                break
            py = yi + 0.5
            for lx in range(bx * BLOCK, min((bx + 1) * BLOCK, tile_size)):
                xi = tx0 + lx
                if xi >= width:
                    break
                px = xi + 0.5
                pix = yi * width + xi
                T_s = 1.0
                T_v = 1.0
                live_s = True
                live_v = True
                A = 0.0
                dsum = 0.0
                med = 0.0
                medk = -1
                dist = 0.0
                S1 = 0.0
                S2 = 0.0
                c0 = 0.0
                c1 = 0.0
                c2 = 0.0
                Av = 0.0
                dvsum = 0.0
                done = n_scan
                for j in range(n_scan):
                    if not live_s and not live_v:
                        done = j
                        break
                    k = lst[j]
                    i = ids[start + k]
                    if px < boxes[i, 0] or px > boxes[i, 1] or py < boxes[i, 2] or py > boxes[i, 3]:
                        continue
                    z, rho, _, _, _, _, _, _, _, _, _, _, _, _, _ = _eval_pair(
                        M, centers, i, px, py, lowpass, edge_on_ratio
                    )
                    if z >= near and not (rho > rho_cut[i]):
                        gauss = math.exp(-0.5 * rho)
                        o = occ[i]
                        a_s = o * gauss
                        if a_s > alpha_max:
                            a_s = alpha_max
                        a_v = o * opa[i] * gauss
                        if a_v > alpha_max:
                            a_v = alpha_max
                        if live_s and a_s >= alpha_min:
                            t_next = T_s * (1.0 - a_s)
                            if t_next < t_min:
                                live_s = False
                            else:
                                w = a_s * T_s
                                for c in range(fc):
                                    out[pix, c] += w * feats[i, c]
                                m = ndc_scale * (1.0 - near / z)
                                dist += w * (m * m * A + S2 - 2.0 * m * S1)
                                A += w
                                S1 += w * m
                                S2 += w * m * m
                                dsum += w * z
                                if T_s > 0.5:
                                    med = z
                                    medk = k
                                T_s = t_next
                                used[start + k] = 1
                        if live_v and a_v >= alpha_min:
                            t_next = T_v * (1.0 - a_v)
                            if t_next < t_min:
                                live_v = False
                            else:
                                w = a_v * T_v
                                c0 += w * colors[i, 0]
                                c1 += w * colors[i, 1]
                                c2 += w * colors[i, 2]
                                Av += w
                                dvsum += w * z
                                T_v = t_next
                                used[start + k] = 1
                n_done[pix] = done
                median_k[pix] = medk
                out[pix, fc] = A
                out[pix, fc + 1] = dsum
                out[pix, fc + 2] = med
                out[pix, fc + 3] = dist
                out[pix, fc + 4] = c0
                out[pix, fc + 5] = c1
                out[pix, fc + 6] = c2
                out[pix, fc + 7] = Av
                out[pix, fc + 8] = dvsum
                stats[pix, 0] = S1
                stats[pix, 1] = S2


@njit(parallel=True, **_JIT)
def backward_kernel(
    M,
    centers,
    occ,
    opa,
    feats,
    colors,
    ids,
    tile_start,
    tile_count,
    tiles_x,
    tile_size,
    width,
    height,
    near,
    far,
    alpha_max,
    alpha_min,
    t_min,
    lowpass,
    edge_on_ratio,
    rho_cut,
    boxes,
    keep,
    n_keep,
    out,
    stats,
    n_done,
    median_k,
    grad_out,
    acc,
):
    """Accumulate dL/d(per-surfel inputs) per binned pair, replaying the forward front to back.

    For one weight set with weights w_k = a_k T_k and a per-pixel loss whose partial derivative
    with respect to w_k is q_k, dL/da_i = q_i T_i - (sum_{k>i} q_k w_k) / (1 - a_i); the suffix sum
    is Q - (prefix incl. i), with Q = sum_k q_k w_k computed from the forward totals.
    """
    n_tiles = tile_count.shape[0]
    fc = feats.shape[1]
    ndc_scale = far / (far - near)
    nbx = (tile_size + BLOCK - 1) // BLOCK
    nb2 = nbx * nbx
    for unit in prange(n_tiles * nb2):
        t = unit // nb2
        nk = n_keep[t]
        if nk == 0:
            continue
        start = tile_start[t]
        tx0 = (t % tiles_x) * tile_size
        ty0 = (t // tiles_x) * tile_size
        by = (unit - t * nb2) // nbx
        bx = (unit - t * nb2) - by * nbx
        lst, n_scan = _block_list(ids, boxes, start, keep, nk, tx0, ty0, tile_size, bx, by)
        tid = get_thread_id()
        for ly in range(by * BLOCK, min((by + 1) * BLOCK, tile_size)):
            yi = ty0 + ly
            if yi >= height:
                break
            py = yi + 0.5
            for lx in range(bx * BLOCK, min((bx + 1) * BLOCK, tile_size)):
                xi = tx0 + lx
                if xi >= width:
                    break
                px = xi + 0.5
                pix = yi * width + xi
                g_A = grad_out[pix, fc]
                g_dsum = grad_out[pix, fc + 1]
                g_med = grad_out[pix, fc + 2]
                g_dist = grad_out[pix, fc + 3]
                g_c0 = grad_out[pix, fc + 4]
                g_c1 = grad_out[pix, fc + 5]
                g_c2 = grad_out[pix, fc + 6]
                g_Av = grad_out[pix, fc + 7]
                g_dv = grad_out[pix, fc + 8]
                A = out[pix, fc]
                S1 = stats[pix, 0]
                S2 = stats[pix, 1]
                Q_s = g_A * A + g_dsum * out[pix, fc + 1] + g_dist * 2.0 * (A * S2 - S1 * S1)
                for c in range(fc):
                    Q_s += grad_out[pix, c] * out[pix, c]
                Q_v = (
                    g_c0 * out[pix, fc + 4]
                    + g_c1 * out[pix, fc + 5]
                    + g_c2 * out[pix, fc + 6]
                    + g_Av * out[pix, fc + 7]
                    + g_dv * out[pix, fc + 8]
                )
                medk = median_k[pix]
                P_s = 0.0
                P_v = 0.0
                T_s = 1.0
                T_v = 1.0
                live_s = True
                live_v = True
                for j in range(n_done[pix]):
                    k = lst[j]
                    i = ids[start + k]
                    if px < boxes[i, 0] or px > boxes[i, 1] or py < boxes[i, 2] or py > boxes[i, 3]:
                        continue
                    z, rho, use_plane, plane_ok, u, v, p2, dx, dy, hx0, hx1, hx2, hy0, hy1, hy2 = _eval_pair(
                        M, centers, i, px, py, lowpass, edge_on_ratio
                    )
                    if not (z >= near) or rho > rho_cut[i]:
                        continue
                    gauss = math.exp(-0.5 * rho)
                    o = occ[i]
                    op = opa[i]
                    raw_s = o * gauss
                    a_s = raw_s
                    if a_s > alpha_max:
                        a_s = alpha_max
                    oo = o * op
                    raw_v = oo * gauss
                    a_v = raw_v
                    if a_v > alpha_max:
                        a_v = alpha_max
                    g_z = 0.0
                    g_gauss = 0.0
                    touched = False
                    if live_s and a_s >= alpha_min:
                        t_next = T_s * (1.0 - a_s)
                        if t_next < t_min:
                            live_s = False
                        else:
                            touched = True
                            w = a_s * T_s
                            m = ndc_scale * (1.0 - near / z)
                            q = g_A + g_dsum * z + g_dist * (m * m * A - 2.0 * m * S1 + S2)
                            for c in range(fc):
                                q += grad_out[pix, c] * feats[i, c]
                                acc[tid, i, G_FEAT + c] += grad_out[pix, c] * w
                            P_s += q * w
                            g_a = q * T_s - (Q_s - P_s) / (1.0 - a_s)
                            g_z += g_dsum * w + g_dist * 2.0 * w * (m * A - S1) * (ndc_scale * near / (z * z))
                            if k == medk:
                                g_z += g_med
                            if raw_s <= alpha_max:
                                acc[tid, i, G_OCC] += g_a * gauss
                                g_gauss += g_a * o
                            T_s = t_next
                    if live_v and a_v >= alpha_min:
                        t_next = T_v * (1.0 - a_v)
                        if t_next < t_min:
                            live_v = False
                        else:
                            touched = True
                            w = a_v * T_v
                            q = g_Av + g_dv * z + g_c0 * colors[i, 0] + g_c1 * colors[i, 1] + g_c2 * colors[i, 2]
                            acc[tid, i, G_COLOR] += g_c0 * w
                            acc[tid, i, G_COLOR + 1] += g_c1 * w
                            acc[tid, i, G_COLOR + 2] += g_c2 * w
                            P_v += q * w
                            g_a = q * T_v - (Q_v - P_v) / (1.0 - a_v)
                            g_z += g_dv * w
                            if raw_v <= alpha_max:
                                g_oo = g_a * gauss
                                acc[tid, i, G_OCC] += g_oo * op
                                acc[tid, i, G_OPA] += g_oo * o
                                g_gauss += g_a * oo
                            T_v = t_next
                    if not touched:
                        continue
                    g_rho = -0.5 * gauss * g_gauss
                    if use_plane:
                        if plane_ok:
                            # z = u m6 + v m7 + m8 ; rho = u^2 + v^2
                            acc[tid, i, G_M + 6] += g_z * u
                            acc[tid, i, G_M + 7] += g_z * v
                            acc[tid, i, G_M + 8] += g_z
                            g_u = g_z * M[i, 6] + 2.0 * u * g_rho
                            g_v = g_z * M[i, 7] + 2.0 * v * g_rho
                            gp0 = g_u / p2
                            gp1 = g_v / p2
                            gp2 = -(g_u * u + g_v * v) / p2
                            # p = hx x hy: dL/dhx = hy x gp, dL/dhy = gp x hx
                            ghx0 = hy1 * gp2 - hy2 * gp1
                            ghx1 = hy2 * gp0 - hy0 * gp2
                            ghx2 = hy0 * gp1 - hy1 * gp0
                            ghy0 = gp1 * hx2 - gp2 * hx1
                            ghy1 = gp2 * hx0 - gp0 * hx2
                            ghy2 = gp0 * hx1 - gp1 * hx0
                            acc[tid, i, G_M + 0] += ghx0
                            acc[tid, i, G_M + 1] += ghx1
                            acc[tid, i, G_M + 2] += ghx2
                            acc[tid, i, G_M + 3] += ghy0
                            acc[tid, i, G_M + 4] += ghy1
                            acc[tid, i, G_M + 5] += ghy2
                            acc[tid, i, G_M + 6] -= px * ghx0 + py * ghy0
                            acc[tid, i, G_M + 7] -= px * ghx1 + py * ghy1
                            acc[tid, i, G_M + 8] -= px * ghx2 + py * ghy2
                        else:
                            acc[tid, i, G_M + 8] += g_z
                    else:
                        acc[tid, i, G_M + 8] += g_z
                        acc[tid, i, G_CENTER] += g_rho * lowpass * 2.0 * dx
                        acc[tid, i, G_CENTER + 1] += g_rho * lowpass * 2.0 * dy


@njit(parallel=True, **_JIT)
def sum_threads_kernel(acc, result):
    """``result[i] = sum over threads of acc[thread, i]`` (the backward's per-thread accumulators)."""
    n_threads = acc.shape[0]
    for i in prange(acc.shape[1]):
        for c in range(acc.shape[2]):
            total = 0.0
            for th in range(n_threads):
                total += acc[th, i, c]
            result[i, c] = total
