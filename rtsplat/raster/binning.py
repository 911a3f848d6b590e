"""Tile binning and depth sort: which surfels each screen tile must visit, front to back."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor


@dataclass
class TileBins:
    tiles_x: int
    tiles_y: int
    tile_size: int
    surfel_ids: Tensor  # [P] int64, surfel index of each (tile, surfel) pair, sorted by tile then depth
    tile_start: Tensor  # [tiles_x * tiles_y] int64, first pair of each tile
    tile_count: Tensor  # [tiles_x * tiles_y] int64, pairs of each tile
    width: int = 0  # image size in pixels (border tiles reach past it)
    height: int = 0

    @property
    def num_tiles(self) -> int:
        return self.tiles_x * self.tiles_y


@torch.no_grad()
def bin_tiles(
    bbox_min: Tensor, bbox_max: Tensor, depths: Tensor, valid: Tensor, width: int, height: int, tile_size: int
) -> TileBins:
    """Assign each valid surfel to every tile its screen box touches; sort each tile by depth.

    A surfel is evaluated at *every* pixel of the tiles it touches (as in 2DGS); the box only
    decides the tiles. Ties in depth keep the surfel order (stable sort).
    """
    device = depths.device
    tiles_x = (width + tile_size - 1) // tile_size
    tiles_y = (height + tile_size - 1) // tile_size
    n = depths.shape[0]
    ids = torch.nonzero(valid, as_tuple=False).flatten()
    # clamped while still floats: a box edge beyond the int64 range must not wrap around
    last = bbox_min.new_tensor([tiles_x - 1, tiles_y - 1])
    lo = torch.minimum(torch.floor(bbox_min[ids] / tile_size).clamp_min(0), last).long()
    hi = torch.minimum(torch.floor(bbox_max[ids] / tile_size).clamp_min(0), last).long()
    span = hi - lo + 1
    counts = span[:, 0] * span[:, 1]
    pair_surfel = torch.repeat_interleave(ids, counts)
    first = torch.cumsum(counts, 0) - counts
    local = torch.arange(pair_surfel.shape[0], device=device) - torch.repeat_interleave(first, counts)
    span_x = torch.repeat_interleave(span[:, 0], counts)
    tile_x = torch.repeat_interleave(lo[:, 0], counts) + local % span_x
    tile_y = torch.repeat_interleave(lo[:, 1], counts) + local // span_x
    tile_id = tile_y * tiles_x + tile_x

    order = torch.argsort(depths.detach(), stable=True)
    rank = torch.empty_like(order)
    rank[order] = torch.arange(n, device=device)
    key = tile_id * max(n, 1) + rank[pair_surfel]
    key_sorted, perm = torch.sort(key, stable=True)
    surfel_ids = pair_surfel[perm]
    tile_count = torch.bincount(tile_id, minlength=tiles_x * tiles_y)
    tile_start = torch.cumsum(tile_count, 0) - tile_count
    return TileBins(tiles_x, tiles_y, tile_size, surfel_ids, tile_start, tile_count, width, height)
