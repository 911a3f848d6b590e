"""Numba kernels of the ``cpu`` rasterizer backend (see :mod:`rtsplat.raster.cpu`).

Imported lazily by :mod:`rtsplat.raster.cpu` on the first rasterization, never by ``import
rtsplat``: importing numba costs ~0.5 s and the first call compiles (or loads from the cache).

All arithmetic is float64 (``grad_out`` may be float32: read exactly into float64). Per-surfel
inputs (projected by :mod:`rtsplat.raster.projection`):

* ``M`` [N,9]: ray transform, row major (rows: x w, y w, w);
* ``centers`` [N,2]: projected centres (px); ``occ``/``opa`` [N]: occupancy / opacity;
* ``feats`` [N,Fc]: surface attributes (features, then camera-facing normals);
* ``colors`` [N,3]: volume radiance;
* ``rho_cut`` [N]: pairs with rho above it cannot reach ``alpha_min`` in either weight set (see
  :func:`surfel_bounds_kernel`); they are skipped before the exponential;
* ``boxes`` [N,4]: pixel boxes outside which rho > ``rho_cut`` (see :func:`surfel_bounds_kernel`);
  :func:`tile_entries_kernel` keeps per tile the entries whose box meets it (``keep``/``n_keep``),
  then each 4x4 pixel block of the tile the entries whose box meets the block (``n_done`` counts
  positions in that block list), and each pixel skips entries whose box it is outside of. The
  parallel work unit of the forward and of the backward is one tile (its blocks one after the other, so
  that the tile's packed entries stay in cache).

Per pixel output row (``out`` [H*W, Fc+9]), the layout of the reference backend:
``feats (Fc) | alpha | depth_sum | depth_median | distortion | color (3) | volume_alpha | volume_depth_sum``.

Per-surfel gradient row layout (``acc`` [threads, N, 16+Fc], one slice per thread indexed by
``numba.get_thread_id()`` so that threads never write the same memory, summed over threads by
:func:`sum_threads_kernel` into ``acc[0]``): ``M (9) | centers (2) | occ | opa | colors (3) | feats (Fc)``.
"""

from __future__ import annotations

import math

import numpy as np
from numba import get_thread_id, njit, prange

G_M, G_CENTER, G_OCC, G_OPA, G_COLOR, G_FEAT = 0, 9, 11, 12, 13, 16

_JIT = dict(cache=True, nogil=True, error_model="numpy", fastmath=False)


@njit(inline="always", **_JIT)
def _cross(a0, a1, a2, b0, b1, b2):
    """The cross product a x b of two 3-vectors given by components."""
    return a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0


@njit(inline="always", **_JIT)
def _pixel_rows(m0, m1, m2, m3, m4, m5, m6, m7, m8, px, py):
    """The two planes through pixel centre (px, py) in the surfel's (u, v, 1) frame: the rows x w - px w
    and y w - py w of the ray transform (rows m0..m2, m3..m5, m6..m8), whose cross product gives the
    ray-splat intersection (:func:`_eval_pair`)."""
    return m0 - px * m6, m1 - px * m7, m2 - px * m8, m3 - py * m6, m4 - py * m7, m5 - py * m8


@njit(inline="always", **_JIT)
def _eval_pair(m0, m1, m2, m3, m4, m5, m6, m7, m8, cx, cy, px, py, lowpass, edge_on_ratio):
    """Ray-splat intersection at pixel centre (px, py) of the surfel with ray transform rows
    (m0 m1 m2 | m3 m4 m5 | m6 m7 m8) and projected centre (cx, cy): reference semantics."""
    hx0, hx1, hx2, hy0, hy1, hy2 = _pixel_rows(m0, m1, m2, m3, m4, m5, m6, m7, m8, px, py)
    p0, p1, p2 = _cross(hx0, hx1, hx2, hy0, hy1, hy2)
    return _eval_crossed(p0, p1, p2, m6, m7, m8, cx, cy, px, py, lowpass, edge_on_ratio)


@njit(inline="always", **_JIT)
def _eval_crossed(p0, p1, p2, m6, m7, m8, cx, cy, px, py, lowpass, edge_on_ratio):
    """:func:`_eval_pair` from the cross product p = hx x hy of the pixel's two planes (:func:`_pixel_rows`),
    for callers that computed it already: z, rho, use_plane, plane_ok, u, v, p2."""
    plane_ok = abs(p2) > edge_on_ratio * max(abs(p0), abs(p1))
    if plane_ok:
        u = p0 / p2
        v = p1 / p2
        rho3 = u * u + v * v
    else:
        u = 0.0
        v = 0.0
        rho3 = np.inf
    dx = cx - px
    dy = cy - py
    rho2 = lowpass * (dx * dx + dy * dy)
    use_plane = rho3 <= rho2
    if use_plane:
        rho = rho3
        z = u * m6 + v * m7 + m8
    else:
        rho = rho2
        z = m8
    return z, rho, use_plane, plane_ok, u, v, p2


