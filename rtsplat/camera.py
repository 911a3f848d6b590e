"""The one camera convention of rtsplat.

A :class:`Camera` is a pinhole camera:

* ``K``: 3x3 intrinsics ``[[fx, 0, cx], [0, fy, cy], [0, 0, 1]]`` in pixels;
* ``world_to_camera``: 4x4 rigid transform, OpenCV axes (x right, y down, z forward);
* ``width``, ``height``: image size in pixels.

Pixel coordinates follow COLMAP (and gsplat): the top-left *corner* of the image is (0, 0), so the
centre of pixel (column i, row j) is at (i + 0.5, j + 0.5). This is :data:`PIXEL_CENTER_OFFSET`.
COLMAP models and their ``cam_from_world`` poses use exactly this convention, so conversions are
plain copies. (The original 2DGS CUDA code samples pixels at integer coordinates; we do not.)
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

PIXEL_CENTER_OFFSET = 0.5


@dataclass(frozen=True)
class Camera:
    K: Tensor  # [3, 3]
    world_to_camera: Tensor  # [4, 4]
    width: int
    height: int

    def __post_init__(self) -> None:
        if tuple(self.K.shape) != (3, 3):
            raise ValueError(f"Camera.K must be 3x3, got shape {tuple(self.K.shape)}")
        if tuple(self.world_to_camera.shape) != (4, 4):
            raise ValueError(
                f"Camera.world_to_camera must be 4x4, got shape {tuple(self.world_to_camera.shape)}"
            )
        if int(self.width) <= 0 or int(self.height) <= 0:
            raise ValueError(f"Camera size must be positive, got {self.width}x{self.height}")
        if self.K.device != self.world_to_camera.device:
            raise ValueError("Camera.K and Camera.world_to_camera must be on the same device")

    @property
    def device(self) -> torch.device:
        return self.K.device

    @property
    def rotation(self) -> Tensor:
        """World-to-camera rotation [3, 3]."""
        return self.world_to_camera[:3, :3]

    @property
    def translation(self) -> Tensor:
        """World-to-camera translation [3]."""
        return self.world_to_camera[:3, 3]

    @property
    def center(self) -> Tensor:
        """Camera centre in world coordinates [3]."""
        return -self.rotation.T @ self.translation

    def to(self, device=None, dtype=None) -> Camera:
        return Camera(
            K=self.K.to(device=device, dtype=dtype),
            world_to_camera=self.world_to_camera.to(device=device, dtype=dtype),
            width=int(self.width),
            height=int(self.height),
        )

    def scaled(self, factor: float) -> Camera:
        """The camera of the image area-downsampled by ``factor`` (e.g. 2 halves the size; see
        :func:`rtsplat.io.images.area_downsample`, which crops the right/bottom edge to a multiple of
        the factor, so the size is rounded down).

        With the corner-at-(0,0) pixel convention the scaling of K is exact: fx, fy, cx, cy / factor.
        """
        if factor == 1:
            return self
        K = self.K.clone()
        K[:2] = K[:2] / factor
        return Camera(K, self.world_to_camera, int(self.width // factor), int(self.height // factor))

    def corrected(self, correction: Tensor) -> Camera:
        """This camera moved by ``correction`` [6] (rotation vector, translation) expressed in its own
        frame: ``world_to_camera' = rigid_motion(correction) @ world_to_camera``. Differentiable in
        ``correction``; a zero correction gives this camera's pose exactly."""
        motion = rigid_motion(correction.to(self.world_to_camera))
        return Camera(self.K, motion @ self.world_to_camera, int(self.width), int(self.height))

    def project(self, points: Tensor) -> tuple[Tensor, Tensor]:
        """World points [N, 3] -> (pixel coordinates [N, 2], camera depth z [N])."""
        cam = points @ self.rotation.T + self.translation
        uvw = cam @ self.K.T
        z = cam[:, 2]
        return uvw[:, :2] / z[:, None], z


