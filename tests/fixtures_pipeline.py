"""Small synthetic scenes for the pipeline tests (no network, no Mitsuba).

:func:`make_corner_scene` ray-casts an inside corner (a floor and two walls, each textured with a
different ``skimage.data`` photograph) from cameras on an arc, so SfM has real texture and parallax,
and the ground-truth cameras are known. A "window" rectangle on one wall is the transparent region
used for the masks.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

SIZE = 2.0  # the corner spans [0, SIZE] on each axis
WINDOW = (0.5, 1.5, 0.6, 1.6)  # on the wall x = 0: y0, y1, z0, z1


@dataclass
class GtView:
    name: str
    K: np.ndarray
    world_to_camera: np.ndarray
    width: int
    height: int


def _textures() -> list[np.ndarray]:
    from skimage import color, data, transform

    out = []
    for img in (data.astronaut(), data.coffee(), data.chelsea()):
        img = img.astype(np.float32) / 255.0
        if img.ndim == 2:
            img = color.gray2rgb(img)
        out.append(transform.resize(img, (256, 256), anti_aliasing=True).astype(np.float32))
    return out


def _look_at(eye: np.ndarray, target: np.ndarray, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    f = target - eye
    f /= np.linalg.norm(f)
    r = np.cross(f, up)
    r /= np.linalg.norm(r)
    d = np.cross(f, r)
    R = np.stack([r, d, f])
    w2c = np.eye(4)
    w2c[:3, :3] = R
    w2c[:3, 3] = -R @ eye
    return w2c


def corner_cameras(n: int, width: int, height: int) -> list[GtView]:
    fx = 0.9 * width
    K = np.array([[fx, 0, width / 2], [0, fx, height / 2], [0, 0, 1.0]])
    target = np.array([0.6, 0.6, 0.6])
    views = []
    for i in range(n):
        a = np.deg2rad(20 + 50 * i / max(n - 1, 1))
        eye = np.array([0.6 + 3.2 * np.cos(a), 0.6 + 3.2 * np.sin(a), 1.6 + 0.3 * np.sin(3 * a)])
        views.append(GtView(f"view_{i:03d}", K, _look_at(eye, target), width, height))
    return views


def render_view(view: GtView, textures: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """(RGB float32 [H, W, 3], window mask bool [H, W]) by ray casting the three planes."""
    import cv2

    h, w = view.height, view.width
    u, v = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)
    pix = np.stack([u, v, np.ones_like(u)], axis=-1).reshape(-1, 3)
    R, t = view.world_to_camera[:3, :3], view.world_to_camera[:3, 3]
    dirs = (pix @ np.linalg.inv(view.K).T) @ R  # world directions (R^T d)
    origin = -R.T @ t
    best = np.full(len(pix), np.inf)
    rgb = np.full((len(pix), 3), 0.2, np.float32)
    window = np.zeros(len(pix), bool)
    # plane axis index, (u axis, v axis) for the texture
    for axis, (ua, va), tex in zip((2, 0, 1), ((0, 1), (1, 2), (0, 2)), textures, strict=True):
        with np.errstate(divide="ignore", invalid="ignore"):
            s = -origin[axis] / dirs[:, axis]
            p = origin + s[:, None] * dirs
        ok = (s > 0) & (s < best) & np.all((p >= -1e-9) & (p <= SIZE + 1e-9), axis=1)
        tu = np.clip(p[:, ua] / SIZE * 255, 0, 255).astype(np.float32)
        tv = np.clip(p[:, va] / SIZE * 255, 0, 255).astype(np.float32)
        sample = cv2.remap(tex, tu.reshape(-1, 1), tv.reshape(-1, 1), cv2.INTER_LINEAR).reshape(-1, 3)
        rgb[ok] = sample[ok]
        best[ok] = s[ok]
        win = (p[:, 1] > WINDOW[0]) & (p[:, 1] < WINDOW[1]) & (p[:, 2] > WINDOW[2]) & (p[:, 2] < WINDOW[3])
        window = np.where(ok, win if axis == 0 else False, window)
    return rgb.reshape(h, w, 3), window.reshape(h, w)


def surface_points(n: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    pts = rng.uniform(0, SIZE, size=(n, 3))
    axis = rng.integers(0, 3, size=n)
    pts[np.arange(n), axis] = 0.0
    return pts, rng.integers(0, 255, size=(n, 3)).astype(np.uint8)


def make_corner_scene(
    scene_dir: str | Path,
    n_views: int = 12,
    width: int = 200,
    height: int = 150,
    with_model: bool = False,
    with_masks: bool = False,
    ext: str = ".png",
) -> list[GtView]:
    """Write ``<scene_dir>/images`` (and optionally ``sparse/0`` with the true cameras and
    ``transparent_masks``); returns the ground-truth views (names with extension)."""
    import cv2

    from rtsplat.io.images import write_mask, write_png

    scene_dir = Path(scene_dir)
    (scene_dir / "images").mkdir(parents=True, exist_ok=True)
    textures = _textures()
    views = corner_cameras(n_views, width, height)
    for v in views:
        img, win = render_view(v, textures)
        v.name = v.name + ext
        if ext == ".png":
            write_png(scene_dir / "images" / v.name, img)
        else:
            cv2.imwrite(str(scene_dir / "images" / v.name), (img[..., ::-1] * 255).round().astype(np.uint8))
        if with_masks:
            (scene_dir / "transparent_masks").mkdir(exist_ok=True)
            write_mask(scene_dir / "transparent_masks" / f"{Path(v.name).stem}.png", win)
    if with_model:
        from rtsplat.io.colmap import write_model

        xyz, rgb = surface_points(500)
        write_model(
            scene_dir / "sparse" / "0", [(v.name, v.K, v.world_to_camera, v.width, v.height) for v in views], xyz, rgb
        )
    return views
