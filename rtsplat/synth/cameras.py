"""Ground-truth camera paths and the conversion of :class:`rtsplat.camera.Camera` to Mitsuba.

rtsplat cameras use OpenCV axes (x right, y down, z forward) and COLMAP pixel centres
(i + 0.5, j + 0.5). Mitsuba's ``perspective`` sensor looks along its local +z with +y up and +x
to the *left*, so its camera-to-world matrix is ours with the x and y axes negated. Mitsuba's
film maps the sensor's field of view onto the image corners exactly like COLMAP (pixel (0, 0) is
the top-left corner), so a centred pinhole with square pixels converts without offsets; the test
suite checks this by projecting a bright marker.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import ClassVar

import numpy as np
import torch

from rtsplat.camera import Camera, camera_from_fov
from rtsplat.camera import pixel_rays as camera_pixel_rays


@dataclass(frozen=True)
class OrbitPath:
    """An orbit around ``target`` with a sinusoidal height variation.

    View ``i`` of ``n`` has azimuth ``azimuth_start + i * azimuth_span / n`` (degrees; the last
    view does not repeat the first on a full 360-degree orbit) and camera height
    ``height_mid + height_amplitude * sin(2 pi * height_cycles * i / n)``.
    """

    TYPE: ClassVar[str] = "orbit"  # scene.json's camera_path type
    target: tuple[float, float, float] = (0.0, 0.0, 0.5)
    radius: float = 4.0
    height_mid: float = 2.0
    height_amplitude: float = 0.6
    height_cycles: float = 2.0
    azimuth_start: float = 0.0
    azimuth_span: float = 360.0
    fov_x_deg: float = 55.0

    def eyes(self, n: int) -> np.ndarray:
        """Camera centres [n, 3] (world, z up)."""
        i = np.arange(n, dtype=np.float64)
        full = abs(self.azimuth_span) >= 360.0
        step = self.azimuth_span / (n if full else max(n - 1, 1))
        az = np.radians(self.azimuth_start + i * step)
        z = self.height_mid + self.height_amplitude * np.sin(2 * np.pi * self.height_cycles * i / n)
        tx, ty, _ = self.target
        return np.stack([tx + self.radius * np.cos(az), ty + self.radius * np.sin(az), z], axis=1)

    def cameras(self, n: int, width: int, height: int) -> list[Camera]:
        """The ``n`` ground-truth cameras (float64), all with the same centred intrinsics."""
        return [
            camera_from_fov(
                tuple(eye),
                self.target,
                width=width,
                height=height,
                fov_x_deg=self.fov_x_deg,
                dtype=torch.float64,
            )
            for eye in self.eyes(n)
        ]


@dataclass(frozen=True)
class WalkPath:
    """A forward-facing walk past: camera centres evenly spaced on the segment ``start`` - ``end`` with
    a sinusoidal height variation, view ``i`` looking at the point at the same fraction of the segment
    ``look_start`` - ``look_end`` (parallel views when the two segments are parallel and as long, a slow
    turn when the looked-at segment is shorter).

    View ``i`` of ``n`` is at fraction ``i / (n - 1)``; its height is the segment's plus
    ``height_amplitude * sin(2 pi * height_cycles * i / n)``.
    """

    TYPE: ClassVar[str] = "walk"  # scene.json's camera_path type
    start: tuple[float, float, float] = (-1.0, -3.0, 1.2)
    end: tuple[float, float, float] = (1.0, -3.0, 1.2)
    look_start: tuple[float, float, float] = (-0.5, 0.0, 1.0)
    look_end: tuple[float, float, float] = (0.5, 0.0, 1.0)
    height_amplitude: float = 0.1
    height_cycles: float = 2.0
    fov_x_deg: float = 55.0

    def _fractions(self, n: int) -> np.ndarray:
        return np.arange(n, dtype=np.float64) / max(n - 1, 1)

    def eyes(self, n: int) -> np.ndarray:
        """Camera centres [n, 3] (world, z up)."""
        f = self._fractions(n)[:, None]
        eyes = (1 - f) * np.asarray(self.start) + f * np.asarray(self.end)
        eyes[:, 2] += self.height_amplitude * np.sin(2 * np.pi * self.height_cycles * np.arange(n) / n)
        return eyes

    def targets(self, n: int) -> np.ndarray:
        """The looked-at points [n, 3]."""
        f = self._fractions(n)[:, None]
        return (1 - f) * np.asarray(self.look_start) + f * np.asarray(self.look_end)

    def cameras(self, n: int, width: int, height: int) -> list[Camera]:
        """The ``n`` ground-truth cameras (float64), all with the same centred intrinsics."""
        return [
            camera_from_fov(tuple(eye), tuple(target), width=width, height=height, fov_x_deg=self.fov_x_deg,
                            dtype=torch.float64)
            for eye, target in zip(self.eyes(n), self.targets(n), strict=True)
        ]


CameraPath = OrbitPath | WalkPath


def camera_to_world_np(camera: Camera) -> np.ndarray:
    """4x4 camera-to-world matrix (OpenCV axes) as float64 numpy."""
    return np.linalg.inv(camera.world_to_camera.detach().cpu().double().numpy())


SAMPLER = "multijitter"


def effective_spp(spp: int) -> int:
    """The sample count Mitsuba's ``multijitter`` sampler uses for ``spp``: a grid of
    floor(sqrt(spp)) x ceil(spp / floor(sqrt(spp))) strata (36 -> 36, 32 -> 35)."""
    nx = max(int(math.isqrt(int(spp))), 1)
    return nx * -(-int(spp) // nx)


def mitsuba_sensor(camera: Camera, spp: int, seed: int = 0) -> dict:
    """A Mitsuba ``perspective`` sensor dict that sees exactly what ``camera`` sees.

    The sampler is ``multijitter`` (stratified): at a glass surface the choice between reflection
    and transmission is then stratified over a pixel's samples, which cuts the noise of see-through
    pixels about threefold against ``independent`` at the same cost.

    Only centred principal points and square pixels are supported (what :class:`OrbitPath`
    produces); anything else raises ``ValueError``.
    """
    import mitsuba as mi

    K = camera.K.detach().cpu().double().numpy()
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    w, h = int(camera.width), int(camera.height)
    if abs(fx - fy) > 1e-6 * fx or abs(cx - w / 2) > 1e-6 or abs(cy - h / 2) > 1e-6 or K[0, 1] != 0:
        raise ValueError("mitsuba_sensor supports centred principal points and square pixels only")
    flip = np.diag([-1.0, -1.0, 1.0, 1.0])  # OpenCV camera axes -> Mitsuba camera axes
    to_world = camera_to_world_np(camera) @ flip
    return {
        "type": "perspective",
        "fov_axis": "x",
        "fov": math.degrees(2.0 * math.atan(0.5 * w / fx)),
        "near_clip": 0.01,
        "far_clip": 1000.0,
        "to_world": mi.ScalarTransform4f(to_world.tolist()),
        "sampler": {"type": SAMPLER, "sample_count": effective_spp(spp), "seed": int(seed)},
        "film": {
            "type": "hdrfilm",
            "width": w,
            "height": h,
            "rfilter": {"type": "box"},
            "pixel_format": "rgb",
        },
    }


def pixel_rays(camera: Camera, u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """:func:`rtsplat.camera.pixel_rays` in float64 numpy, for Mitsuba: (origin [3], unit directions [N, 3])."""
    origin, directions = camera_pixel_rays(camera.to(device="cpu", dtype=torch.float64), u, v)
    return origin.detach().numpy(), directions.detach().numpy()
