"""Photographic textures and the environment map of the synthetic scenes.

All textures are real photographs shipped inside scikit-image (no download), so that the
renders have the kind of texture SfM needs. Images are returned as float32 *linear* RGB arrays
(sRGB decoded), which is what Mitsuba's ``bitmap`` texture expects for float data.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

# scikit-image data images that are bundled with the package (no network needed), colour ones.
# name -> file inside skimage.data.data_dir
_PHOTO_FILES: dict[str, str] = {
    "astronaut": "astronaut.png",
    "coffee": "coffee.png",
    "chelsea": "chelsea.png",
    "rocket": "rocket.jpg",
    "motorcycle": "motorcycle_left.png",
    "ihc": "ihc.png",
    "retina": "retina.jpg",
    "hubble": "hubble_deep_field.jpg",
    "gravel": "gravel.png",
    "brick": "brick.png",
    "grass": "grass.png",
    "camera": "camera.png",
    "coins": "coins.png",
    "horse": "horse.png",
}
PHOTOS: tuple[str, ...] = tuple(_PHOTO_FILES)
# colourful, feature-rich photographs for objects and walls
OBJECT_PHOTOS: tuple[str, ...] = ("astronaut", "coffee", "chelsea", "rocket", "motorcycle", "ihc")
# the floor is a 3 x 3 mosaic of these (several are grey-level texture photographs)
FLOOR_PHOTOS: tuple[str, ...] = ("gravel", "brick", "grass", "camera", "coins", "coffee", "chelsea",
                                 "motorcycle", "astronaut")


def srgb_to_linear(x: np.ndarray) -> np.ndarray:
    """sRGB-encoded values in [0, 1] -> linear values (IEC 61966-2-1)."""
    x = np.asarray(x, dtype=np.float32)
    return np.where(x <= 0.04045, x / 12.92, ((x + 0.055) / 1.055) ** 2.4).astype(np.float32)


def linear_to_srgb(x: np.ndarray) -> np.ndarray:
    """Linear values -> sRGB-encoded values in [0, 1] (clipped)."""
    x = np.clip(np.asarray(x, dtype=np.float32), 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055).astype(np.float32)


def to_srgb8(x: np.ndarray) -> np.ndarray:
    """Linear float image -> 8-bit sRGB image (rounded, clipped)."""
    return np.round(linear_to_srgb(x) * 255.0).astype(np.uint8)


def load_photo(name: str, size: int | None = None) -> np.ndarray:
    """A bundled scikit-image photograph as a linear float32 [H, W, 3] array.

    ``size``: if given, the image is centre-cropped to a square and resized to ``size`` x ``size``.
    """
    import skimage.data
    import skimage.io
    from skimage.transform import resize

    if name not in _PHOTO_FILES:
        raise ValueError(f"unknown photo {name!r}; choose from {', '.join(PHOTOS)}")
    img = skimage.io.imread(Path(skimage.data.data_dir) / _PHOTO_FILES[name])
    if img.ndim == 2:
        img = np.stack([img] * 3, axis=-1)
    img = img[..., :3].astype(np.float32) / 255.0
    if size is not None:
        h, w = img.shape[:2]
        s = min(h, w)
        top, left = (h - s) // 2, (w - s) // 2
        img = img[top : top + s, left : left + s]
        img = resize(img, (size, size), order=1, anti_aliasing=True).astype(np.float32)
    return srgb_to_linear(img)


def mosaic(names: list[str] | tuple[str, ...], grid: int, tile: int) -> np.ndarray:
    """A ``grid`` x ``grid`` mosaic of distinct photos (linear RGB), each ``tile`` pixels wide."""
    if len(names) < grid * grid:
        raise ValueError(f"mosaic needs {grid * grid} photos, got {len(names)}")
    rows = []
    for r in range(grid):
        rows.append(np.concatenate([load_photo(names[r * grid + c], tile) for c in range(grid)], axis=1))
    return np.concatenate(rows, axis=0)


def environment_map(
    height: int = 128, *, band_photos: tuple[str, ...] = ("coffee", "astronaut", "rocket", "chelsea"),
    sky_radiance: float = 1.6, band_gain: float = 2.0, ground_radiance: float = 0.15,
) -> np.ndarray:
    """Equirectangular environment (linear RGB, [height, 2*height, 3]), y-up like Mitsuba's envmap.

    Top: a bright sky gradient; a horizon band (elevation -5 to 30 degrees) made of photographs,
    so that glass shows structured, clearly visible reflections; below: a dark ground.
    """
    width = 2 * height
    rows = (np.arange(height) + 0.5) / height
    elevation = 90.0 - 180.0 * rows  # degrees, +90 at the top row
    env = np.zeros((height, width, 3), dtype=np.float32)
    t = np.clip((elevation - 30.0) / 60.0, 0.0, 1.0)[:, None]
    sky = (1 - t) * np.array([0.85, 0.9, 1.0]) + t * np.array([0.45, 0.6, 1.0])
    env[:] = (sky_radiance * sky)[:, None, :]
    band = (elevation <= 30.0) & (elevation >= -5.0)
    band_rows = int(band.sum())
    if band_rows > 0:
        tiles = [load_photo(n, band_rows) for n in band_photos]
        strip = np.concatenate(tiles, axis=1)
        reps = int(np.ceil(width / strip.shape[1]))
        strip = np.concatenate([strip] * reps, axis=1)[:, :width]
        env[band] = band_gain * strip
    env[elevation < -5.0] = ground_radiance
    return env.astype(np.float32)
