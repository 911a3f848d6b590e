"""Readable pure-PyTorch reference rasterizer: the oracle for every faster backend.

For every screen tile it evaluates all (pixel, surfel) pairs of the tile as dense tensors
[tiles, pixels, surfels] and composites front to back with cumulative products, so autograd
provides the gradients of every surfel parameter. Semantics (shared by all backends):

* ray-splat intersection through the homogeneous plane of the surfel (2DGS):
  h_x = M_x - x M_w, h_y = M_y - y M_w, (u, v) = (p_0, p_1) / p_2 with p = h_x x h_y;
  rho_3d = u^2 + v^2, or +inf when the surfel is seen edge-on (|p_2| <= 1e-6 max(|p_0|, |p_1|));
* object-space low-pass fallback rho = min(rho_3d, rho_2d), rho_2d = 2 |centre - pixel|^2;
  the depth of the pair is the ray-plane intersection depth, or the centre depth when the
  low-pass term wins (2DGS uses the intersection depth there too; it diverges for edge-on
  surfels, so we deliberately use the centre depth, which is finite and continuous);
* G = exp(-rho / 2); per-pair surface alpha min(0.99, occupancy G) and volume alpha
  min(0.99, occupancy opacity G); a pair contributes to a weight set when its alpha >= 1/255
  and its depth >= near (0.2);
* each weight set stops on its own: a surfel that would bring that set's transmittance below
  1e-4 is not composited, nor is anything behind it (2DGS ``test_T``); a fast backend may end
  the traversal of a pixel only when both sets have stopped;
* a surfel is evaluated at every pixel of every tile that its 3-sigma screen box touches.
"""

from __future__ import annotations

import torch
from torch import Tensor

from rtsplat.camera import PIXEL_CENTER_OFFSET, Camera
from rtsplat.raster.binning import TileBins, bin_tiles
from rtsplat.raster.projection import Projection, project_surfels
from rtsplat.raster.types import RasterOutput, RasterSettings, Surfels

EDGE_ON_RATIO = 1e-6


def exclusive_cumprod(x: Tensor, dim: int = -1) -> Tensor:
    """prod_{j<i} x_j along ``dim`` (1 for the first element)."""
    ones = torch.ones_like(x.narrow(dim, 0, 1))
    return torch.cat([ones, torch.cumprod(x, dim).narrow(dim, 0, x.shape[dim] - 1)], dim)


def exclusive_cumsum(x: Tensor, dim: int = -1) -> Tensor:
    return torch.cumsum(x, dim) - x


def ndc_depth(z: Tensor, near: float, far: float) -> Tensor:
    """The [0,1] depth mapping of the 2DGS distortion loss."""
    return far / (far - near) * (1.0 - near / z)


def _tile_chunks(bins: TileBins, pixels_per_tile: int, budget: int) -> list[Tensor]:
    """Group non-empty tiles so that (tiles x pixels x max surfels) stays under ``budget``."""
    counts = bins.tile_count.tolist()
    chunks, current, current_max = [], [], 0
    for tile, count in enumerate(counts):
        if count == 0:
            continue
        new_max = max(current_max, count)
        if current and (len(current) + 1) * pixels_per_tile * new_max > budget:
            chunks.append(current)
            current, new_max = [], count
        current.append(tile)
        current_max = new_max
    if current:
        chunks.append(current)
    return [torch.tensor(c, dtype=torch.long, device=bins.surfel_ids.device) for c in chunks]