@njit(inline="always", **_JIT)
def _nan_min(a, b):
    """min that returns NaN when either argument is NaN (numpy's ``minimum``)."""
    if a != a or b != b:
        return np.nan
    return a if a < b else b


@njit(inline="always", **_JIT)
def _nan_max(a, b):
    """max that returns NaN when either argument is NaN (numpy's ``maximum``)."""
    if a != a or b != b:
        return np.nan
    return a if a > b else b


@njit(parallel=True, **_JIT)
def surfel_bounds_kernel(M, centers, occ, opa, alpha_min, lowpass, rho_cut, boxes):
    """Per surfel: ``rho_cut`` (the kernel exponent above which neither weight set can reach
    ``alpha_min``) and ``boxes`` (x_min, x_max, y_min, y_max: pixel coordinates outside which
    rho > ``rho_cut``).

    Cut-off: both alphas are at most max(occupancy, occupancy x opacity) x exp(-rho/2), so a pair
    with rho > 2 ln(that / alpha_min) contributes nothing; the margin (1e-6 + 1e-9 rho) keeps every
    pair near the threshold for the exact test, so skipping changes no result. +inf (never skip)
    when ``alpha_min`` <= 0 or for NaN inputs, -inf (always skip) for a surfel whose alphas are 0.

    Box: rho = min(rho_3d, rho_2d) <= cut needs rho_3d <= cut (the pixel's ray meets the surfel
    plane inside the ellipse u^2 + v^2 <= cut, whose projection is bounded by the dual-conic box of
    :func:`rtsplat.raster.projection.ellipse_screen_box`) or rho_2d <= cut (a disc of radius
    sqrt(cut / lowpass) around the centre). The union of both boxes, widened by a safety margin,
    bounds every pixel a surfel can contribute to. Unbounded projections (the ellipse reaches the
    camera plane) and non-finite values give an infinite box: no skipping, the exact test decides;
    a surfel whose cut is -inf gets an empty box.
    """
    for n in prange(M.shape[0]):
        o = occ[n]
        peak = _nan_max(o, o * opa[n])
        if alpha_min <= 0:
            cut = np.inf
        else:
            cut = 2.0 * np.log(peak / alpha_min)
            if cut != cut:
                cut = np.inf  # NaN inputs: leave them to the exact test
            finite = cut - cut == 0.0
            cut = cut + (1e-6 + 1e-9 * (abs(cut) if finite else 0.0))
        rho_cut[n] = cut
        boxes[n, 0] = -np.inf
        boxes[n, 1] = np.inf
        boxes[n, 2] = -np.inf
        boxes[n, 3] = np.inf
        if cut == -np.inf:  # all alphas are 0: the surfel contributes nowhere
            boxes[n, 0] = np.inf
            boxes[n, 1] = -np.inf
            boxes[n, 2] = np.inf
            boxes[n, 3] = -np.inf
            continue
        if not (cut - cut == 0.0):
            continue
        c2 = cut if cut > 0.0 else 0.0
        rx0 = M[n, 0]
        rx1 = M[n, 1]
        rx2 = M[n, 2]
        ry0 = M[n, 3]
        ry1 = M[n, 4]
        ry2 = M[n, 5]
        rw0 = M[n, 6]
        rw1 = M[n, 7]
        rw2 = M[n, 8]
        d = c2 * rw0 * rw0 + c2 * rw1 * rw1 - rw2 * rw2
        if not (d < 0.0):
            continue
        cx = (c2 * rx0 * rw0 + c2 * rx1 * rw1 - rx2 * rw2) / d
        cy = (c2 * ry0 * rw0 + c2 * ry1 * rw1 - ry2 * rw2) / d
        ex = np.sqrt(_nan_max(cx * cx - (c2 * rx0 * rx0 + c2 * rx1 * rx1 - rx2 * rx2) / d, 0.0))
        ey = np.sqrt(_nan_max(cy * cy - (c2 * ry0 * ry0 + c2 * ry1 * ry1 - ry2 * ry2) / d, 0.0))
        r = np.sqrt(c2 / lowpass) if lowpass > 0 else np.inf
        ox = centers[n, 0]
        oy = centers[n, 1]
        x0 = _nan_min(cx - ex, ox - r)
        x1 = _nan_max(cx + ex, ox + r)
        y0 = _nan_min(cy - ey, oy - r)
        y1 = _nan_max(cy + ey, oy + r)
        mx = 1e-2 + 1e-3 * (x1 - x0) + 1e-6 * (abs(cx) + abs(ox))
        my = 1e-2 + 1e-3 * (y1 - y0) + 1e-6 * (abs(cy) + abs(oy))
        b0 = x0 - mx
        b1 = x1 + mx
        b2 = y0 - my
        b3 = y1 + my
        if b0 - b0 == 0.0 and b1 - b1 == 0.0 and b2 - b2 == 0.0 and b3 - b3 == 0.0:
            boxes[n, 0] = b0
            boxes[n, 1] = b1
            boxes[n, 2] = b2
            boxes[n, 3] = b3


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


