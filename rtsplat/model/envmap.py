"""Learnable equirectangular environment *feature* map with mip levels (Ref-GS "Sph-Mip").

Sampled at a direction with trilinear filtering: bilinear inside two adjacent mip levels,
linear between them; the mip level is ``roughness * (levels - 1)``. Longitude wraps around (the
columns' indices wrap); latitude is clamped at the poles. The mip levels are rows of one texel
table (:class:`MipTable`); a lookup gathers its eight taps from it, in torch's ops
(:meth:`EnvironmentMap.lookup_reference`, any device) or on the CPU in numba kernels with a
hand-written backward (:class:`TrilinearLookup`), instead of nvdiffrast. With autograd on the CPU a lookup
reads the map itself (:class:`MipLookup`: the same kernels, the table's first level a view of the map).

Direction convention: world z is up; longitude phi = atan2(y, x) maps to the map's columns,
colatitude theta = acos(z) to its rows (row 0 = +z).
"""

from __future__ import annotations

import math

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor, nn

from rtsplat.raster.numba_runtime import SURFEL_CHUNK, load_numba_module, numba_threads


class EnvironmentMap(nn.Module):
    def __init__(self, channels: int = 16, height: int = 512, width: int = 1024, levels: int = 9):
        super().__init__()
        self.levels = int(levels)
        # channels last (texel after texel, each texel's channels together): the texel table's first level
        # is then a view of the map, and the pyramid's 2x2 averages and their gradients run on contiguous texels
        self.features = nn.Parameter(torch.zeros(1, channels, height, width).to(memory_format=torch.channels_last))
        # (first row, height, width) of every level in the texel table; a buffer, so it lives on the
        # map's device and a lookup needs no copy from the host
        self.register_buffer("level_layout", torch.tensor(level_layout(height, width, self.levels)),
                             persistent=False)
        self._table_cache: tuple | None = None  # (key, table) of the last texel table built without autograd

    @property
    def channels(self) -> int:
        return self.features.shape[1]

    def pyramid(self, count: int | None = None) -> list[Tensor]:
        """The first ``count`` (default: all) mip levels (:func:`mip_levels`)."""
        return mip_levels(self.features, min(count or self.levels, self.levels))

    @staticmethod
    def direction_to_uv(directions: Tensor) -> tuple[Tensor, Tensor]:
        """Unit directions [M,3] -> (u in [0,1) longitude, v in [0,1] colatitude)."""
        x, y, z = directions.unbind(-1)
        phi = torch.atan2(y, x)  # (-pi, pi]
        u = (phi + math.pi) / (2 * math.pi)
        v = torch.acos(z.clamp(-1 + 1e-6, 1 - 1e-6)) / math.pi
        return u, v

    def texel_table(self, levels: int | None = None) -> tuple[Tensor, list[tuple[int, int, int]]]:
        """The first ``levels`` (default: all) mip levels' texels as rows of one table
        [sum H_l W_l, C] (channels contiguous, level after level, row major) and per level
        (first row, height, width): :meth:`pyramid`'s levels, built by :class:`MipTable`."""
        count = min(levels or self.levels, self.levels)
        table = MipTable.apply(self.features, count)
        return table, level_layout(self.features.shape[-2], self.features.shape[-1], count)

    @staticmethod
    def sample_level(level: Tensor, u: Tensor, v: Tensor) -> Tensor:
        """Bilinear sample [M,C] of one map ``level`` [1,C,H,W] at (u, v) [M]: the taps of
        :meth:`_bilinear_taps` (longitude wraps around, colatitude clamps at the poles). Without autograd
        the four taps are gathered and weighed one after the other into one [C,M] sum (the same values,
        in about half the time: no [C,M,4] tensors)."""
        _, C, H, W = level.shape
        # channel-major [C, H*W] is a view of the map (no copy); gathering whole columns from it is
        # several times faster than gathering 3-float rows from a strided texel-major view
        table = level[0].reshape(C, H * W)
        if torch.is_grad_enabled():
            rows, weights = EnvironmentMap._bilinear_taps(u, v, 0, H, W)
            taps = table.index_select(1, rows.reshape(-1)).reshape(C, *rows.shape)
            return (taps * weights[None].to(table.dtype)).sum(-1).T
        rows, weights = EnvironmentMap._bilinear_taps(u, v, 0, H, W, stacked=False)
        total = None
        for r, w in zip(rows, weights, strict=True):
            tap = table.index_select(1, r) * w.to(table.dtype)
            total = tap if total is None else total.add_(tap)
        return total.T

    @staticmethod
    def _bilinear_taps(u: Tensor, v: Tensor, offset: Tensor | int, H: Tensor | int, W: Tensor | int,
                       stacked: bool = True) -> tuple[Tensor, Tensor] | tuple[list[Tensor], list[Tensor]]:
        """Table rows [M,4] and weights [M,4] of the bilinear sample at (u, v) in the level of
        ``offset``/``H``/``W`` (per sample [M], or one int for every sample); not ``stacked``: the four
        columns of each as lists of [M]. Texel (i, j) has its centre at (u, v) = ((j + 0.5) / W,
        (i + 0.5) / H); columns wrap around (longitude), rows clamp (poles)."""
        x = u * W - 0.5
        y = v * H - 0.5
        x0 = torch.floor(x)
        y0 = torch.floor(y)
        fx = x - x0
        fy = y - y0
        x0 = x0.long()
        y0 = y0.long()
        if isinstance(H, Tensor):
            Hi, Wi = H.long(), W.long()
            ya = torch.minimum(torch.clamp_min(y0, 0), Hi - 1)
            yb = torch.minimum(torch.clamp_min(y0 + 1, 0), Hi - 1)
        else:  # one level for all samples: scalar operands, fewer [M] tensors
            Hi, Wi = int(H), int(W)
            ya = y0.clamp(0, Hi - 1)
            yb = (y0 + 1).clamp(0, Hi - 1)
        xa, xb = torch.remainder(x0, Wi), torch.remainder(x0 + 1, Wi)
        ya, yb = ya * Wi, yb * Wi
        if isinstance(offset, Tensor) or offset:
            ya, yb = ya + offset, yb + offset
        rows = [ya + xa, ya + xb, yb + xa, yb + xb]
        gx, gy = 1 - fx, 1 - fy
        weights = [gx * gy, fx * gy, gx * fy, fx * fy]
        if not stacked:
            return rows, weights
        return torch.stack(rows, 1), torch.stack(weights, 1)

    def forward(self, directions: Tensor, roughness: Tensor, table: Tensor | None = None) -> Tensor:
        """Features [M,C] at unit ``directions`` [M,3]; ``roughness`` [M] in [0,1] picks the level.

        Trilinear: the bilinear samples of levels ``floor(l)`` and ``floor(l) + 1`` (l = roughness x
        (levels - 1)) blended by the fraction of l. All eight taps of a sample are rows of one texel
        table; levels above the largest one sampled are not built. ``table``: the texel table of every
        level (:meth:`texel_table`) when the caller shares one between lookups of the same map (a render's
        tracked and untracked pixels); its gradient, if any, is the caller's. On the CPU (float32 or float64,
        numba installed) the lookup and its backward are numba kernels (:class:`TrilinearLookup`, or
        :class:`MipLookup` with autograd and no ``table``), with and without autograd alike; elsewhere torch's
        ops (:meth:`lookup_reference`), which the kernels are tested against."""
        u, v = self.direction_to_uv(directions)
        level = (roughness.clamp(0, 1) * (self.levels - 1)).reshape(-1)
        if table is None and torch.is_grad_enabled() and TrilinearLookup.applies(self.features[0, 0], u, v, level):
            self._table_cache = None  # see _lookup_table: a lookup with autograd drops the kept table
            return MipLookup.apply(self.features, u, v, level, self.level_layout,
                                   self._levels_read(level)).to(directions.dtype)
        if table is None:
            table = self._lookup_table(self._levels_read(level))
        if TrilinearLookup.applies(table, u, v, level):
            out = TrilinearLookup.apply(table, u, v, level, self.level_layout)
        else:
            out = self.lookup_reference(table, u, v, level)
        return out.to(directions.dtype)

    def _levels_read(self, level: Tensor) -> int:
        """How many levels (from the first) a lookup at mip ``level`` [M] reads: on the CPU up to the one above
        the largest sampled; elsewhere all of them (finding the largest would wait for the device)."""
        if level.device.type != "cpu":
            return self.levels
        if level.numel() == 0:
            return 1
        top = float(level.detach().max())
        if not math.isfinite(top):
            return self.levels
        low = min(max(math.floor(top), 0), self.levels - 1)
        return min(low + 1, self.levels - 1) + 1

    def lookup_reference(self, table: Tensor, u: Tensor, v: Tensor, level: Tensor) -> Tensor:
        """The trilinear lookup [M,C] of :meth:`forward` at (``u``, ``v``) and mip ``level`` [M] in torch's ops:
        with autograd one gather of the eight taps from ``table`` (and one scatter into it backward), without it
        the weighed taps written one by one."""
        lo = level.floor().clamp(0, self.levels - 1)
        frac = level - lo
        lo_i = lo.long()
        has_hi = lo_i + 1 < self.levels  # at the last level there is no next one: its taps weigh 0
        hi_i = torch.where(has_hi, lo_i + 1, lo_i)
        info = self.level_layout.to(u.device)  # [levels, 3]: first row, H, W
        stacked = torch.is_grad_enabled()
        rows, weights = [], []
        for idx, blend in ((lo_i, 1 - frac), (hi_i, frac * has_hi)):
            at = info[idx]
            r, w = self._bilinear_taps(u, v, at[:, 0], at[:, 1].to(u.dtype), at[:, 2].to(u.dtype), stacked=stacked)
            if stacked:
                rows.append(r)
                weights.append(w * blend[:, None])
            else:
                rows.extend(r)
                weights.extend(w_k * blend for w_k in w)
        if not stacked:
            # without autograd each weighed tap is written straight into its slot of the [M, 8, C] tensor
            # (no [M*8] index or weight tensors, no separate product tensor): the same products and the
            # same sum, so the same bits, in about 3/4 of the time
            taps = table.new_empty(u.shape[0], len(rows), table.shape[1])
            for k, (r, w) in enumerate(zip(rows, weights, strict=True)):
                torch.mul(table.index_select(0, r), w.to(table.dtype)[:, None], out=taps[:, k])
            return taps.sum(1)
        rows = torch.cat(rows, 1)  # [M, 8]
        weights = torch.cat(weights, 1).to(table.dtype)
        taps = table.index_select(0, rows.reshape(-1)).reshape(*rows.shape, table.shape[1])  # [M, 8, C]
        return (taps * weights[:, :, None]).sum(1)

    def _lookup_table(self, count: int) -> Tensor:
        """:meth:`texel_table` of ``count`` levels; without autograd it is kept and reused until the map
        changes (its version counter moves) or its device or dtype do, so frames rendered one after
        the other build the mip pyramid once. A lookup with autograd drops the kept table: the trainer's
        fused Adam step changes the map without moving its version counter, and it changes it only after
        a step whose lookups passed a gradient. So no lookup without autograd may run between such a
        lookup and the optimizer step: a training render shares its table instead (``table``)."""
        if torch.is_grad_enabled():
            self._table_cache = None
            return self.texel_table(count)[0]
        features = self.features
        key = (count, features._version, features.data_ptr(), features.dtype, features.device)
        if self._table_cache is None or self._table_cache[0] != key:
            self._table_cache = (key, self.texel_table(count)[0])
        return self._table_cache[1]


