"""Camera paths for videos, derived from the training cameras.

Every function takes and returns float64 tensors: world-to-camera poses ``[N, 4, 4]`` in the convention
of :mod:`rtsplat.camera` (OpenCV axes), points ``[3]``, intrinsics ``[3, 3]``.

* :func:`orbit_path`: a full circle around ``center`` (the region of interest) at the cameras' mean
  distance from it and their mean elevation above the plane normal to the cameras' mean up direction,
  starting at the azimuth of the first camera and always looking at ``center``;
* :func:`spiral_path`: around the mean camera position, in the plane of its view, with radii from the
  spread of the camera positions (their 90th percentile along each of its axes) and a slower motion
  along its viewing axis, looking at ``center``: for forward-facing captures;
* :func:`interpolated_path`: through the given poses in their order (the capture order: the caller
  sorts them by name), positions on a Catmull-Rom spline and rotations by spherical linear
  interpolation of their quaternions, ``frames`` evenly spread over the parameter, so that with
  ``frames = m (N - 1) + 1`` every ``m``-th frame is one of the poses exactly.

:func:`path_intrinsics` gives the pinhole matrix of the training cameras for another image size.
Bad settings (fewer than two frames, too few cameras, cameras at the centre) are a
:class:`~rtsplat.errors.PipelineError`.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from rtsplat.camera import look_at
from rtsplat.errors import PipelineError

PATHS = ("orbit", "spiral", "interpolate")
SPIRAL_ROTATIONS = 2  # turns of the spiral over the video
SPIRAL_PERCENTILE = 0.9  # radii of the spiral: this quantile of |camera position - mean| along each axis


def _poses(w2c) -> Tensor:
    poses = torch.as_tensor(w2c, dtype=torch.float64)
    if poses.ndim != 3 or tuple(poses.shape[1:]) != (4, 4):
        raise ValueError(f"camera poses must be [N, 4, 4], got {tuple(poses.shape)}")
    return poses


def camera_centers(w2c) -> Tensor:
    """World positions [N, 3] of world-to-camera poses [N, 4, 4]."""
    poses = _poses(w2c)
    rotation, translation = poses[:, :3, :3], poses[:, :3, 3]
    return -(rotation.transpose(1, 2) @ translation[:, :, None])[:, :, 0]


def mean_up(w2c) -> Tensor:
    """The unit world direction [3] that the cameras show upwards on average (image y points down)."""
    up = -_poses(w2c)[:, 1, :3].sum(0)
    norm = up.norm()
    if norm < 1e-9:
        raise PipelineError("the training cameras have no common up direction (their image-up axes cancel out)",
                            fix="use --path interpolate, which follows the cameras' own orientations")
    return up / norm


def _check_frames(frames: int) -> int:
    if isinstance(frames, bool) or not isinstance(frames, int) or frames < 2:
        raise PipelineError(f"a camera path needs at least 2 frames, got {frames!r}", fix="pass --frames 2 or more")
    return frames


def _check_cameras(poses: Tensor, needed: int, path: str) -> None:
    if len(poses) < needed:
        raise PipelineError(f"the {path} path needs at least {needed} training camera(s), the run has {len(poses)}",
                            fix="use a prepared scene with more training views, or another --path")


def _basis(up: Tensor) -> tuple[Tensor, Tensor]:
    """Two unit vectors orthogonal to ``up`` and to each other."""
    helper = torch.tensor([1.0, 0.0, 0.0], dtype=up.dtype) if abs(float(up[0])) < 0.9 else \
        torch.tensor([0.0, 1.0, 0.0], dtype=up.dtype)
    a = torch.linalg.cross(up, helper)
    a = a / a.norm()
    return a, torch.linalg.cross(up, a)


def _looking_at(positions: Tensor, center: Tensor, up: Tensor) -> Tensor:
    return torch.stack([look_at(p, center, up, dtype=torch.float64) for p in positions])


def orbit_geometry(w2c, center) -> dict[str, float]:
    """The orbit's ``distance`` (mean distance of the camera centres to ``center``) and ``elevation``
    (mean angle in radians of their offsets above the plane normal to :func:`mean_up`)."""
    poses = _poses(w2c)
    center = torch.as_tensor(center, dtype=torch.float64)
    offsets = camera_centers(poses) - center
    distances = offsets.norm(dim=1)
    if float(distances.min()) < 1e-9:
        raise PipelineError("a training camera sits at the centre of the region of interest, so no orbit around it "
                            "can be derived", fix="use --path interpolate or --path spiral")
    up = mean_up(poses)
    elevation = torch.asin(((offsets @ up) / distances).clamp(-1, 1))
    return {"distance": float(distances.mean()), "elevation": float(elevation.mean())}


def orbit_path(w2c, center, frames: int) -> Tensor:
    """World-to-camera poses [frames, 4, 4] on a circle around ``center`` (see the module docstring); the
    last frame stops one step short of the first, so a looping video does not repeat it."""
    poses, frames = _poses(w2c), _check_frames(frames)
    _check_cameras(poses, 1, "orbit")
    center = torch.as_tensor(center, dtype=torch.float64)
    geometry = orbit_geometry(poses, center)
    up = mean_up(poses)
    if abs(math.cos(geometry["elevation"])) < 1e-3:
        raise PipelineError("the training cameras look straight down or up on average, so an orbit would look "
                            "along its own up axis", fix="use --path interpolate or --path spiral")
    a, b = _basis(up)
    first = camera_centers(poses[:1])[0] - center
    start = math.atan2(float(first @ b), float(first @ a))
    angles = start + 2 * math.pi * torch.arange(frames, dtype=torch.float64) / frames
    cos_e, sin_e = math.cos(geometry["elevation"]), math.sin(geometry["elevation"])
    directions = cos_e * (torch.cos(angles)[:, None] * a + torch.sin(angles)[:, None] * b) + sin_e * up
    return _looking_at(center + geometry["distance"] * directions, center, up)


def spiral_path(w2c, center, frames: int, rotations: int = SPIRAL_ROTATIONS) -> Tensor:
    """World-to-camera poses [frames, 4, 4] on a spiral around the mean camera position (module docstring)."""
    poses, frames = _poses(w2c), _check_frames(frames)
    _check_cameras(poses, 2, "spiral")
    center = torch.as_tensor(center, dtype=torch.float64)
    up = mean_up(poses)
    positions = camera_centers(poses)
    mean = positions.mean(0)
    if float((mean - center).norm()) < 1e-9:
        raise PipelineError("the training cameras' mean position is the centre of the region of interest, so the "
                            "spiral has no viewing direction", fix="use --path orbit or --path interpolate")
    try:
        axes = look_at(mean, center, up, dtype=torch.float64)[:3, :3]  # rows: right, down, forward
    except ValueError:
        raise PipelineError("the cameras look along their mean up direction, so the spiral has no orientation",
                            fix="use --path interpolate") from None
    radii = torch.quantile(((positions - mean) @ axes.T).abs(), SPIRAL_PERCENTILE, dim=0)
    t = 2 * math.pi * rotations * torch.arange(frames, dtype=torch.float64) / frames
    local = torch.stack([radii[0] * torch.cos(t), radii[1] * torch.sin(t), radii[2] * torch.sin(t / rotations)], 1)
    return _looking_at(mean + local @ axes, center, up)


def _quaternions(rotations: Tensor) -> Tensor:
    """Unit quaternions [N, 4] (w, x, y, z) of rotation matrices [N, 3, 3]."""
    out = []
    for R in rotations:
        trace = float(R[0, 0] + R[1, 1] + R[2, 2])
        if trace > 0:
            s = 2 * math.sqrt(trace + 1)
            q = [s / 4, (R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s]
        else:
            i = int(torch.argmax(torch.diagonal(R)))
            j, k = (i + 1) % 3, (i + 2) % 3
            s = 2 * math.sqrt(max(float(1 + R[i, i] - R[j, j] - R[k, k]), 1e-12))
            q = [0.0] * 4
            q[0] = (R[k, j] - R[j, k]) / s
            q[1 + i] = s / 4
            q[1 + j] = (R[j, i] + R[i, j]) / s
            q[1 + k] = (R[k, i] + R[i, k]) / s
        q = torch.tensor([float(v) for v in q], dtype=torch.float64)
        out.append(q / q.norm())
    return torch.stack(out)


def _rotation(q: Tensor) -> Tensor:
    w, x, y, z = q
    return torch.stack([
        torch.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)]),
        torch.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)]),
        torch.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]),
    ])


def slerp(q0: Tensor, q1: Tensor, t: float) -> Tensor:
    """Spherical linear interpolation of unit quaternions (the shorter arc)."""
    dot = float(q0 @ q1)
    if dot < 0:
        q1, dot = -q1, -dot
    if dot > 0.9995:  # nearly the same rotation: linear, renormalised
        q = q0 + t * (q1 - q0)
        return q / q.norm()
    theta = math.acos(dot)
    return (math.sin((1 - t) * theta) * q0 + math.sin(t * theta) * q1) / math.sin(theta)


def catmull_rom(p0: Tensor, p1: Tensor, p2: Tensor, p3: Tensor, t: float) -> Tensor:
    """The uniform Catmull-Rom spline between ``p1`` (t = 0) and ``p2`` (t = 1)."""
    return 0.5 * (2 * p1 + (p2 - p0) * t + (2 * p0 - 5 * p1 + 4 * p2 - p3) * t * t
                  + (3 * p1 - p0 - 3 * p2 + p3) * t * t * t)


def interpolated_path(w2c, frames: int) -> Tensor:
    """World-to-camera poses [frames, 4, 4] through ``w2c`` in their order (module docstring): the first
    frame is the first pose, the last frame the last pose."""
    poses, frames = _poses(w2c), _check_frames(frames)
    _check_cameras(poses, 2, "interpolate")
    positions = camera_centers(poses)
    # ends extended by reflection, so the spline's end tangents follow the first and last segments
    padded = torch.cat([2 * positions[:1] - positions[1:2], positions, 2 * positions[-1:] - positions[-2:-1]])
    cam_to_world = poses[:, :3, :3].transpose(1, 2)
    quats = _quaternions(cam_to_world)
    for i in range(1, len(quats)):  # one hemisphere, so consecutive slerps take the shorter arc
        if float(quats[i] @ quats[i - 1]) < 0:
            quats[i] = -quats[i]
    segments = len(poses) - 1
    out = []
    for k in range(frames):
        u = segments * k / (frames - 1)
        i = min(int(math.floor(u)), segments - 1)
        t = u - i
        position = catmull_rom(padded[i], padded[i + 1], padded[i + 2], padded[i + 3], t)
        rotation = _rotation(slerp(quats[i], quats[i + 1], t)).T  # world-to-camera
        pose = torch.eye(4, dtype=torch.float64)
        pose[:3, :3] = rotation
        pose[:3, 3] = -rotation @ position
        out.append(pose)
    return torch.stack(out)


def camera_path(path: str, w2c, center, frames: int) -> Tensor:
    """The poses of the path named ``path`` (one of :data:`PATHS`)."""
    if path == "orbit":
        return orbit_path(w2c, center, frames)
    if path == "spiral":
        return spiral_path(w2c, center, frames)
    if path == "interpolate":
        return interpolated_path(w2c, frames)
    raise PipelineError(f"unknown camera path {path!r}", fix=f"use one of {', '.join(PATHS)}")


def even_size(width: int, height: int) -> tuple[int, int]:
    """The size rounded down to even numbers (H.264 in yuv420p halves both for the colour planes)."""
    return int(width) - int(width) % 2, int(height) - int(height) % 2


def path_intrinsics(Ks, widths, heights, width: int | None = None) -> tuple[Tensor, int, int]:
    """The training cameras' pinhole matrix for frames ``width`` pixels wide (None: the first camera's
    width) and the matching height, both rounded down to even numbers: the median over the cameras of
    fx, fy, cx, cy in units of their image size, scaled to the frame size. Returns (K [3, 3], W, H)."""
    Ks = torch.stack([torch.as_tensor(K, dtype=torch.float64).reshape(3, 3) for K in Ks]) if len(Ks) else \
        torch.zeros(0, 3, 3, dtype=torch.float64)
    sizes = torch.as_tensor([[w, h] for w, h in zip(widths, heights, strict=True)], dtype=torch.float64)
    if len(Ks) == 0 or len(Ks) != len(sizes):
        raise PipelineError("no training cameras to take the video's intrinsics from",
                            fix="use a prepared scene with training views")
    base_w, base_h = float(sizes[0, 0]), float(sizes[0, 1])
    scale_w = base_w if width is None else float(width)
    scale_h = scale_w * base_h / base_w
    out_w, out_h = even_size(round(scale_w), round(scale_h))  # rounding down crops the right/bottom edge
    if out_w < 2 or out_h < 2:
        raise PipelineError(f"video frames of {out_w}x{out_h} pixels are too small", fix="pass a larger --width")
    normalised = torch.stack([Ks[:, 0, 0] / sizes[:, 0], Ks[:, 1, 1] / sizes[:, 1], Ks[:, 0, 2] / sizes[:, 0],
                              Ks[:, 1, 2] / sizes[:, 1]], 1).median(0).values
    K = torch.tensor([[normalised[0] * scale_w, 0.0, normalised[2] * scale_w],
                      [0.0, normalised[1] * scale_h, normalised[3] * scale_h], [0.0, 0.0, 1.0]], dtype=torch.float64)
    return K, out_w, out_h
