"""Triton kernels of the ``triton`` rasterizer backend (see :mod:`rtsplat.raster.gpu`).

Imported lazily by :mod:`rtsplat.raster.gpu` on the first rasterization, never by ``import rtsplat``.
``triton.jit`` decides at import whether the kernels run compiled (CUDA tensors) or in Triton's
interpreter (``TRITON_INTERPRET=1`` set before this module is first imported; CPU tensors).

One program per screen tile; its lanes are the tile's pixels (``PIX`` = TILE x TILE rounded up to a
power of two, the extra lanes masked). All lanes walk the tile's depth-sorted list together, one
surfel per step, so every per-surfel value is a scalar load shared by the whole tile.

Per-surfel inputs, in the compute dtype ``DTYPE`` (float32, or float64 for float64 inputs):

* ``M`` [N,9] ray transforms, row major (rows: x w, y w, w); ``centers`` [N,2] projected centres (px);
* ``occ``/``opa`` [N] occupancy / opacity; ``feats`` [N,fc] surface attributes (features, then
  camera-facing normals); ``colors`` [N,3] volume radiance;
* ``params`` [7]: near, far, alpha_max, alpha_min, transmittance_min, lowpass_inv_var, edge-on ratio
  (a tensor, so that float64 runs compare against float64 thresholds).

Binned lists (int32): ``ids`` [pairs] surfel of each (tile, surfel) pair, sorted by tile then depth;
``tile_start``/``tile_count`` [tiles].

Per-pixel outputs (rows of the image, ``pix = y * width + x``):

* ``out`` [H*W, fc+9]: ``feats (fc) | alpha | depth_sum | depth_median | distortion | color (3) |
  volume_alpha | volume_depth_sum`` (the reference's channel order);
* ``aux`` [H*W, 4]: final surface and volume transmittance, sum w m, sum w m^2 (m = NDC depth);
* ``stops`` [H*W, 3] int32: per weight set the list position where it stopped (the first surfel it
  did not composite because the transmittance would drop below the cut; the list length when it
  never stopped), and the list position of the median-depth surfel (-1: none);
* ``used`` [pairs] int8: the pair contributed to at least one pixel of the image (either set).

Gradient rows (``grad`` [N, 16+fc], summed over tiles with one atomic add per surfel, tile and entry):
``M (9) | centers (2) | occ | opa | colors (3) | feats (fc)``.
"""

from __future__ import annotations

import triton
import triton.language as tl

# gradient row layout (offsets of M, centers, occ, opa, colors, feats), shared with rtsplat.raster.gpu
G_M = tl.constexpr(0)
G_CENTER = tl.constexpr(9)
G_OCC = tl.constexpr(11)
G_OPA = tl.constexpr(12)
G_COLOR = tl.constexpr(13)
G_FEAT = tl.constexpr(16)
LIVE_CHECK = tl.constexpr(8)


@triton.jit
def _pair(M_ptr, centers_ptr, i, px, py, lowpass, edge_on_ratio):
    """Ray-splat intersection of surfel ``i`` at the lanes' pixel centres: the reference semantics."""
    base = M_ptr + i * 9
    m0 = tl.load(base + 0)
    m1 = tl.load(base + 1)
    m2 = tl.load(base + 2)
    m3 = tl.load(base + 3)
    m4 = tl.load(base + 4)
    m5 = tl.load(base + 5)
    m6 = tl.load(base + 6)
    m7 = tl.load(base + 7)
    m8 = tl.load(base + 8)
    hx0 = m0 - px * m6
    hx1 = m1 - px * m7
    hx2 = m2 - px * m8
    hy0 = m3 - py * m6
    hy1 = m4 - py * m7
    hy2 = m5 - py * m8
    p0 = hx1 * hy2 - hx2 * hy1
    p1 = hx2 * hy0 - hx0 * hy2
    p2 = hx0 * hy1 - hx1 * hy0
    plane_ok = tl.abs(p2) > edge_on_ratio * tl.maximum(tl.abs(p0), tl.abs(p1))
    p2_safe = tl.where(plane_ok, p2, 1.0)
    u = tl.where(plane_ok, p0 / p2_safe, 0.0)
    v = tl.where(plane_ok, p1 / p2_safe, 0.0)
    rho3 = tl.where(plane_ok, u * u + v * v, float("inf"))
    dx = tl.load(centers_ptr + i * 2) - px
    dy = tl.load(centers_ptr + i * 2 + 1) - py
    rho2 = lowpass * (dx * dx + dy * dy)
    use_plane = rho3 <= rho2
    rho = tl.where(use_plane, rho3, rho2)
    z = tl.where(use_plane, u * m6 + v * m7 + m8, m8)
    return (z, rho, use_plane, plane_ok, u, v, p2_safe, dx, dy, hx0, hx1, hx2, hy0, hy1, hy2, m6, m7)