def mip_levels(features: Tensor, count: int) -> list[Tensor]:
    """``features`` [1,C,H,W] and its next ``count - 1`` mip levels: each the previous one's 2x2 average
    (``avg_pool2d`` with ``ceil_mode``: a partial window at an odd edge averages the texels it holds),
    or the previous one itself (the same tensor) once that is smaller than 2x4."""
    levels = [features]
    for _ in range(count - 1):
        top = levels[-1]
        levels.append(top if top.shape[-2] < 2 or top.shape[-1] < 4 else F.avg_pool2d(top, 2, ceil_mode=True))
    return levels


class MipTable(torch.autograd.Function):
    """``features`` [1,C,H,W] -> the texel table of its first ``count`` mip levels [sum H_l W_l, C]
    (:meth:`EnvironmentMap.texel_table`), with a backward of its own.

    The levels are :func:`mip_levels`'; for a channels-last map every level's rows are a view and the only
    copy is the table itself. The backward walks the levels of :func:`level_layout` from the coarsest
    down, adding a quarter of each texel's gradient to the four texels it averages (in place, on
    contiguous rows: no [1,C,H,W] gradient per level, no transposes), the same sums as autograd's through
    ``avg_pool2d``; a level of odd size goes through ``avg_pool2d``'s own backward, whose partial windows
    average fewer texels, and a level that repeats the one before (below 2x4) passes its gradient on whole."""

    @staticmethod
    def forward(ctx, features: Tensor, count: int) -> Tensor:
        ctx.layout = level_layout(features.shape[-2], features.shape[-1], count)
        channels = features.shape[1]
        return torch.cat([level[0].permute(1, 2, 0).reshape(-1, channels) for level in mip_levels(features, count)])

    @staticmethod
    def backward(ctx, grad: Tensor):
        channels = grad.shape[1]
        grad = grad.contiguous().clone()  # the levels' gradients accumulate in place, coarsest first
        level_grads = [grad[first:first + h * w].view(h, w, channels) for first, h, w in ctx.layout]
        spread_to_first_level(level_grads, ctx.layout)
        return level_grads[0].permute(2, 0, 1)[None], None