NPIX = BLOCK * BLOCK


@njit(inline="always", **_JIT)
def _block_pixels(tx0, ty0, tile_size, bx, by, width, height):
    """Pixel-centre coordinates and flat indices of block (bx, by), clipped to the tile and image."""
    x0 = tx0 + bx * BLOCK
    y0 = ty0 + by * BLOCK
    nx = min(BLOCK, tile_size - bx * BLOCK, width - x0)
    ny = min(BLOCK, tile_size - by * BLOCK, height - y0)
    npx = max(nx, 0) * max(ny, 0)
    pxs = np.empty(NPIX, dtype=np.float64)
    pys = np.empty(NPIX, dtype=np.float64)
    pixs = np.empty(NPIX, dtype=np.int64)
    for p in range(npx):
        xi = x0 + p % nx
        yi = y0 + p // nx
        pxs[p] = xi + 0.5
        pys[p] = yi + 0.5
        pixs[p] = yi * width + xi
    for p in range(npx, NPIX):  # padding, for loops over all NPIX slots: a copy of a real pixel
        pxs[p] = x0 + 0.5
        pys[p] = y0 + 0.5
        pixs[p] = -1
    return pxs, pys, pixs, npx


@njit(inline="always", **_JIT)
def _geometry_buffers():
    """Per-pixel scratch of one block for :func:`_packed_entry_geometry`: rho, z, u, v, p2 (float64) and
    contributes, use-plane, plane-defined (bool)."""
    return (np.empty(NPIX, dtype=np.float64), np.empty(NPIX, dtype=np.float64), np.empty(NPIX, dtype=np.float64),
            np.empty(NPIX, dtype=np.float64), np.empty(NPIX, dtype=np.float64), np.empty(NPIX, dtype=np.bool_),
            np.empty(NPIX, dtype=np.bool_), np.empty(NPIX, dtype=np.bool_))


# Packed entry row of the forward (one per kept entry of a tile, in depth order, read sequentially by
# the tile's blocks): box (4) | M (9) | centre (2) | rho cut-off | occupancy | occupancy x opacity.
P_BOX, P_M, P_CENTER, P_CUT, P_OCC, P_OCC_OPA, PACK = 0, 4, 13, 15, 16, 17, 18


@njit(inline="always", **_JIT)
def _pack_tile(M, centers, occ, opa, ids, boxes, rho_cut, keep, start, nk, pk):
    """Row j of ``pk``: the packed data of the tile's kept entry j (list position ``keep[start + j]``)."""
    for j in range(nk):
        i = ids[start + keep[start + j]]
        for c in range(4):
            pk[j, P_BOX + c] = boxes[i, c]
        for c in range(9):
            pk[j, P_M + c] = M[i, c]
        pk[j, P_CENTER] = centers[i, 0]
        pk[j, P_CENTER + 1] = centers[i, 1]
        pk[j, P_CUT] = rho_cut[i]
        o = occ[i]
        pk[j, P_OCC] = o
        pk[j, P_OCC_OPA] = o * opa[i]


@njit(inline="always", **_JIT)
def _tile_block_lists(pk, nk, tx0, ty0, tile_size, nbx, lists, counts):
    """Per block b of the tile, ``lists[b, :counts[b]]``: the kept entries (rows of ``pk``, depth order
    kept) whose box meets the block, in one pass over the tile's entries."""
    for b in range(nbx * nbx):
        counts[b] = 0
    for j in range(nk):
        b0 = pk[j, P_BOX]
        b1 = pk[j, P_BOX + 1]
        b2 = pk[j, P_BOX + 2]
        b3 = pk[j, P_BOX + 3]
        for by in range(nbx):
            lo_y = ty0 + by * BLOCK + 0.5
            hi_y = ty0 + min((by + 1) * BLOCK, tile_size) - 0.5
            if not (b3 >= lo_y and b2 <= hi_y):
                continue
            for bx in range(nbx):
                lo_x = tx0 + bx * BLOCK + 0.5
                hi_x = tx0 + min((bx + 1) * BLOCK, tile_size) - 0.5
                if b1 >= lo_x and b0 <= hi_x:
                    b = by * nbx + bx
                    lists[b, counts[b]] = j
                    counts[b] += 1


