"""Near-field reflections in planar glass: mirror planes, mirrored surfels and which pixel sees which plane.

A direction-only environment lookup places everything a pane reflects at infinity. What a pane
reflects of the scene near it (the room behind a shop window, the car beside a car window) is in the
model already, as the surfels that the views see directly. For a planar pane, that reflection is the
model rendered through the pane's mirror image:

* the pane is a plane ``n . x + d = 0`` with a rectangle on it (:func:`fit_planes` finds them in oriented
  points; the trainer gives it the surface depth of the see-through pixels);
* the surfels on the camera's side of the plane (not the glass itself, which lies on the plane, and
  not what is seen through it, which lies behind) are reflected in the plane (:func:`mirror_points`,
  :func:`mirror_quats`: centres mirrored, rotations composed with the reflection so that they stay
  rotations) and rasterized from the real camera (``RTModel.near_reflection``): every pixel then sees,
  along its own ray, the scene that the ray reflected in the plane sees;
* each pixel takes the near reflection of the first plane rectangle its ray hits
  (:func:`plane_assignment`), with the volume alpha of that render as its coverage. What the reflected
  ray sees past the model's surfels (sky, far scenery) stays the environment lookup's:
  ``L = C_near + (1 - A_near) L_env`` (:class:`rtsplat.model.specular.SpecularNetwork`).

A plane row holds ``normal (3), centre (3), u axis (3), half extents along u and v (2), thickness (1)``
(``v = n x u``; surfels within the thickness of the plane are the glass and are not reflected), then the
pane's bend (6): the height of the glass above the plane, ``h(u, v) = a u^2 + b u v + c v^2 + d u + e v + f``
in the plane's own coordinates (zero for flat glass; rows of 12 columns read as flat).

Curved glass (a windshield, a bent shop window) is served by the same mirrored render. At a pixel whose
glass is bent, the ray meets the glass at a point ``x`` off the plane, with a normal tilted from the
plane's; the reflected ray ``r`` leaves ``x`` in another direction than the plane would send it. Mirrored
in the plane, that ray is the straight line from ``M x`` along ``M r``; where it meets what it sees (at the
distance the mirrored render shows at that pixel) is a point the real camera sees at some pixel ``q`` of
the mirrored render, and the pixel takes its near reflection from there (:func:`bent_lookup`, sampled
bilinearly). For flat glass ``q`` is the pixel itself. The bend is fitted with the plane
(:func:`fit_planes`: a least-squares quadric over the plane's inliers, kept where it tilts the normal by at
least :data:`BEND_MIN_DEGREES` somewhere on the rectangle).
"""

from __future__ import annotations

import torch
from torch import Tensor

from rtsplat.camera import PIXEL_CENTER_OFFSET, Camera

PLANE_COLUMNS = 18
FLAT_COLUMNS = 12  # a row without its bend (flat glass)
BEND_MIN_DEGREES = 1.0  # a fitted bend that tilts the normal less than this anywhere on its rectangle is flat
BEND_MIN_POINTS = 32  # fewer inliers than this fit no bend
MIN_RAY_COSINE = 1e-4  # rays this close to parallel with a plane never hit it (no grazing blow-up)
CHUNK = 8192  # points scored against every candidate plane at once in fit_planes


def empty_planes(dtype=torch.float32, device=None) -> Tensor:
    return torch.zeros(0, PLANE_COLUMNS, dtype=dtype, device=device)


def with_bend(planes: Tensor) -> Tensor:
    """Plane rows [K,18]: rows of 12 columns (flat glass) get a zero bend; rows of 18 are returned as they are."""
    if planes.shape[-1] == PLANE_COLUMNS:
        return planes
    if planes.shape[-1] != FLAT_COLUMNS:
        raise ValueError(f"plane rows have {FLAT_COLUMNS} or {PLANE_COLUMNS} columns, got {planes.shape[-1]}")
    return torch.cat([planes, planes.new_zeros(*planes.shape[:-1], PLANE_COLUMNS - FLAT_COLUMNS)], -1)