def spread_to_first_level(level_grads: list[Tensor], layout: list[tuple[int, int, int]]) -> None:
    """Add the gradients of the mip levels ``level_grads`` ([H_l, W_l, C] each, ``layout``'s levels) down to the
    first, in place, coarsest first: a quarter of each texel's gradient to the four texels it averages (on
    contiguous rows: no [1,C,H,W] gradient per level, no transposes), the same sums as autograd's through
    ``avg_pool2d``; a level of odd size goes through ``avg_pool2d``'s own backward, whose partial windows average
    fewer texels, and a level that repeats the one before (below 2x4) passes its gradient on whole."""
    for i in range(len(layout) - 1, 0, -1):
        coarse, fine = level_grads[i], level_grads[i - 1]
        (_, h, w), (_, fh, fw) = layout[i], layout[i - 1]
        channels = coarse.shape[-1]
        if (fh, fw) == (h, w):  # the same level again
            fine.add_(coarse)
        elif (fh, fw) == (2 * h, 2 * w):
            fine.view(h, 2, w, 2, channels).add_(coarse.view(h, 1, w, 1, channels), alpha=0.25)
        else:
            shape = torch.empty(1, channels, fh, fw, dtype=coarse.dtype, device=coarse.device)
            spread = torch.ops.aten.avg_pool2d_backward(coarse.permute(2, 0, 1)[None], shape, [2, 2], [2, 2],
                                                        [0, 0], True, True, None)
            fine.add_(spread[0].permute(1, 2, 0))


