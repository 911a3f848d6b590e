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
  rotations) and rasterized from the real camera (``RTModel._near_reflection``): every pixel then sees,
  along its own ray, the scene that the ray reflected in the plane sees;
* each pixel takes the near reflection of the first plane rectangle its ray hits
  (:func:`plane_assignment`), with the volume alpha of that render as its coverage. What the reflected
  ray sees past the model's surfels (sky, far scenery) stays the environment lookup's:
  ``L = C_near + (1 - A_near) L_env`` (:class:`rtsplat.model.specular.SpecularNetwork`).

A plane row holds ``normal (3), centre (3), u axis (3), half extents along u and v (2), thickness (1)``
(``v = n x u``; surfels within the thickness of the plane are the glass and are not reflected).
"""

from __future__ import annotations

import torch
from torch import Tensor

from rtsplat.camera import Camera

PLANE_COLUMNS = 12
MIN_RAY_COSINE = 1e-4  # rays this close to parallel with a plane never hit it (no grazing blow-up)
CHUNK = 8192  # points scored against every candidate plane at once in fit_planes


def empty_planes(dtype=torch.float32, device=None) -> Tensor:
    return torch.zeros(0, PLANE_COLUMNS, dtype=dtype, device=device)


def plane_parts(planes: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor, Tensor]:
    """normal [K,3], centre [K,3], u [K,3], v [K,3], half extents [K,2] and thickness [K] of plane rows [K,12]."""
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
    """Plane rows [K,12] turned about their centres by the rotation vectors ``rotation`` [K,3] (normal and
    rectangle together) and then moved by ``shift`` [K] along their turned normals; extents and thickness
    stay. Differentiable in ``rotation`` and ``shift`` (the trainer refines the fitted planes this way)."""
    n, c, u, _, half, thickness = plane_parts(planes)
    n = rotate_vectors(n, rotation)
    u = rotate_vectors(u, rotation)
    c = c + shift[:, None] * n
    return torch.cat([n, c, u, half, thickness[:, None]], -1)


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


def fit_planes(
    points: Tensor, normals: Tensor, *, tolerance: float, max_planes: int = 6, min_share: float = 0.05,
    max_angle_deg: float = 15.0, candidates: int = 256, seed: int = 0,
) -> tuple[Tensor, Tensor]:
    """Planes [K,12] that explain the oriented points [N,3] (with unit normals [N,3]), and the share of
    the points each explains [K] (their sum: the share explained).

    Sequential RANSAC: each round draws ``candidates`` points and takes each one's own plane (its
    position and normal); the candidate with the most inliers (within ``tolerance`` of the plane and
    with a normal within ``max_angle_deg`` of it, either side) wins and is refitted to its inliers
    (least squares), which leave the pool. Rounds stop at ``max_planes`` or when the best plane
    explains less than ``min_share`` of all the points. The rectangle of a plane is the smallest-area one
    holding its inliers (grown by ``tolerance``); its thickness is ``tolerance``. Scoring is chunked: a
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
        planes.append(torch.cat([normal, centre, u, extent]))
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