def _composite_chunk(
    tiles: Tensor, bins: TileBins, proj: Projection, surfels: Surfels, settings: RasterSettings
) -> tuple[Tensor, Tensor, Tensor]:
    """Composite the tiles of one chunk. Returns (channels [T,P,C], surfel ids [T,K], used [T,K])."""
    ts = bins.tile_size
    device, dtype = proj.depths.device, proj.depths.dtype
    count = bins.tile_count[tiles]
    kmax = int(count.max())
    slot = torch.arange(kmax, device=device)
    in_list = slot[None, :] < count[:, None]  # [T,K]
    pair = (bins.tile_start[tiles][:, None] + slot[None, :]).clamp_max(max(bins.surfel_ids.shape[0] - 1, 0))
    ids = torch.where(in_list, bins.surfel_ids[pair], torch.zeros_like(pair))  # [T,K]

    # pixel centres of each tile [T,P]
    local = torch.arange(ts, device=device, dtype=dtype) + PIXEL_CENTER_OFFSET
    tx = (tiles % bins.tiles_x).to(dtype) * ts
    ty = torch.div(tiles, bins.tiles_x, rounding_mode="floor").to(dtype) * ts
    px = (tx[:, None, None] + local[None, None, :]).expand(-1, ts, ts).reshape(len(tiles), ts * ts)
    py = (ty[:, None, None] + local[None, :, None]).expand(-1, ts, ts).reshape(len(tiles), ts * ts)

    M = proj.ray_transform[ids]  # [T,K,3,3]
    row_x, row_y, row_w = M[:, None, :, 0, :], M[:, None, :, 1, :], M[:, None, :, 2, :]  # [T,1,K,3]
    h_x = row_x - px[:, :, None, None] * row_w  # [T,P,K,3]
    h_y = row_y - py[:, :, None, None] * row_w
    p = torch.linalg.cross(h_x, h_y, dim=-1)
    p0, p1, p2 = p.unbind(-1)
    plane_ok = p2.abs() > EDGE_ON_RATIO * torch.maximum(p0.abs(), p1.abs()).detach()
    p2_safe = torch.where(plane_ok, p2, torch.ones_like(p2))
    u = torch.where(plane_ok, p0 / p2_safe, torch.zeros_like(p0))
    v = torch.where(plane_ok, p1 / p2_safe, torch.zeros_like(p1))
    rho_3d = torch.where(plane_ok, u * u + v * v, torch.full_like(u, float("inf")))

    center = proj.centers[ids]  # [T,K,2]
    dx = center[:, None, :, 0] - px[:, :, None]
    dy = center[:, None, :, 1] - py[:, :, None]
    rho_2d = settings.lowpass_inv_var * (dx * dx + dy * dy)
    use_plane = rho_3d <= rho_2d
    rho = torch.where(use_plane, rho_3d, rho_2d)
    w_row = M[:, None, :, 2, :]
    z_plane = u * w_row[..., 0] + v * w_row[..., 1] + w_row[..., 2]
    z = torch.where(use_plane, z_plane, w_row[..., 2].expand_as(z_plane))
    gauss = torch.exp(-0.5 * rho)

    pair_ok = in_list[:, None, :] & (z >= settings.near)
    z = torch.where(pair_ok, z, torch.full_like(z, settings.near))  # keeps 1/z finite below
    occupancy = surfels.occupancy[ids][:, None, :]
    opacity = surfels.opacity[ids][:, None, :]
    a_s = (occupancy * gauss).clamp_max(settings.alpha_max)
    a_v = (occupancy * opacity * gauss).clamp_max(settings.alpha_max)
    hit_s = pair_ok & (a_s >= settings.alpha_min)
    hit_v = pair_ok & (a_v >= settings.alpha_min)
    a_s = torch.where(hit_s, a_s, torch.zeros_like(a_s))
    a_v = torch.where(hit_v, a_v, torch.zeros_like(a_v))

    T_s = exclusive_cumprod(1.0 - a_s)
    T_v = exclusive_cumprod(1.0 - a_v)
    with torch.no_grad():
        keep_s = hit_s & (T_s * (1.0 - a_s) >= settings.transmittance_min)
        keep_v = hit_v & (T_v * (1.0 - a_v) >= settings.transmittance_min)
        # each set stops at its first failing surfel: keep only the prefix before it
        keep_s &= torch.cumprod((keep_s | ~hit_s).to(torch.uint8), -1).bool()
        keep_v &= torch.cumprod((keep_v | ~hit_v).to(torch.uint8), -1).bool()
    w_s = torch.where(keep_s, a_s * T_s, torch.zeros_like(a_s))  # surface weights p_i
    w_v = torch.where(keep_v, a_v * T_v, torch.zeros_like(a_v))  # volume weights w_i

    feats = torch.cat([surfels.features, proj.normals], -1)[ids]  # [T,K,F+3]
    surface = torch.einsum("tpk,tkc->tpc", w_s, feats)
    alpha = w_s.sum(-1, keepdim=True)
    depth_sum = (w_s * z).sum(-1, keepdim=True)
    with torch.no_grad():
        crossing = keep_s & (T_s > 0.5)
        last = (crossing * (slot + 1)).argmax(-1, keepdim=True)  # last surfel with T > 0.5
        has_median = crossing.any(-1, keepdim=True)
    depth_median = torch.where(has_median, torch.gather(z, -1, last), torch.zeros_like(alpha))
    m = ndc_depth(z, settings.near, settings.far)
    distortion = (
        w_s * (m * m * exclusive_cumsum(w_s) + exclusive_cumsum(w_s * m * m) - 2 * m * exclusive_cumsum(w_s * m))
    ).sum(-1, keepdim=True)

    color = torch.einsum("tpk,tkc->tpc", w_v, surfels.colors[ids])
    volume_alpha = w_v.sum(-1, keepdim=True)
    volume_depth_sum = (w_v * z).sum(-1, keepdim=True)

    channels = torch.cat(
        [surface, alpha, depth_sum, depth_median, distortion, color, volume_alpha, volume_depth_sum], -1
    )
    # visible: contributed to a pixel of the image (border tiles extend past the image edge)
    inside = ((px < bins.width) & (py < bins.height))[:, :, None]  # [T,P,1]
    used = ((keep_s | keep_v) & inside).any(1)  # [T,K]
    return channels, ids, used & in_list


def _safe_divide(num: Tensor, den: Tensor) -> Tensor:
    """num / den where den > 0, else 0 (the gradient stays finite: den is 0 or >= 1/255 here)."""
    ok = den > 0
    return torch.where(ok, num / torch.where(ok, den, torch.ones_like(den)), torch.zeros_like(num))