class TrilinearLookup(torch.autograd.Function):
    """The environment map's trilinear lookup on the CPU: ``table`` [T,C] (the texel table of
    :meth:`EnvironmentMap.texel_table`), samples at (``u``, ``v``) and mip ``level`` [M], ``layout`` [levels, 3]
    (first row, H, W of every level) -> [M,C] in the table's type, by the numba kernels of
    :mod:`rtsplat.model.envmap_kernels`. The values and gradients (of the table, u, v and the level) are those of
    :meth:`EnvironmentMap.lookup_reference` up to rounding (float64 arithmetic here), in a half to two thirds of
    its time forward and backward (docs/performance.md, "The environment lookup in numba"). A sample with a
    non-finite coordinate gives NaN and reads no texel."""

    @staticmethod
    def applies(table: Tensor, u: Tensor, v: Tensor, level: Tensor) -> bool:
        """Whether the kernels take this lookup: CPU tensors, a float32 or float64 table, numba installed."""
        if any(t.device.type != "cpu" for t in (table, u, v, level)):
            return False
        if table.dtype not in (torch.float32, torch.float64) or table.dim() != 2:
            return False
        return load_numba_module("rtsplat.model.envmap_kernels") is not None

    @staticmethod
    def forward(ctx, table: Tensor, u: Tensor, v: Tensor, level: Tensor, layout: Tensor) -> Tensor:
        data = table.detach().contiguous()
        out, ctx.taps = _lookup(data, data[:0], layout, u, v, level)
        ctx.save_for_backward(data)
        ctx.sample_dtypes = (u.dtype, v.dtype, level.dtype)
        return out

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad: Tensor):
        (table,) = ctx.saved_tensors
        g_table, _, *g_samples = _lookup_gradients(table, table[:0], ctx.taps, grad, ctx.needs_input_grad[0],
                                                   any(ctx.needs_input_grad[1:4]), ctx.sample_dtypes)
        return g_table, *g_samples, None