def rigid_motion(correction: Tensor) -> Tensor:
    """4x4 rigid transform of a [6] vector: rotation ``exp([w]x)`` of the rotation vector ``w =
    correction[:3]`` (radians) and translation ``correction[3:]``. The matrix exponential is finite,
    with finite gradients, at and near the zero rotation."""
    w = correction[:3]
    zero = w.new_zeros(())
    skew = torch.stack([zero, -w[2], w[1], w[2], zero, -w[0], -w[1], w[0], zero]).reshape(3, 3)
    top = torch.cat([torch.linalg.matrix_exp(skew), correction[3:, None]], dim=1)
    bottom = correction.new_tensor([[0.0, 0.0, 0.0, 1.0]])
    return torch.cat([top, bottom], dim=0)


def pixel_rays(camera: Camera, u: Tensor, v: Tensor) -> tuple[Tensor, Tensor]:
    """World-space rays through continuous pixel positions ``u``, ``v`` (any equal shapes; the image's
    top-left corner is (0, 0), pixel centres are at + :data:`PIXEL_CENTER_OFFSET`).

    Returns (the camera centre [3], unit directions [..., 3]) in the camera's dtype.
    """
    K, R = camera.K, camera.rotation
    u, v = torch.as_tensor(u, dtype=K.dtype, device=K.device), torch.as_tensor(v, dtype=K.dtype, device=K.device)
    d_cam = torch.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], torch.ones_like(u)], dim=-1)
    d = d_cam @ R  # R^T applied to row vectors
    return camera.center, d / torch.linalg.vector_norm(d, dim=-1, keepdim=True)


def intrinsics(fx: float, fy: float, cx: float, cy: float, *, dtype=torch.float32, device=None) -> Tensor:
    return torch.tensor([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]], dtype=dtype, device=device)


def look_at(eye, target, up=(0.0, 0.0, 1.0), *, dtype=torch.float32, device=None) -> Tensor:
    """World-to-camera 4x4 (OpenCV axes) of a camera at ``eye`` looking at ``target``.

    ``up`` is the world direction that should appear upwards in the image (image y points down).
    """
    eye_t = torch.as_tensor(eye, dtype=torch.float64)
    forward = torch.as_tensor(target, dtype=torch.float64) - eye_t
    forward = forward / forward.norm()
    up_t = torch.as_tensor(up, dtype=torch.float64)
    right = torch.linalg.cross(forward, up_t)
    if right.norm() < 1e-9:
        raise ValueError("look_at: 'up' is parallel to the viewing direction")
    right = right / right.norm()
    down = torch.linalg.cross(forward, right)
    R = torch.stack([right, down, forward])  # rows: camera axes in world coordinates
    w2c = torch.eye(4, dtype=torch.float64)
    w2c[:3, :3] = R
    w2c[:3, 3] = -R @ eye_t
    return w2c.to(dtype=dtype, device=device)


def camera_from_fov(
    eye, target, *, width: int, height: int, fov_x_deg: float = 60.0, up=(0.0, 0.0, 1.0),
    dtype=torch.float32, device=None,
) -> Camera:
    """Convenience: a centred pinhole camera with horizontal field of view ``fov_x_deg``."""
    fx = 0.5 * width / math.tan(math.radians(fov_x_deg) / 2)
    K = intrinsics(fx, fx, width / 2, height / 2, dtype=dtype, device=device)
    return Camera(K, look_at(eye, target, up, dtype=dtype, device=device), int(width), int(height))


def camera_from_colmap(
    fx: float, fy: float, cx: float, cy: float, width: int, height: int, cam_from_world_3x4, *,
    dtype=torch.float32, device=None,
) -> Camera:
    """Build a camera from COLMAP PINHOLE parameters and a ``cam_from_world`` 3x4 matrix.

    COLMAP uses the same axes and pixel convention, so this is a copy (no flips, no offsets).
    """
    w2c = torch.eye(4, dtype=torch.float64)
    w2c[:3, :4] = torch.as_tensor(cam_from_world_3x4, dtype=torch.float64).reshape(3, 4)
    return Camera(
        intrinsics(fx, fy, cx, cy, dtype=dtype, device=device), w2c.to(dtype=dtype, device=device),
        int(width), int(height),
    )