@njit(inline="always", **_JIT)
def _packed_tile(t, M, centers, occ, opa, ids, boxes, rho_cut, keep, n_keep, tile_start, tiles_x, tile_size, nbx):
    """Tile ``t`` made ready for a compositing kernel: its first pair, its top-left pixel, its kept entries
    packed (:func:`_pack_tile`) and listed per 4x4 block (:func:`_tile_block_lists`: ``lists[b, :counts[b]]``,
    positions in the tile's kept entries)."""
    nk = n_keep[t]
    start = tile_start[t]
    tx0 = (t % tiles_x) * tile_size
    ty0 = (t // tiles_x) * tile_size
    pk = np.empty((nk, PACK), dtype=np.float64)
    _pack_tile(M, centers, occ, opa, ids, boxes, rho_cut, keep, start, nk, pk)
    lists = np.empty((nbx * nbx, nk), dtype=np.int32)
    counts = np.empty(nbx * nbx, dtype=np.int64)
    _tile_block_lists(pk, nk, tx0, ty0, tile_size, nbx, lists, counts)
    return start, tx0, ty0, pk, lists, counts


@njit(inline="always", **_JIT)
def _packed_geometry(pk, j):
    """Packed entry ``j``'s box (4), ray transform (9), projected centre (2) and rho cut-off."""
    return (pk[j, P_BOX], pk[j, P_BOX + 1], pk[j, P_BOX + 2], pk[j, P_BOX + 3], pk[j, P_M], pk[j, P_M + 1],
            pk[j, P_M + 2], pk[j, P_M + 3], pk[j, P_M + 4], pk[j, P_M + 5], pk[j, P_M + 6], pk[j, P_M + 7],
            pk[j, P_M + 8], pk[j, P_CENTER], pk[j, P_CENTER + 1], pk[j, P_CUT])


@njit(inline="always", **_JIT)
def _packed_entry_geometry(pk, j, pxs, pys, npx, near, lowpass, edge_on_ratio,
                           rho_b, z_b, u_b, v_b, p2_b, ok_b, plane_b, plane_ok_b):
    """The ray-splat geometry of packed entry ``j`` at the block's ``npx`` pixels, in one branch-free loop
    (:func:`_eval_pair`), into the per-pixel buffers; ``ok_b``: inside its box, rho within its cut-off
    and in front of ``near``. Returns the entry's ray transform (m0..m8)."""
    b0, b1, b2, b3, m0, m1, m2, m3, m4, m5, m6, m7, m8, cx, cy, cut = _packed_geometry(pk, j)
    for p in range(npx):
        px = pxs[p]
        py = pys[p]
        z, rho, use_plane, plane_ok, u, v, p2 = _eval_pair(
            m0, m1, m2, m3, m4, m5, m6, m7, m8, cx, cy, px, py, lowpass, edge_on_ratio
        )
        rho_b[p] = rho
        z_b[p] = z
        u_b[p] = u
        v_b[p] = v
        p2_b[p] = p2
        plane_b[p] = use_plane
        plane_ok_b[p] = plane_ok
        ok_b[p] = not ((px < b0) | (px > b1) | (py < b2) | (py > b3) | (rho > cut) | (not (z >= near)))
    return m0, m1, m2, m3, m4, m5, m6, m7, m8


# Rows of the backward's per-pixel terms (:func:`_block_gradient_terms`): the image gradient of the alpha,
# depth sum, median depth, distortion, colour (3), volume alpha and volume depth sum, and the forward totals
# A, S1, S2 that the distortion's gradient reads.
T_ALPHA, T_DSUM, T_MEDIAN, T_DIST, T_C0, T_C1, T_C2, T_VALPHA, T_VDSUM, T_A, T_S1, T_S2, N_TERMS = range(13)


@njit(inline="always", **_JIT)
def _block_gradient_terms(out, stats, n_done, median_k, grad_out, fc, pixs, npx, st, live, limit, terms, g_feat,
                          median_b):
    """Set up the backward of one block: per pixel ``p`` the sums Q_s, Q_v of q_k w_k of both weight sets
    from the forward totals (``st[0:2]``), the prefix sums (``st[2:4]``) and transmittances (``st[4:6]``)
    reset, both sets live, the walk's length ``limit``, and the pixel's image gradient and totals copied
    into ``terms`` (rows ``T_*``), ``g_feat`` [NPIX, fc] and ``median_b``, where the entry loop reads them.
    Returns the longest walk of the block."""
    n_run = 0
    for p in range(npx):
        pix = pixs[p]
        A = out[pix, fc]
        S1 = stats[pix, 0]
        S2 = stats[pix, 1]
        Q_s = (
            grad_out[pix, fc] * A
            + grad_out[pix, fc + 1] * out[pix, fc + 1]
            + grad_out[pix, fc + 3] * 2.0 * (A * S2 - S1 * S1)
        )
        for c in range(fc):
            Q_s += grad_out[pix, c] * out[pix, c]
            g_feat[p, c] = grad_out[pix, c]
        st[0, p] = Q_s
        st[1, p] = (
            grad_out[pix, fc + 4] * out[pix, fc + 4]
            + grad_out[pix, fc + 5] * out[pix, fc + 5]
            + grad_out[pix, fc + 6] * out[pix, fc + 6]
            + grad_out[pix, fc + 7] * out[pix, fc + 7]
            + grad_out[pix, fc + 8] * out[pix, fc + 8]
        )
        st[2, p] = 0.0
        st[3, p] = 0.0
        st[4, p] = 1.0
        st[5, p] = 1.0
        live[0, p] = True
        live[1, p] = True
        for r in range(T_A):  # the image gradient's rows, in the output row's order
            terms[r, p] = grad_out[pix, fc + r]
        terms[T_A, p] = A
        terms[T_S1, p] = S1
        terms[T_S2, p] = S2
        median_b[p] = median_k[pix]
        limit[p] = n_done[pix]
        n_run = max(n_run, limit[p])
    return n_run


REACH_MARGIN = 1e-12  # relative margin of :func:`_entry_reach`'s test over the exact rho test's rounding


@njit(inline="always", **_JIT)
def _entry_reach(pk, j, pxs, pys, lowpass, active, cand, c0, c1, c2):
    """``cand[p]``: pixel slot ``p`` of the block is active and may be in reach of packed entry ``j``;
    returns how many are; ``c0, c1, c2`` [NPIX]: the cross product p of each slot, which the exact test
    then reads (:func:`_eval_crossed`) instead of computing it again. A superset of the pixels the exact
    test (:func:`_eval_pair`, as in
    :func:`_entry_geometry`) finds inside the box with rho within the cut-off, tested without division
    in one loop over all NPIX slots that LLVM vectorises: with p = hx x hy of :func:`_eval_pair`,
    rho_3d = (p0^2 + p1^2) / p2^2 <= cut is tested as p0^2 + p1^2 <= cut' p2^2 where cut' exceeds the
    cut-off by ``REACH_MARGIN`` (relative), far more than the few ulp by which the two roundings differ;
    rho_2d and the box are tested as the exact test does; edge-on planes (rho_3d = inf in the exact
    test) are left to it. Tiny or non-finite terms and NaN fall to the candidate side. The exact
    geometry is then computed only for the candidates, so the outputs are those of the exact test."""
    b0, b1, b2, b3, m0, m1, m2, m3, m4, m5, m6, m7, m8, cx, cy, cut = _packed_geometry(pk, j)
    cut_hi = cut + abs(cut) * REACH_MARGIN
    n = 0
    for p in range(NPIX):
        px = pxs[p]
        py = pys[p]
        hx0, hx1, hx2, hy0, hy1, hy2 = _pixel_rows(m0, m1, m2, m3, m4, m5, m6, m7, m8, px, py)
        p0, p1, p2 = _cross(hx0, hx1, hx2, hy0, hy1, hy2)
        c0[p] = p0
        c1[p] = p1
        c2[p] = p2
        q2 = p2 * p2
        plane_out = (p0 * p0 + p1 * p1 > cut_hi * q2) & (q2 > 1e-200)
        dx = cx - px
        dy = cy - py
        rho2 = lowpass * (dx * dx + dy * dy)
        out = (px < b0) | (px > b1) | (py < b2) | (py > b3) | ((rho2 > cut_hi) & plane_out)
        c = active[p] & (not out)
        cand[p] = c
        n += c
    return n


@njit(**_JIT)
def spread_order(n):
    """A permutation of ``range(n)`` in which every run of consecutive positions is spread over the
    whole range: the bit-reversal order (of the next power of two, values >= n left out). Positions
    0, 1, 2, 3 ... of it are 0, n'/2, n'/4, 3n'/4 ... (n' = that power of two), so the first half of
    it holds the even values and the second the odd ones, each quarter one residue modulo 4, and
    so on. A parallel loop over it hands each thread (or each contiguous run of iterations) work
    from all over the image."""
    bits = 0
    while (1 << bits) < n:
        bits += 1
    order = np.empty(n, dtype=np.int64)
    m = 0
    for u in range(1 << bits):
        r = 0
        for b in range(bits):
            r |= ((u >> b) & 1) << (bits - 1 - b)
        if r < n:
            order[m] = r
            m += 1
    return order


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
    """Composite every pixel front to back; one tile per work unit. The tile's kept entries are packed
    (:func:`_pack_tile`) and listed per 4x4 block (:func:`_tile_block_lists`); then block by block,
    entry by entry: a division-free test over the block's pixels (:func:`_entry_reach`) skips the
    entry when no pixel still traversing can be in its reach, else each candidate pixel gets the
    exact geometry (:func:`_eval_pair`) and composites the entry if it is within reach."""
    n_tiles = tile_count.shape[0]
    fc = feats.shape[1]
    ndc_scale = far / (far - near)
    nbx = (tile_size + BLOCK - 1) // BLOCK
    nb2 = nbx * nbx
    # tiles in spread order: numba's workqueue threading layer splits a parallel loop's iterations
    # into one contiguous run per thread, whatever the chunk size, and tiles of one image region cost
    # alike (on the dome's 320x240 frame the top half of the tiles took 36% of the work)
    order = spread_order(n_tiles)
    for u in prange(n_tiles):
        t = order[u]
        if n_keep[t] == 0:
            continue
        start, tx0, ty0, pk, lists, counts = _packed_tile(
            t, M, centers, occ, opa, ids, boxes, rho_cut, keep, n_keep, tile_start, tiles_x, tile_size, nbx
        )
        # per pixel: T_s T_v A dsum med dist S1 S2 c0 c1 c2 Av dvsum
        st = np.empty((13, NPIX), dtype=np.float64)
        medk_b = np.empty(NPIX, dtype=np.int64)
        live = np.empty((2, NPIX), dtype=np.bool_)
        running = np.empty(NPIX, dtype=np.bool_)
        cand = np.empty(NPIX, dtype=np.bool_)
        c0 = np.empty(NPIX, dtype=np.float64)
        c1 = np.empty(NPIX, dtype=np.float64)
        c2 = np.empty(NPIX, dtype=np.float64)
        for b in range(nb2):
            by = b // nbx
            bx = b - by * nbx
            pxs, pys, pixs, npx = _block_pixels(tx0, ty0, tile_size, bx, by, width, height)
            if npx == 0:
                continue
            n_scan = counts[b]
            for p in range(NPIX):
                for r in range(13):
                    st[r, p] = 0.0
                st[0, p] = 1.0
                st[1, p] = 1.0
                medk_b[p] = -1
                live[0, p] = True
                live[1, p] = True
                running[p] = p < npx
            for p in range(npx):
                n_done[pixs[p]] = n_scan
            alive = npx
            for jj in range(n_scan):
                if alive == 0:
                    break
                j = lists[b, jj]
                if _entry_reach(pk, j, pxs, pys, lowpass, running, cand, c0, c1, c2) == 0:
                    continue
                k = keep[start + j]
                i = ids[start + k]
                b0, b1, b2, b3, m0, m1, m2, m3, m4, m5, m6, m7, m8, cx, cy, cut = _packed_geometry(pk, j)
                o = pk[j, P_OCC]
                oo = pk[j, P_OCC_OPA]
                entry_used = False
                for p in range(npx):
                    if not cand[p]:
                        continue
                    px = pxs[p]
                    py = pys[p]
                    z, rho, _, _, _, _, _ = _eval_crossed(
                        c0[p], c1[p], c2[p], m6, m7, m8, cx, cy, px, py, lowpass, edge_on_ratio
                    )
                    if (px < b0) | (px > b1) | (py < b2) | (py > b3) | (rho > cut) | (not (z >= near)):
                        continue
                    pix = pixs[p]
                    gauss = math.exp(-0.5 * rho)
                    a_s = o * gauss
                    if a_s > alpha_max:
                        a_s = alpha_max
                    a_v = oo * gauss
                    if a_v > alpha_max:
                        a_v = alpha_max
                    if live[0, p] and a_s >= alpha_min:
                        T_s = st[0, p]
                        t_next = T_s * (1.0 - a_s)
                        if t_next < t_min:
                            live[0, p] = False
                        else:
                            w = a_s * T_s
                            for c in range(fc):
                                out[pix, c] += w * feats[i, c]
                            m = ndc_scale * (1.0 - near / z)
                            A = st[2, p]
                            S1 = st[6, p]
                            S2 = st[7, p]
                            st[5, p] += w * (m * m * A + S2 - 2.0 * m * S1)
                            st[2, p] = A + w
                            st[6, p] = S1 + w * m
                            st[7, p] = S2 + w * m * m
                            st[3, p] += w * z
                            if T_s > 0.5:
                                st[4, p] = z
                                medk_b[p] = k
                            st[0, p] = t_next
                            entry_used = True
                    if live[1, p] and a_v >= alpha_min:
                        T_v = st[1, p]
                        t_next = T_v * (1.0 - a_v)
                        if t_next < t_min:
                            live[1, p] = False
                        else:
                            w = a_v * T_v
                            st[8, p] += w * colors[i, 0]
                            st[9, p] += w * colors[i, 1]
                            st[10, p] += w * colors[i, 2]
                            st[11, p] += w
                            st[12, p] += w * z
                            st[1, p] = t_next
                            entry_used = True
                    if not live[0, p] and not live[1, p]:
                        running[p] = False
                        n_done[pix] = jj + 1
                        alive -= 1
                if entry_used and used[start + k] == 0:
                    used[start + k] = 1
            for p in range(npx):
                pix = pixs[p]
                median_k[pix] = medk_b[p]
                out[pix, fc] = st[2, p]
                out[pix, fc + 1] = st[3, p]
                out[pix, fc + 2] = st[4, p]
                out[pix, fc + 3] = st[5, p]
                out[pix, fc + 4] = st[8, p]
                out[pix, fc + 5] = st[9, p]
                out[pix, fc + 6] = st[10, p]
                out[pix, fc + 7] = st[11, p]
                out[pix, fc + 8] = st[12, p]
                stats[pix, 0] = st[6, p]
                stats[pix, 1] = st[7, p]

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
    """Accumulate dL/d(per-surfel inputs), replaying the forward front to back per 4x4 block. One tile per
    work unit, as in the forward: its kept entries packed (:func:`_pack_tile`) and listed per block
    (:func:`_tile_block_lists`), the lists the forward walked.

    For one weight set with weights w_k = a_k T_k and a per-pixel loss whose partial derivative
    with respect to w_k is q_k, dL/da_i = q_i T_i - (sum_{k>i} q_k w_k) / (1 - a_i); the suffix sum
    is Q - (prefix incl. i), with Q = sum_k q_k w_k computed from the forward totals. The gradient
    of one entry is summed over the pixels of the block first, then added to the thread's row.
    """
    n_tiles = tile_count.shape[0]
    fc = feats.shape[1]
    n_grad = G_FEAT + fc
    ndc_scale = far / (far - near)
    nbx = (tile_size + BLOCK - 1) // BLOCK
    nb2 = nbx * nbx
    order = spread_order(n_tiles)  # as in the forward: each thread's contiguous run from all over the image
    for u in prange(n_tiles):
        t = order[u]
        if n_keep[t] == 0:
            continue
        start, tx0, ty0, pk, lists, counts = _packed_tile(
            t, M, centers, occ, opa, ids, boxes, rho_cut, keep, n_keep, tile_start, tiles_x, tile_size, nbx
        )
        tid = get_thread_id()
        rho_b, z_b, u_b, v_b, p2_b, ok_b, plane_b, plane_ok_b = _geometry_buffers()
        st = np.empty((6, NPIX), dtype=np.float64)  # per pixel: Q_s Q_v P_s P_v T_s T_v
        live = np.empty((2, NPIX), dtype=np.bool_)
        limit = np.empty(NPIX, dtype=np.int64)
        terms = np.empty((N_TERMS, NPIX), dtype=np.float64)
        g_feat = np.empty((NPIX, max(fc, 1)), dtype=np.float64)
        median_b = np.empty(NPIX, dtype=np.int64)
        eg = np.zeros(n_grad, dtype=np.float64)
        for b in range(nb2):
            by = b // nbx
            bx = b - by * nbx
            pxs, pys, pixs, npx = _block_pixels(tx0, ty0, tile_size, bx, by, width, height)
            if npx == 0:
                continue
            n_run = _block_gradient_terms(out, stats, n_done, median_k, grad_out, fc, pixs, npx,
                                          st, live, limit, terms, g_feat, median_b)
            for j in range(n_run):
                jp = lists[b, j]
                k = keep[start + jp]
                i = ids[start + k]
                m0, m1, m2, m3, m4, m5, m6, m7, m8 = _packed_entry_geometry(
                    pk, jp, pxs, pys, npx, near, lowpass, edge_on_ratio,
                    rho_b, z_b, u_b, v_b, p2_b, ok_b, plane_b, plane_ok_b,
                )
                o = pk[jp, P_OCC]
                oo = pk[jp, P_OCC_OPA]
                op = opa[i]
                fi = feats[i]
                ci0 = colors[i, 0]
                ci1 = colors[i, 1]
                ci2 = colors[i, 2]
                any_touched = False
                for p in range(npx):
                    if not ok_b[p] or j >= limit[p]:
                        continue
                    z = z_b[p]
                    gauss = math.exp(-0.5 * rho_b[p])
                    raw_s = o * gauss
                    a_s = raw_s
                    if a_s > alpha_max:
                        a_s = alpha_max
                    raw_v = oo * gauss
                    a_v = raw_v
                    if a_v > alpha_max:
                        a_v = alpha_max
                    g_z = 0.0
                    g_gauss = 0.0
                    touched = False
                    if live[0, p] and a_s >= alpha_min:
                        T_s = st[4, p]
                        t_next = T_s * (1.0 - a_s)
                        if t_next < t_min:
                            live[0, p] = False
                        else:
                            touched = True
                            w = a_s * T_s
                            g_dsum = terms[T_DSUM, p]
                            g_dist = terms[T_DIST, p]
                            A = terms[T_A, p]
                            S1 = terms[T_S1, p]
                            m = ndc_scale * (1.0 - near / z)
                            q = terms[T_ALPHA, p] + g_dsum * z + g_dist * (m * m * A - 2.0 * m * S1 + terms[T_S2, p])
                            for c in range(fc):
                                q += g_feat[p, c] * fi[c]
                                eg[G_FEAT + c] += g_feat[p, c] * w
                            P_s = st[2, p] + q * w
                            st[2, p] = P_s
                            g_a = q * T_s - (st[0, p] - P_s) / (1.0 - a_s)
                            g_z += g_dsum * w + g_dist * 2.0 * w * (m * A - S1) * (ndc_scale * near / (z * z))
                            if k == median_b[p]:
                                g_z += terms[T_MEDIAN, p]
                            if raw_s <= alpha_max:
                                eg[G_OCC] += g_a * gauss
                                g_gauss += g_a * o
                            st[4, p] = t_next
                    if live[1, p] and a_v >= alpha_min:
                        T_v = st[5, p]
                        t_next = T_v * (1.0 - a_v)
                        if t_next < t_min:
                            live[1, p] = False
                        else:
                            touched = True
                            w = a_v * T_v
                            g_c0 = terms[T_C0, p]
                            g_c1 = terms[T_C1, p]
                            g_c2 = terms[T_C2, p]
                            g_dv = terms[T_VDSUM, p]
                            q = (
                                terms[T_VALPHA, p]
                                + g_dv * z
                                + g_c0 * ci0
                                + g_c1 * ci1
                                + g_c2 * ci2
                            )
                            eg[G_COLOR] += g_c0 * w
                            eg[G_COLOR + 1] += g_c1 * w
                            eg[G_COLOR + 2] += g_c2 * w
                            P_v = st[3, p] + q * w
                            st[3, p] = P_v
                            g_a = q * T_v - (st[1, p] - P_v) / (1.0 - a_v)
                            g_z += g_dv * w
                            if raw_v <= alpha_max:
                                g_oo = g_a * gauss
                                eg[G_OCC] += g_oo * op
                                eg[G_OPA] += g_oo * o
                                g_gauss += g_a * oo
                            st[5, p] = t_next
                    if not touched:
                        continue
                    any_touched = True
                    g_rho = -0.5 * gauss * g_gauss
                    px = pxs[p]
                    py = pys[p]
                    if plane_b[p]:
                        if plane_ok_b[p]:
                            u = u_b[p]
                            v = v_b[p]
                            p2 = p2_b[p]
                            hx0, hx1, hx2, hy0, hy1, hy2 = _pixel_rows(m0, m1, m2, m3, m4, m5, m6, m7, m8, px, py)
                            # z = u m6 + v m7 + m8 ; rho = u^2 + v^2
                            eg[G_M + 6] += g_z * u
                            eg[G_M + 7] += g_z * v
                            eg[G_M + 8] += g_z
                            g_u = g_z * m6 + 2.0 * u * g_rho
                            g_v = g_z * m7 + 2.0 * v * g_rho
                            inv_p2 = 1.0 / p2
                            gp0 = g_u * inv_p2
                            gp1 = g_v * inv_p2
                            gp2 = -(g_u * u + g_v * v) * inv_p2
                            # p = hx x hy: dL/dhx = hy x gp, dL/dhy = gp x hx
                            ghx0, ghx1, ghx2 = _cross(hy0, hy1, hy2, gp0, gp1, gp2)
                            ghy0, ghy1, ghy2 = _cross(gp0, gp1, gp2, hx0, hx1, hx2)
                            eg[G_M + 0] += ghx0
                            eg[G_M + 1] += ghx1
                            eg[G_M + 2] += ghx2
                            eg[G_M + 3] += ghy0
                            eg[G_M + 4] += ghy1
                            eg[G_M + 5] += ghy2
                            eg[G_M + 6] -= px * ghx0 + py * ghy0
                            eg[G_M + 7] -= px * ghx1 + py * ghy1
                            eg[G_M + 8] -= px * ghx2 + py * ghy2
                        else:
                            eg[G_M + 8] += g_z
                    else:
                        eg[G_M + 8] += g_z
                        eg[G_CENTER] += g_rho * lowpass * 2.0 * (centers[i, 0] - px)
                        eg[G_CENTER + 1] += g_rho * lowpass * 2.0 * (centers[i, 1] - py)
                if any_touched:
                    for c in range(n_grad):
                        acc[tid, i, c] += eg[c]
                        eg[c] = 0.0


@njit(parallel=True, **_JIT)
def sum_threads_kernel(acc):
    """``acc[0, i] += acc[t, i]`` for every other thread t (the backward's per-thread sums)."""
    n_threads = acc.shape[0]
    for i in prange(acc.shape[1]):
        for th in range(1, n_threads):
            for c in range(acc.shape[2]):
                acc[0, i, c] += acc[th, i, c]