def _zero_through(surfels: Surfels, screen_probe: Tensor | None) -> Tensor:
    """A scalar 0 that depends on every surfel tensor needing a gradient (each gets a zero gradient):
    when every surfel is culled the image still backpropagates. Sums of empty slices, so non-finite
    parameters give 0, not NaN."""
    tensors = [surfels.means, surfels.quats, surfels.scales, surfels.occupancy, surfels.opacity,
               surfels.features, surfels.colors, screen_probe]
    zero = torch.zeros((), device=surfels.device, dtype=surfels.dtype)
    for t in tensors:
        if t is not None and t.requires_grad:
            zero = zero + t[:0].sum()
    return zero


def rasterize_reference(
    surfels: Surfels, camera: Camera, settings: RasterSettings, screen_probe: Tensor | None = None
) -> RasterOutput:
    n = len(surfels)
    device, dtype = surfels.device, surfels.dtype
    if screen_probe is None and torch.is_grad_enabled():
        screen_probe = torch.zeros(n, 2, device=device, dtype=dtype, requires_grad=True)
    proj = project_surfels(surfels, camera, settings, screen_probe)
    W, H, ts = camera.width, camera.height, settings.tile_size
    bins = bin_tiles(proj.bbox_min, proj.bbox_max, proj.depths, proj.valid, W, H, ts)

    F = surfels.features.shape[1]
    n_channels = F + 3 + 1 + 1 + 1 + 1 + 3 + 1 + 1
    P = ts * ts
    visible = torch.zeros(n, dtype=torch.bool, device=device)
    tile_ids, tile_values = [], []
    for tiles in _tile_chunks(bins, P, settings.max_pairs_per_chunk):
        channels, ids, used = _composite_chunk(tiles, bins, proj, surfels, settings)
        tile_ids.append(tiles)
        tile_values.append(channels)
        visible[ids[used]] = True
    image_tiles = torch.zeros(bins.num_tiles, P, n_channels, device=device, dtype=dtype)
    if tile_ids:
        image_tiles = image_tiles.index_copy(0, torch.cat(tile_ids), torch.cat(tile_values))
    image = (
        image_tiles.reshape(bins.tiles_y, bins.tiles_x, ts, ts, n_channels)
        .permute(0, 2, 1, 3, 4)
        .reshape(bins.tiles_y * ts, bins.tiles_x * ts, n_channels)[:H, :W]
    )
    if torch.is_grad_enabled() and not image.requires_grad:
        image = image + _zero_through(surfels, screen_probe)
    return split_image(image, F, proj, visible, screen_probe)


def split_image(image: Tensor, num_features: int, proj: Projection, visible: Tensor,
                screen_probe: Tensor | None) -> RasterOutput:
    """The :class:`RasterOutput` of a composited image [H,W,C] whose channels are, in order: the
    G-buffer (``num_features``), normal 3, alpha, depth sum, median depth, distortion, colour 3,
    volume alpha, volume depth sum. Every backend composites into this layout."""
    features, normal, alpha, depth_sum, depth_median, distortion, color, volume_alpha, volume_depth_sum = image.split(
        [num_features, 3, 1, 1, 1, 1, 3, 1, 1], dim=-1
    )
    return RasterOutput(
        features=features,
        normal=normal,
        depth=_safe_divide(depth_sum, alpha),
        depth_median=depth_median,
        alpha=alpha,
        distortion=distortion,
        color=color,
        volume_alpha=volume_alpha,
        volume_depth=_safe_divide(volume_depth_sum, volume_alpha),
        means2d=proj.centers,
        radii=proj.radii,
        visible=visible,
        screen_probe=screen_probe,
        width=image.shape[1],
        height=image.shape[0],
    )


def rasterize_tiled(composite, surfels: Surfels, camera: Camera, settings: RasterSettings,
                    screen_probe: Tensor | None, project=project_surfels, binner=bin_tiles) -> RasterOutput:
    """The frame the fast backends share: the screen probe, projection and tile binning (``project`` and
    ``binner``: by default the torch functions, on the surfels' device), then ``composite`` (an autograd
    Function's ``apply`` taking the ray transforms, centres, occupancy, opacity, G-buffer features with
    the normals appended, colours, the bins and ``(W, H, settings)``, returning the image in
    :func:`split_image`'s layout and the visibility)."""
    n = len(surfels)
    if screen_probe is None and torch.is_grad_enabled():
        screen_probe = torch.zeros(n, 2, device=surfels.device, dtype=surfels.dtype, requires_grad=True)
    proj = project(surfels, camera, settings, screen_probe)
    W, H = int(camera.width), int(camera.height)
    bins = binner(proj.bbox_min, proj.bbox_max, proj.depths, proj.valid, W, H, settings.tile_size)
    feats = torch.cat([surfels.features, proj.normals], -1)
    image, visible = composite(proj.ray_transform, proj.centers, surfels.occupancy, surfels.opacity, feats,
                               surfels.colors, bins, (W, H, settings))
    return split_image(image, surfels.features.shape[1], proj, visible, screen_probe)