class MipLookup(torch.autograd.Function):
    """The trilinear lookup of :class:`TrilinearLookup` straight from the map: ``apply(features [1,C,H,W], u, v,
    level [M], layout [levels, 3], count)`` -> [M,C], the values of ``TrilinearLookup.apply(MipTable.apply(features,
    count), ...)`` and the same gradients, bit for bit, without the texel table's copy of the first level.

    The kernels read the texel table in two parts: the first level, a view of a channels-last map, and the ``count
    - 1`` coarser levels (:func:`mip_levels`), concatenated. The backward adds the first level's gradient into a
    buffer laid out as the map, which becomes the map's gradient, and the coarser levels' into one of their own,
    spread down to the first (:func:`spread_to_first_level`): no copy of the table's gradient, and none for the map's
    when its gradient is laid out as it is."""

    @staticmethod
    def forward(ctx, features: Tensor, u: Tensor, v: Tensor, level: Tensor, layout: Tensor, count: int) -> Tensor:
        _, channels, height, width = features.shape
        features = features.detach()
        fine = features[0].permute(1, 2, 0).reshape(height * width, channels).contiguous()
        coarser = [lv[0].permute(1, 2, 0).reshape(-1, channels) for lv in mip_levels(features, count)[1:]]
        coarse = torch.cat(coarser) if coarser else fine[:0]
        out, ctx.taps = _lookup(fine, coarse, layout, u, v, level)
        ctx.save_for_backward(fine, coarse)
        ctx.layout = level_layout(height, width, count)
        ctx.sample_dtypes = (u.dtype, v.dtype, level.dtype)
        return out

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad: Tensor):
        fine, coarse = ctx.saved_tensors
        g_fine, g_coarse, *g_samples = _lookup_gradients(fine, coarse, ctx.taps, grad, ctx.needs_input_grad[0],
                                                         any(ctx.needs_input_grad[1:4]), ctx.sample_dtypes)
        g_features = None
        if g_fine is not None:
            split = fine.shape[0]  # the table row where the coarser levels start, their row 0 in g_coarse
            level_grads = [g_fine.view(ctx.layout[0][1], ctx.layout[0][2], -1)] + [
                g_coarse[first - split:first - split + h * w].view(h, w, -1) for first, h, w in ctx.layout[1:]]
            spread_to_first_level(level_grads, ctx.layout)
            g_features = level_grads[0].permute(2, 0, 1)[None]
        return g_features, *g_samples, None, None


def _lookup(fine: Tensor, coarse: Tensor, layout: Tensor, u: Tensor, v: Tensor, level: Tensor) -> tuple[Tensor, tuple]:
    """The forward kernel on the texel table in two parts (its first rows in ``fine``, the rest in ``coarse``):
    the lookup [M,C] in the table's type, and what the backward reads (each sample's taps' rows, weights and the
    weights' derivatives)."""
    kernels = load_numba_module("rtsplat.model.envmap_kernels")
    split = fine.shape[0]
    m = u.shape[0]
    rows = np.empty((m, kernels.TAPS), dtype=np.int64)
    weights, d_u, d_v, d_level = (np.empty((m, kernels.TAPS), dtype=np.float64) for _ in range(4))
    out = torch.empty(m, fine.shape[1], dtype=fine.dtype)
    with numba_threads(SURFEL_CHUNK):
        kernels.lookup_forward_kernel(fine.numpy(), coarse.numpy(), split, layout.to("cpu", torch.int64).numpy(),
                                      _samples(u), _samples(v), _samples(level), rows, weights, d_u, d_v, d_level,
                                      out.numpy())
    return out, (rows, weights, d_u, d_v, d_level)


def _lookup_gradients(fine: Tensor, coarse: Tensor, taps: tuple, grad: Tensor, table_grad: bool, sample_grad: bool,
                      sample_dtypes: tuple) -> tuple:
    """The gradients of the table's two parts (``table_grad``; else None, None) and of the samples' u, v and level
    (``sample_grad``; else three None) from the lookup's gradient ``grad`` [M,C]."""
    kernels = load_numba_module("rtsplat.model.envmap_kernels")
    split = fine.shape[0]
    rows, weights, d_u, d_v, d_level = taps
    g = grad.to(fine.dtype).contiguous().numpy()
    g_fine = g_coarse = None
    samples = (None, None, None)
    if table_grad:
        g_fine, g_coarse = torch.zeros_like(fine), torch.zeros_like(coarse)
        kernels.lookup_table_grad_kernel(g, rows, weights, g_fine.numpy(), g_coarse.numpy(), split)
    if sample_grad:
        sample = np.empty((3, rows.shape[0]), dtype=np.float64)
        with numba_threads(SURFEL_CHUNK):
            kernels.lookup_sample_grad_kernel(fine.numpy(), coarse.numpy(), split, g, rows, d_u, d_v, d_level,
                                              *sample)
        samples = tuple(torch.from_numpy(s).to(dtype) for s, dtype in zip(sample, sample_dtypes, strict=True))
    return g_fine, g_coarse, *samples


def _samples(t: Tensor) -> np.ndarray:
    """A sample coordinate [M] as a contiguous numpy array of its own float type."""
    return t.detach().contiguous().numpy()


def level_layout(height: int, width: int, levels: int) -> list[tuple[int, int, int]]:
    """(first row, height, width) of each mip level in :meth:`EnvironmentMap.texel_table`, from the
    sizes alone (the same halving rule as :func:`mip_levels`)."""
    layout, offset = [], 0
    for _ in range(levels):
        layout.append((offset, height, width))
        offset += height * width
        if height >= 2 and width >= 4:
            height, width = math.ceil(height / 2), math.ceil(width / 2)
    return layout