@triton.jit
def forward_kernel(
    M_ptr, centers_ptr, occ_ptr, opa_ptr, feats_ptr, colors_ptr,
    ids_ptr, tile_start_ptr, tile_count_ptr, params_ptr,
    out_ptr, aux_ptr, stops_ptr, used_ptr,
    tiles_x, width, height, fc,
    TILE: tl.constexpr, PIX: tl.constexpr, FCP: tl.constexpr, DTYPE: tl.constexpr,
):
    t = tl.program_id(0)
    cnt = tl.load(tile_count_ptr + t)
    start = tl.load(tile_start_ptr + t)
    near = tl.load(params_ptr + 0)
    far = tl.load(params_ptr + 1)
    alpha_max = tl.load(params_ptr + 2)
    alpha_min = tl.load(params_ptr + 3)
    t_min = tl.load(params_ptr + 4)
    lowpass = tl.load(params_ptr + 5)
    edge_on_ratio = tl.load(params_ptr + 6)
    ndc_scale = far / (far - near)

    lane = tl.arange(0, PIX)
    xi = (t % tiles_x) * TILE + lane % TILE
    yi = (t // tiles_x) * TILE + lane // TILE
    inside = (lane < TILE * TILE) & (xi < width) & (yi < height)
    pix = yi * width + xi
    px = xi.to(DTYPE) + 0.5
    py = yi.to(DTYPE) + 0.5
    ch = tl.arange(0, FCP)
    ch_ok = ch < fc

    zero = tl.zeros([PIX], DTYPE)
    T_s = zero + 1.0
    T_v = zero + 1.0
    live_s = inside
    live_v = inside
    stop_s = tl.where(inside, cnt, 0)
    stop_v = tl.where(inside, cnt, 0)
    median_k = tl.full([PIX], -1, tl.int32)
    feat_acc = tl.zeros([PIX, FCP], DTYPE)
    A = zero
    S1 = zero
    S2 = zero
    dist = zero
    depth_sum = zero
    median = zero
    c0 = zero
    c1 = zero
    c2 = zero
    A_v = zero
    depth_sum_v = zero

    j = 0
    pair_lanes = tl.zeros([PIX], tl.int32)
    any_live = cnt > 0
    go = any_live
    # front to back; ends when the list ends or both sets of every lane have stopped (checked every
    # LIVE_CHECK steps: the check is a reduction over the tile, and extra steps composite nothing)
    while go:
        i = tl.load(ids_ptr + start + j)
        z, rho, _, _, _, _, _, _, _, _, _, _, _, _, _, _, _ = _pair(
            M_ptr, centers_ptr, i, px, py, lowpass, edge_on_ratio
        )
        gauss = tl.exp(-0.5 * rho)
        o = tl.load(occ_ptr + i)
        # clamp with where, not minimum: a NaN alpha stays NaN and fails the alpha_min test (reference)
        a_s = o * gauss
        a_s = tl.where(a_s > alpha_max, alpha_max, a_s)
        a_v = o * tl.load(opa_ptr + i) * gauss
        a_v = tl.where(a_v > alpha_max, alpha_max, a_v)
        z_ok = z >= near
        z = tl.where(z_ok, z, near)
        m = ndc_scale * (1.0 - near / z)

        # surface set
        hit_s = live_s & z_ok & (a_s >= alpha_min)
        next_s = T_s * (1.0 - a_s)
        fail_s = hit_s & (next_s < t_min)
        comp_s = hit_s & (next_s >= t_min)
        stop_s = tl.where(fail_s, j, stop_s)
        live_s = live_s & (fail_s == 0)
        w = tl.where(comp_s, a_s * T_s, 0.0)
        f = tl.load(feats_ptr + i * fc + ch, mask=ch_ok, other=0.0)
        feat_acc += w[:, None] * f[None, :]
        dist += w * (m * m * A + S2 - 2.0 * m * S1)
        A += w
        S1 += w * m
        S2 += w * m * m
        depth_sum += w * z
        at_median = comp_s & (T_s > 0.5)
        median = tl.where(at_median, z, median)
        median_k = tl.where(at_median, j, median_k)
        T_s = tl.where(comp_s, next_s, T_s)

        # volume set
        hit_v = live_v & z_ok & (a_v >= alpha_min)
        next_v = T_v * (1.0 - a_v)
        fail_v = hit_v & (next_v < t_min)
        comp_v = hit_v & (next_v >= t_min)
        stop_v = tl.where(fail_v, j, stop_v)
        live_v = live_v & (fail_v == 0)
        w = tl.where(comp_v, a_v * T_v, 0.0)
        c0 += w * tl.load(colors_ptr + i * 3)
        c1 += w * tl.load(colors_ptr + i * 3 + 1)
        c2 += w * tl.load(colors_ptr + i * 3 + 2)
        A_v += w
        depth_sum_v += w * z
        T_v = tl.where(comp_v, next_v, T_v)

        # every lane that composited the pair writes the same flag: no reduction needed
        tl.store(used_ptr + start + j + pair_lanes, 1, mask=comp_s | comp_v)
        j += 1
        if j % LIVE_CHECK == 0:
            any_live = tl.max((live_s | live_v).to(tl.int32), axis=0) > 0
        go = (j < cnt) & any_live

    row = fc + 9
    tl.store(out_ptr + pix[:, None] * row + ch[None, :], feat_acc, mask=inside[:, None] & ch_ok[None, :])
    base = out_ptr + pix * row + fc
    tl.store(base + 0, A, mask=inside)
    tl.store(base + 1, depth_sum, mask=inside)
    tl.store(base + 2, median, mask=inside)
    tl.store(base + 3, dist, mask=inside)
    tl.store(base + 4, c0, mask=inside)
    tl.store(base + 5, c1, mask=inside)
    tl.store(base + 6, c2, mask=inside)
    tl.store(base + 7, A_v, mask=inside)
    tl.store(base + 8, depth_sum_v, mask=inside)
    tl.store(aux_ptr + pix * 4 + 0, T_s, mask=inside)
    tl.store(aux_ptr + pix * 4 + 1, T_v, mask=inside)
    tl.store(aux_ptr + pix * 4 + 2, S1, mask=inside)
    tl.store(aux_ptr + pix * 4 + 3, S2, mask=inside)
    tl.store(stops_ptr + pix * 3 + 0, stop_s, mask=inside)
    tl.store(stops_ptr + pix * 3 + 1, stop_v, mask=inside)
    tl.store(stops_ptr + pix * 3 + 2, median_k, mask=inside)


@triton.jit
def backward_kernel(
    M_ptr, centers_ptr, occ_ptr, opa_ptr, feats_ptr, colors_ptr,
    ids_ptr, tile_start_ptr, tile_count_ptr, params_ptr,
    out_ptr, aux_ptr, stops_ptr, grad_out_ptr, grad_ptr,
    tiles_x, width, height, fc,
    TILE: tl.constexpr, PIX: tl.constexpr, FCP: tl.constexpr, DTYPE: tl.constexpr,
):
    """dL/d(per-surfel inputs), walking each tile's list back to front (2DGS/3DGS style).

    For one weight set with weights w_k = a_k T_k and dL/dw_k = q_k:
    dL/da_i = q_i T_i - (sum_{k>i} q_k w_k) / (1 - a_i). Walking back to front, the suffix sum
    is a running sum and T_i = T_{i+1} / (1 - a_i) starts from the saved final transmittance.
    The distortion's dL/dw uses the forward totals (A, sum w m, sum w m^2).
    """
    t = tl.program_id(0)
    start = tl.load(tile_start_ptr + t)
    near = tl.load(params_ptr + 0)
    far = tl.load(params_ptr + 1)
    alpha_max = tl.load(params_ptr + 2)
    alpha_min = tl.load(params_ptr + 3)
    lowpass = tl.load(params_ptr + 5)
    edge_on_ratio = tl.load(params_ptr + 6)
    ndc_scale = far / (far - near)

    lane = tl.arange(0, PIX)
    xi = (t % tiles_x) * TILE + lane % TILE
    yi = (t // tiles_x) * TILE + lane // TILE
    inside = (lane < TILE * TILE) & (xi < width) & (yi < height)
    pix = yi * width + xi
    px = xi.to(DTYPE) + 0.5
    py = yi.to(DTYPE) + 0.5
    ch = tl.arange(0, FCP)
    ch_ok = ch < fc

    row = fc + 9
    g_feat = tl.load(grad_out_ptr + pix[:, None] * row + ch[None, :], mask=inside[:, None] & ch_ok[None, :], other=0.0)
    gbase = grad_out_ptr + pix * row + fc
    g_A = tl.load(gbase + 0, mask=inside, other=0.0)
    g_dsum = tl.load(gbase + 1, mask=inside, other=0.0)
    g_med = tl.load(gbase + 2, mask=inside, other=0.0)
    g_dist = tl.load(gbase + 3, mask=inside, other=0.0)
    g_c0 = tl.load(gbase + 4, mask=inside, other=0.0)
    g_c1 = tl.load(gbase + 5, mask=inside, other=0.0)
    g_c2 = tl.load(gbase + 6, mask=inside, other=0.0)
    g_Av = tl.load(gbase + 7, mask=inside, other=0.0)
    g_dv = tl.load(gbase + 8, mask=inside, other=0.0)
    A = tl.load(out_ptr + pix * row + fc, mask=inside, other=0.0)
    T_s = tl.load(aux_ptr + pix * 4 + 0, mask=inside, other=1.0)
    T_v = tl.load(aux_ptr + pix * 4 + 1, mask=inside, other=1.0)
    S1 = tl.load(aux_ptr + pix * 4 + 2, mask=inside, other=0.0)
    S2 = tl.load(aux_ptr + pix * 4 + 3, mask=inside, other=0.0)
    stop_s = tl.load(stops_ptr + pix * 3 + 0, mask=inside, other=0)
    stop_v = tl.load(stops_ptr + pix * 3 + 1, mask=inside, other=0)
    median_k = tl.load(stops_ptr + pix * 3 + 2, mask=inside, other=-1)
    zero = tl.zeros([PIX], DTYPE)
    suffix_s = zero
    suffix_v = zero

    n_steps = tl.max(tl.maximum(stop_s, stop_v), axis=0)
    for step in range(0, n_steps):
        j = n_steps - 1 - step
        i = tl.load(ids_ptr + start + j)
        z, rho, use_plane, plane_ok, u, v, p2, dx, dy, hx0, hx1, hx2, hy0, hy1, hy2, m6, m7 = _pair(
            M_ptr, centers_ptr, i, px, py, lowpass, edge_on_ratio
        )
        gauss = tl.exp(-0.5 * rho)
        o = tl.load(occ_ptr + i)
        op = tl.load(opa_ptr + i)
        raw_s = o * gauss
        a_s = tl.where(raw_s > alpha_max, alpha_max, raw_s)
        oo = o * op
        raw_v = oo * gauss
        a_v = tl.where(raw_v > alpha_max, alpha_max, raw_v)
        z_ok = z >= near
        z = tl.where(z_ok, z, near)
        m = ndc_scale * (1.0 - near / z)

        # surface set: composited where the forward had not stopped yet and the pair hits
        comp_s = (j < stop_s) & z_ok & (a_s >= alpha_min)
        one_minus_s = tl.where(comp_s, 1.0 - a_s, 1.0)
        T_s = T_s / one_minus_s
        w = tl.where(comp_s, a_s * T_s, 0.0)
        f = tl.load(feats_ptr + i * fc + ch, mask=ch_ok, other=0.0)
        q = g_A + g_dsum * z + g_dist * (m * m * A - 2.0 * m * S1 + S2) + tl.sum(g_feat * f[None, :], axis=1)
        g_a = tl.where(comp_s, q * T_s - suffix_s / one_minus_s, 0.0)
        suffix_s += w * q
        g_z = w * g_dsum + g_dist * 2.0 * w * (m * A - S1) * (ndc_scale * near / (z * z))
        g_z += tl.where(comp_s & (median_k == j), g_med, 0.0)
        unclamped = comp_s & (raw_s <= alpha_max)
        g_occ = tl.where(unclamped, g_a * gauss, 0.0)
        g_gauss = tl.where(unclamped, g_a * o, 0.0)
        g_f = tl.sum(g_feat * w[:, None], axis=0)

        # volume set
        comp_v = (j < stop_v) & z_ok & (a_v >= alpha_min)
        one_minus_v = tl.where(comp_v, 1.0 - a_v, 1.0)
        T_v = T_v / one_minus_v
        w = tl.where(comp_v, a_v * T_v, 0.0)
        col0 = tl.load(colors_ptr + i * 3)
        col1 = tl.load(colors_ptr + i * 3 + 1)
        col2 = tl.load(colors_ptr + i * 3 + 2)
        q = g_Av + g_dv * z + g_c0 * col0 + g_c1 * col1 + g_c2 * col2
        g_a = tl.where(comp_v, q * T_v - suffix_v / one_minus_v, 0.0)
        suffix_v += w * q
        g_z += w * g_dv
        unclamped = comp_v & (raw_v <= alpha_max)
        g_oo = tl.where(unclamped, g_a * gauss, 0.0)
        g_occ += g_oo * op
        g_opa = g_oo * o
        g_gauss += tl.where(unclamped, g_a * oo, 0.0)

        touched = comp_s | comp_v
        if tl.max(touched.to(tl.int32), axis=0) > 0:
            g_rho = tl.where(touched, -0.5 * gauss * g_gauss, 0.0)
            g_z = tl.where(touched, g_z, 0.0)
            on_plane = touched & use_plane & plane_ok
            on_filter = touched & (use_plane == 0)
            # z = u m6 + v m7 + m8, rho = u^2 + v^2, (u, v) = (p0, p1) / p2, p = hx x hy
            g_u = g_z * m6 + 2.0 * u * g_rho
            g_v = g_z * m7 + 2.0 * v * g_rho
            gp0 = g_u / p2
            gp1 = g_v / p2
            gp2 = -(g_u * u + g_v * v) / p2
            ghx0 = tl.where(on_plane, hy1 * gp2 - hy2 * gp1, 0.0)
            ghx1 = tl.where(on_plane, hy2 * gp0 - hy0 * gp2, 0.0)
            ghx2 = tl.where(on_plane, hy0 * gp1 - hy1 * gp0, 0.0)
            ghy0 = tl.where(on_plane, gp1 * hx2 - gp2 * hx1, 0.0)
            ghy1 = tl.where(on_plane, gp2 * hx0 - gp0 * hx2, 0.0)
            ghy2 = tl.where(on_plane, gp0 * hx1 - gp1 * hx0, 0.0)
            g_m6 = tl.where(on_plane, g_z * u, 0.0) - px * ghx0 - py * ghy0
            g_m7 = tl.where(on_plane, g_z * v, 0.0) - px * ghx1 - py * ghy1
            g_m8 = g_z - px * ghx2 - py * ghy2
            g_cx = tl.where(on_filter, g_rho * lowpass * 2.0 * dx, 0.0)
            g_cy = tl.where(on_filter, g_rho * lowpass * 2.0 * dy, 0.0)

            # one atomic add per value of this surfel for the whole tile; relaxed: the sums need no ordering
            dst = grad_ptr + i * (fc + G_FEAT)
            tl.atomic_add(dst + G_M + 0, tl.sum(ghx0, axis=0), sem="relaxed")
            tl.atomic_add(dst + G_M + 1, tl.sum(ghx1, axis=0), sem="relaxed")
            tl.atomic_add(dst + G_M + 2, tl.sum(ghx2, axis=0), sem="relaxed")
            tl.atomic_add(dst + G_M + 3, tl.sum(ghy0, axis=0), sem="relaxed")
            tl.atomic_add(dst + G_M + 4, tl.sum(ghy1, axis=0), sem="relaxed")
            tl.atomic_add(dst + G_M + 5, tl.sum(ghy2, axis=0), sem="relaxed")
            tl.atomic_add(dst + G_M + 6, tl.sum(g_m6, axis=0), sem="relaxed")
            tl.atomic_add(dst + G_M + 7, tl.sum(g_m7, axis=0), sem="relaxed")
            tl.atomic_add(dst + G_M + 8, tl.sum(g_m8, axis=0), sem="relaxed")
            tl.atomic_add(dst + G_CENTER, tl.sum(g_cx, axis=0), sem="relaxed")
            tl.atomic_add(dst + G_CENTER + 1, tl.sum(g_cy, axis=0), sem="relaxed")
            tl.atomic_add(dst + G_OCC, tl.sum(g_occ, axis=0), sem="relaxed")
            tl.atomic_add(dst + G_OPA, tl.sum(g_opa, axis=0), sem="relaxed")
            tl.atomic_add(dst + G_COLOR, tl.sum(g_c0 * w, axis=0), sem="relaxed")
            tl.atomic_add(dst + G_COLOR + 1, tl.sum(g_c1 * w, axis=0), sem="relaxed")
            tl.atomic_add(dst + G_COLOR + 2, tl.sum(g_c2 * w, axis=0), sem="relaxed")
            tl.atomic_add(dst + G_FEAT + ch, g_f, mask=ch_ok, sem="relaxed")
