"""A tiny see-through scene with known masks for the mask propagation tests (numpy ray casting, no Mitsuba).

A tinted glass ellipsoid stands in a striped environment; cameras circle it at two heights. The true mask
of a view is where its rays hit the ellipsoid; the image shows the environment through a blue tint there.
"""

from __future__ import annotations

import numpy as np

from rtsplat.io.colmap import ColmapModel, ColmapView

RADII = np.array([0.5, 0.35, 0.7])  # ellipsoid semi-axes at the origin


def look_at(eye: np.ndarray, target: np.ndarray) -> np.ndarray:
    f = target - eye
    f /= np.linalg.norm(f)
    r = np.cross(f, (0.0, 0.0, 1.0))
    r /= np.linalg.norm(r)
    R = np.stack([r, np.cross(f, r), f])
    w2c = np.eye(4)
    w2c[:3, :3] = R
    w2c[:3, 3] = -R @ eye
    return w2c


def ring_views(n: int, width: int = 96, height: int = 72, distance: float = 3.0) -> list[ColmapView]:
    fx = 0.9 * width
    K = np.array([[fx, 0, width / 2], [0, fx, height / 2], [0, 0, 1.0]])
    views = []
    for i in range(n):
        a = 2 * np.pi * i / n
        z = 0.6 if i % 2 else -0.3
        eye = np.array([distance * np.cos(a), distance * np.sin(a), z])
        target = np.array([0.05 * np.sin(3 * a), 0.05 * np.cos(2 * a), 0.0])
        views.append(ColmapView(f"view_{i:03d}.png", width, height, "PINHOLE",
                                np.array([fx, fx, width / 2, height / 2]), K, look_at(eye, target)))
    return views


def render(view: ColmapView) -> tuple[np.ndarray, np.ndarray]:
    """(image float [H, W, 3], true mask bool [H, W]) of the view."""
    h, w = view.height, view.width
    u, v = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)
    K, R = view.K, view.world_to_camera[:3, :3]
    d_cam = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1)
    d = d_cam @ R  # world directions (R^T d_cam)
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    o = view.center
    # ray / ellipsoid: |(o + t d) / radii|^2 = 1
    od, dd = o / RADII, d / RADII
    a = (dd * dd).sum(-1)
    b = 2 * (od * dd).sum(-1)
    c = (od * od).sum() - 1
    mask = (b * b - 4 * a * c > 0) & (b < 0)  # hit in front of the camera (which is outside the ellipsoid)
    theta = np.arctan2(d[..., 1], d[..., 0])
    stripes = 0.5 + 0.5 * np.sign(np.sin(5 * theta)) * np.sign(np.sin(8 * d[..., 2]))
    env = np.stack([0.3 + 0.6 * stripes, 0.5 + 0.2 * (d[..., 2] > 0) + 0.2 * np.cos(theta), 0.2 + 0.5 * (1 - stripes)],
                   -1)
    image = np.where(mask[..., None], env * np.array([0.55, 0.75, 1.0]) + np.array([0.0, 0.05, 0.25]), env)
    return np.clip(image, 0, 1).astype(np.float32), mask


def ring_model(n: int, width: int = 96, height: int = 72) -> ColmapModel:
    """The views and SfM-like points on the environment around the object."""
    rng = np.random.default_rng(0)
    points = rng.normal(size=(400, 3))
    points = 4.0 * points / np.linalg.norm(points, axis=1, keepdims=True)
    points[:, 2] *= 0.3
    return ColmapModel(ring_views(n, width, height), points)