def plane_bend(planes: Tensor) -> Tensor:
    """The bend coefficients ``a, b, c, d, e, f`` [K,6] of plane rows (zero for rows of 12 columns)."""
    return with_bend(planes)[:, FLAT_COLUMNS:PLANE_COLUMNS]


def bend_height(bend: Tensor, u: Tensor, v: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """The glass's height above its plane ``h`` and its slopes ``dh/du``, ``dh/dv`` at plane coordinates
    ``u``, ``v`` (any shape), for one row's bend ``a..f`` [6] (``h = a u^2 + b u v + c v^2 + d u + e v + f``)."""
    a, b, c, d, e, f = bend.unbind(-1)
    height = a * u * u + b * u * v + c * v * v + d * u + e * v + f
    return height, 2.0 * a * u + b * v + d, b * u + 2.0 * c * v + e


def plane_parts(planes: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor, Tensor]:
    """normal [K,3], centre [K,3], u [K,3], v [K,3], half extents [K,2] and thickness [K] of plane rows
    [K,12 or 18]."""
    n, c, u, half, thickness = planes[:, 0:3], planes[:, 3:6], planes[:, 6:9], planes[:, 9:11], planes[:, 11]
    return n, c, u, torch.cross(n, u, dim=-1), half, thickness


def signed_distance(points: Tensor, normal: Tensor, centre: Tensor) -> Tensor:
    """``n . (x - c)`` for points [...,3] and one plane's unit normal and centre [3]."""
    return ((points - centre) * normal).sum(-1)


def mirror_points(points: Tensor, normal: Tensor, centre: Tensor) -> Tensor:
    """Points [...,3] reflected in the plane through ``centre`` with unit ``normal``."""
    return points - 2.0 * signed_distance(points, normal, centre)[..., None] * normal


def quat_multiply(a: Tensor, b: Tensor) -> Tensor:
    """Hamilton product of quaternions (w, x, y, z), broadcasting over leading dimensions."""
    aw, ax, ay, az = a.unbind(-1)
    bw, bx, by, bz = b.unbind(-1)
    return torch.stack([
        aw * bw - ax * bx - ay * by - az * bz,
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
    ], -1)


def mirror_quats(quats: Tensor, normal: Tensor) -> Tensor:
    """Rotations [N,4] of surfels reflected in a plane with unit ``normal``.

    The reflection ``H = I - 2 n n^T`` turns a rotation ``R`` into ``H R``, which is not a rotation;
    flipping the surfel's first tangent axis (a 2D Gaussian is symmetric under it) makes it one:
    ``H R diag(-1, 1, 1) = Rot_n(pi) R Rot_x(pi)``, i.e. ``q' = (0, n) q (0, 1, 0, 0)``."""
    about_normal = torch.cat([torch.zeros_like(normal[:1]), normal])
    about_x = torch.tensor([0.0, 1.0, 0.0, 0.0], dtype=quats.dtype, device=quats.device)
    return quat_multiply(quat_multiply(about_normal.to(quats.dtype), quats), about_x)


def rotate_vectors(vectors: Tensor, rotation: Tensor) -> Tensor:
    """``vectors`` [K,3] turned by the rotation vectors ``rotation`` [K,3] (axis times angle, radians;
    Rodrigues' formula). Smooth at a zero rotation: the sine and cosine terms use their series below
    1e-4 radians, so the gradient there is exact and finite."""
    angle_sq = (rotation * rotation).sum(-1, keepdim=True)
    small = angle_sq < 1e-8
    angle = torch.sqrt(torch.where(small, torch.ones_like(angle_sq), angle_sq))
    sin_over = torch.where(small, 1.0 - angle_sq / 6.0, torch.sin(angle) / angle)
    one_minus_cos_over = torch.where(small, 0.5 - angle_sq / 24.0, (1.0 - torch.cos(angle)) / (angle * angle))
    cross = torch.cross(rotation, vectors, dim=-1)
    return vectors + sin_over * cross + one_minus_cos_over * torch.cross(rotation, cross, dim=-1)


def move_planes(planes: Tensor, rotation: Tensor, shift: Tensor) -> Tensor:
    """Plane rows [K,12 or 18] turned about their centres by the rotation vectors ``rotation`` [K,3] (normal
    and rectangle together) and then moved by ``shift`` [K] along their turned normals; extents, thickness
    and bend (in the plane's own coordinates) stay. Differentiable in ``rotation`` and ``shift`` (the trainer
    refines the fitted planes this way)."""
    n, c, u, _, half, thickness = plane_parts(planes)
    n = rotate_vectors(n, rotation)
    u = rotate_vectors(u, rotation)
    c = c + shift[:, None] * n
    return torch.cat([n, c, u, half, thickness[:, None], planes[:, FLAT_COLUMNS:]], -1)


def plane_assignment(camera: Camera, planes: Tensor, directions: Tensor) -> tuple[Tensor, Tensor]:
    """For each pixel ray (unit ``directions`` [H,W,3] from the camera centre), the index of the first
    plane rectangle it hits in front of the camera (-1: none) [H,W] and the distance to it [H,W]
    (inf where none): :func:`first_plane_hit` from the camera centre."""
    return first_plane_hit(camera.center.to(directions.dtype), directions, planes)


def first_plane_hit(origins: Tensor, directions: Tensor, planes: Tensor) -> tuple[Tensor, Tensor]:
    """For rays from ``origins`` [...,3] (or one [3]) along unit ``directions`` [...,3], the index of the
    first plane rectangle hit in front of the origin (-1: none) and the distance to it (inf where none).
    Rays within :data:`MIN_RAY_COSINE` of parallel to a plane miss it."""
    shape = directions.shape[:-1]
    if planes.shape[0] == 0:
        return (torch.full(shape, -1, dtype=torch.long, device=directions.device),
                torch.full(shape, float("inf"), dtype=directions.dtype, device=directions.device))
    n, c, u, v, half, _ = plane_parts(planes.to(directions.dtype))
    origin = origins.to(directions.dtype)[..., None, :]  # [...,1,3]
    cosine = directions @ n.T  # [...,K]
    facing = cosine.abs() > MIN_RAY_COSINE
    t = ((c - origin) * n).sum(-1) / torch.where(facing, cosine, torch.ones_like(cosine))
    hit = origin + t[..., None] * directions[..., None, :]  # [...,K,3]
    local = hit - c
    inside = ((local * u).sum(-1).abs() <= half[:, 0]) & ((local * v).sum(-1).abs() <= half[:, 1])
    valid = facing & inside & (t > 0) & torch.isfinite(t)
    t = torch.where(valid, t, torch.full_like(t, float("inf")))
    distance, index = t.min(-1)
    index = torch.where(torch.isfinite(distance), index, torch.full_like(index, -1))
    return index, distance


def is_bent(planes: Tensor) -> Tensor:
    """[K] bool: the rows whose bend is not zero (curved glass, whose pixels :func:`bent_lookup` moves)."""
    return (plane_bend(planes) != 0).any(-1)


def bent_lookup(camera: Camera, directions: Tensor, plane: Tensor, distance: Tensor,
                content_distance: Tensor, iterations: int = 3) -> tuple[Tensor, Tensor]:
    """Where each pixel of bent glass finds its near reflection in the render mirrored in its plane.

    ``directions`` [H,W,3]: the pixels' unit rays from the camera centre; ``plane``: one row [18];
    ``distance`` [H,W]: along each ray to the plane (inf where the ray misses it); ``content_distance``
    [H,W]: along each ray to what the mirrored render shows there (inf where it shows nothing). Returns
    the pixel coordinates [H,W,2] (x, y; pixel centres at +0.5) to sample the mirrored render at, and [H,W]
    bool where that is defined (the ray meets the plane and the mirrored point lies in front of the camera).

    The ray meets the glass at ``x``, at the glass's height above the plane (``iterations`` fixed-point steps
    from the plane's hit), reflects about the bent normal
    there and is mirrored in the plane: the line from ``x' = M x`` along ``r' = M r``. What it sees is the
    point of the mirrored render that lies on that line: starting from the median distance the render
    shows, ``iterations`` times the line's point at the current distance is projected to a pixel ``q``, and
    the distance becomes that from ``x'`` to what the render shows at ``q`` (a reprojection that converges
    where the render's depth varies slowly). Where the render shows nothing at ``q`` the distance stays.
    With a zero bend the line is the pixel's own ray and ``q`` the pixel itself, whatever the distance. No
    gradient: the lookup is a place to read the render, whose colours carry the gradient."""
    with torch.no_grad():
        dtype = directions.dtype
        H, W = distance.shape
        row = with_bend(plane[None].to(dtype))
        n, c, u, v, _, _ = (t[0] for t in plane_parts(row))
        origin = camera.center.to(dtype)
        hit = torch.isfinite(distance)
        t = torch.where(hit, distance, torch.zeros_like(distance))[..., None]
        cosine = directions @ n
        cosine = torch.where(cosine.abs() > MIN_RAY_COSINE, cosine,
                             torch.full_like(cosine, MIN_RAY_COSINE) * torch.where(cosine < 0, -1.0, 1.0))
        bend = plane_bend(row)[0]
        glass = origin + t * directions
        for _ in range(iterations):  # where the ray meets the bent glass: its height where the ray is now
            local = glass - c
            height, slope_u, slope_v = bend_height(bend, local @ u, local @ v)
            glass = origin + (t + (height / cosine)[..., None]) * directions
        normal = torch.nn.functional.normalize(n - slope_u[..., None] * u - slope_v[..., None] * v, dim=-1)
        reflected = directions - 2.0 * (directions * normal).sum(-1, keepdim=True) * normal
        start = glass - 2.0 * ((glass - c) @ n)[..., None] * n
        along = reflected - 2.0 * (reflected @ n)[..., None] * n
        seen = torch.isfinite(content_distance)
        shown_at = torch.where(seen, content_distance, torch.zeros_like(content_distance))
        content = origin + shown_at[..., None] * directions
        view = camera.to(dtype=dtype)

        def project(points: Tensor) -> tuple[Tensor, Tensor]:  # pixel coordinates [H,W,2], camera depth [H,W]
            xy, depth = view.project(points.reshape(-1, 3))
            return xy.reshape(H, W, 2), depth.reshape(H, W)

        typical = content_distance[seen & hit].median() if bool((seen & hit).any()) else None
        if typical is None:  # the render shows nothing: the line's direction alone (its vanishing point)
            direction = along @ view.rotation.T
            depth = direction[..., 2]
            xy = (direction @ view.K.T)[..., :2] / torch.where(depth > 0, depth, torch.ones_like(depth))[..., None]
        else:
            reach = (typical - t).clamp_min(0.0)
            for _ in range(iterations):
                xy, depth = project(start + reach * along)
                col = (xy[..., 0] - PIXEL_CENTER_OFFSET).round().long()
                line = (xy[..., 1] - PIXEL_CENTER_OFFSET).round().long()
                inside = ((depth > 0) & (col >= 0) & (col < W) & (line >= 0) & (line < H)
                          & torch.isfinite(xy).all(-1))
                flat = (line.clamp(0, H - 1) * W + col.clamp(0, W - 1)).reshape(-1)
                there = inside & seen.reshape(-1)[flat].reshape(H, W)
                target = content.reshape(-1, 3)[flat].reshape(H, W, 3)
                reach = torch.where(there[..., None], (target - start).norm(dim=-1, keepdim=True), reach)
            xy, depth = project(start + reach * along)
        in_front = depth > 1e-6 * (1.0 + t[..., 0])
        valid = hit & in_front & torch.isfinite(xy).all(-1)
        return torch.where(valid[..., None], xy, torch.zeros_like(xy)), valid


def sample_pixels(image: Tensor, xy: Tensor, valid: Tensor) -> Tensor:
    """``image`` [H,W,C] read bilinearly at pixel coordinates ``xy`` [H,W,2] (pixel centres at +0.5), zero
    outside the image and where not ``valid`` [H,W]. Differentiable in ``image``."""
    H, W = image.shape[:2]
    grid = torch.stack([2.0 * xy[..., 0] / W - 1.0, 2.0 * xy[..., 1] / H - 1.0], -1).to(image.dtype)
    out = torch.nn.functional.grid_sample(image.permute(2, 0, 1)[None], grid[None], mode="bilinear",
                                          padding_mode="zeros", align_corners=False)[0].permute(1, 2, 0)
    return torch.where(valid[..., None], out, torch.zeros_like(out))


def fit_bend(local: Tensor, u: Tensor, v: Tensor, normal: Tensor, half: tuple[float, float]) -> Tensor:
    """The bend ``a..f`` [6] of the glass whose points lie at ``local`` [N,3] from a plane's centre (plane
    axes ``u``, ``v``, ``normal``): the least-squares quadric height over the plane; zero when fewer than
    :data:`BEND_MIN_POINTS` points or when it tilts the normal less than :data:`BEND_MIN_DEGREES` at every
    corner and edge midpoint of the rectangle of half extents ``half``."""
    zero = torch.zeros(6, dtype=local.dtype)
    if local.shape[0] < BEND_MIN_POINTS:
        return zero
    pu, pv, height = local @ u, local @ v, local @ normal
    scale_u, scale_v = max(half[0], 1e-9), max(half[1], 1e-9)  # solve in unit coordinates: well conditioned
    su, sv = pu / scale_u, pv / scale_v
    design = torch.stack([su * su, su * sv, sv * sv, su, sv, torch.ones_like(su)], -1)
    solution = torch.linalg.lstsq(design, height[:, None]).solution[:, 0]
    if not torch.isfinite(solution).all():
        return zero
    scales = torch.tensor([scale_u ** 2, scale_u * scale_v, scale_v ** 2, scale_u, scale_v, 1.0], dtype=local.dtype)
    bend = solution / scales
    corners = torch.tensor([[su_, sv_] for su_ in (-1.0, 0.0, 1.0) for sv_ in (-1.0, 0.0, 1.0)], dtype=local.dtype)
    _, slope_u, slope_v = bend_height(bend, corners[:, 0] * scale_u, corners[:, 1] * scale_v)
    tilt = torch.rad2deg(torch.atan(torch.sqrt(slope_u ** 2 + slope_v ** 2)))
    return bend if float(tilt.max()) >= BEND_MIN_DEGREES else zero


def fit_planes(
    points: Tensor, normals: Tensor, *, tolerance: float, max_planes: int = 6, min_share: float = 0.05,
    max_angle_deg: float = 15.0, candidates: int = 256, seed: int = 0,
) -> tuple[Tensor, Tensor]:
    """Planes [K,18] that explain the oriented points [N,3] (with unit normals [N,3]), and the share of
    the points each explains [K] (their sum: the share explained).

    Sequential RANSAC: each round draws ``candidates`` points and takes each one's own plane (its
    position and normal); the candidate with the most inliers (within ``tolerance`` of the plane and
    with a normal within ``max_angle_deg`` of it, either side) wins and is refitted to its inliers
    (least squares), which leave the pool. Rounds stop at ``max_planes`` or when the best plane
    explains less than ``min_share`` of all the points. The rectangle of a plane is the smallest-area one
    holding its inliers (grown by ``tolerance``); its thickness is ``tolerance``; its bend is the quadric
    height of its inliers over it (:func:`fit_bend`; zero for flat glass). Scoring is chunked: a
    round holds [CHUNK, candidates] distances and normal agreements (about 20 MB at the defaults) whatever
    the number of points, and takes O(N candidates) time."""
    points = points.to(torch.float64)
    normals = torch.nn.functional.normalize(normals.to(torch.float64), dim=-1)
    n_all = points.shape[0]
    generator = torch.Generator().manual_seed(seed)
    cos_max = float(torch.cos(torch.deg2rad(torch.tensor(max_angle_deg))))
    remaining = torch.ones(n_all, dtype=torch.bool)
    planes, explained = [], []
    while len(planes) < max_planes:
        pool = torch.nonzero(remaining).flatten()
        if pool.numel() < max(3, int(min_share * n_all)):
            break
        picks = pool[torch.randint(pool.numel(), (min(candidates, pool.numel()),), generator=generator)]
        counts = torch.zeros(picks.numel(), dtype=torch.long)
        offsets = (points[picks] * normals[picks]).sum(-1)  # each candidate plane: n . x = offset
        for start in range(0, pool.numel(), CHUNK):
            chunk = pool[start:start + CHUNK]
            dist = (points[chunk] @ normals[picks].T - offsets).abs()  # [chunk, candidates], no [.., .., 3]
            agree = (normals[chunk] @ normals[picks].T).abs() >= cos_max
            counts += ((dist <= tolerance) & agree).sum(0)
        best = int(counts.argmax())
        if int(counts[best]) < min_share * n_all:
            break
        normal, anchor = normals[picks[best]], points[picks[best]]
        for _ in range(2):  # refit to the inliers, then recollect them
            inliers = pool[(((points[pool] - anchor) @ normal).abs() <= tolerance)
                           & ((normals[pool] @ normal).abs() >= cos_max)]
            if inliers.numel() < 3:
                break
            anchor = points[inliers].mean(0)
            _, _, vh = torch.linalg.svd(points[inliers] - anchor, full_matrices=False)
            normal = vh[2] if float(vh[2] @ normal) >= 0 else -vh[2]
        if inliers.numel() < max(3, min_share * n_all):
            break
        u, v, (lo_u, hi_u), (lo_v, hi_v) = _smallest_rectangle(points[inliers] - anchor, normal)
        centre = anchor + 0.5 * (lo_u + hi_u) * u + 0.5 * (lo_v + hi_v) * v
        extent = torch.tensor([0.5 * (hi_u - lo_u) + tolerance, 0.5 * (hi_v - lo_v) + tolerance, tolerance],
                              dtype=torch.float64)
        bend = fit_bend(points[inliers] - centre, u, v, normal, (float(extent[0]), float(extent[1])))
        planes.append(torch.cat([normal, centre, u, extent, bend]))
        explained.append(inliers.numel() / max(n_all, 1))
        remaining[inliers] = False
    if not planes:
        return empty_planes(), torch.zeros(0)
    return torch.stack(planes).to(torch.float32), torch.tensor(explained, dtype=torch.float32)


def _smallest_rectangle(local: Tensor, normal: Tensor, steps: int = 90):
    """Axes ``u``, ``v`` on the plane and the (low, high) extents along them of the smallest-area
    rectangle holding the in-plane points ``local`` [N,3], over ``steps`` orientations (2 degrees apart)."""
    e1 = torch.linalg.svd(local, full_matrices=False)[2][0]
    e1 = e1 - (e1 @ normal) * normal
    e1 = e1 / e1.norm()
    e2 = torch.linalg.cross(normal, e1)
    xy = torch.stack([local @ e1, local @ e2], -1)  # [N,2]
    angles = torch.arange(steps, dtype=local.dtype) * (torch.pi / 2 / steps)
    axes = torch.stack([torch.cos(angles), torch.sin(angles)], -1)  # [S,2]; the other axis is at +90 degrees
    along = xy @ axes.T  # [N,S]
    across = xy @ torch.stack([-axes[:, 1], axes[:, 0]], -1).T
    area = (along.max(0).values - along.min(0).values) * (across.max(0).values - across.min(0).values)
    best = int(area.argmin())
    u = axes[best, 0] * e1 + axes[best, 1] * e2
    v = torch.linalg.cross(normal, u)
    return (u, v, (float(along[:, best].min()), float(along[:, best].max())),
            (float(across[:, best].min()), float(across[:, best].max())))
