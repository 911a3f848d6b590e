"""Photographic textures and the environment map of the synthetic scenes.

All textures are real photographs shipped inside scikit-image (no download), so that the
renders have the kind of texture SfM needs. Images are returned as float32 *linear* RGB arrays
(sRGB decoded), which is what Mitsuba's ``bitmap`` texture expects for float data.
"""

from __future__ import annotations

import functools
from pathlib import Path

import numpy as np

from rtsplat.io.images import srgb_to_linear

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
}
PHOTOS: tuple[str, ...] = tuple(_PHOTO_FILES)
# colourful, feature-rich photographs for objects and walls
OBJECT_PHOTOS: tuple[str, ...] = ("astronaut", "coffee", "chelsea", "rocket", "motorcycle", "ihc")
# the floor is a 3 x 3 mosaic of these (several are grey-level texture photographs)
FLOOR_PHOTOS: tuple[str, ...] = (
    "gravel",
    "brick",
    "grass",
    "camera",
    "coins",
    "coffee",
    "chelsea",
    "motorcycle",
    "astronaut",
)


@functools.lru_cache(maxsize=32)
def _decoded(name: str) -> np.ndarray:
    """A bundled photograph as sRGB float32 [H, W, 3] in [0, 1] (cached; do not modify)."""
    import skimage.data
    import skimage.io

    if name not in _PHOTO_FILES:
        raise ValueError(f"unknown photo {name!r}; choose from {', '.join(PHOTOS)}")
    path = Path(skimage.data.data_dir) / _PHOTO_FILES[name]
    if not path.is_file():
        raise FileNotFoundError(
            f"scikit-image's bundled photograph {path} is missing; "
            "reinstall scikit-image (pip install --force-reinstall 'scikit-image>=0.22')"
        )
    img = skimage.io.imread(path)
    if img.ndim == 2:
        img = np.stack([img] * 3, axis=-1)
    img = img[..., :3].astype(np.float32) / float(np.iinfo(img.dtype).max if img.dtype.kind == "u" else 1.0)
    img.setflags(write=False)
    return img


def _resize(img: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    from skimage.transform import resize

    return resize(img, shape, order=1, anti_aliasing=True).astype(np.float32)


def load_photo(name: str, size: int | None = None) -> np.ndarray:
    """A bundled scikit-image photograph as a linear float32 [H, W, 3] array.

    ``size``: if given, the image is centre-cropped to a square and resized to ``size`` x ``size``.
    """
    img = _decoded(name)
    if size is not None:
        h, w = img.shape[:2]
        side = min(h, w)
        top, left = (h - side) // 2, (w - side) // 2
        img = _resize(img[top : top + side, left : left + side], (size, size))
    return srgb_to_linear(img)


def photo_crop(name: str, shape: tuple[int, int], rng: np.random.Generator, min_fraction: float = 0.4) -> np.ndarray:
    """A random crop of a photograph (linear RGB) resized to ``shape`` = (rows, columns).

    The crop has the aspect ratio of ``shape`` and covers ``min_fraction`` to all of the largest
    such crop, so that tiles show the photos' structure at different scales.
    """
    img = _decoded(name)
    h, w = img.shape[:2]
    aspect = shape[1] / shape[0]
    ch_max = min(h, int(w / aspect))
    ch = max(8, int(ch_max * float(rng.uniform(min_fraction, 1.0))))
    cw = max(8, min(w, int(round(ch * aspect))))
    top = int(rng.integers(0, h - ch + 1))
    left = int(rng.integers(0, w - cw + 1))
    return srgb_to_linear(_resize(img[top : top + ch, left : left + cw], shape))


def tile_mosaic(
    names: tuple[str, ...] | list[str], rows: int, cols: int, tile: int, rng: np.random.Generator
) -> np.ndarray:
    """A ``rows`` x ``cols`` mosaic (linear RGB, ``tile`` pixels per tile) of random photo crops.

    Photos are drawn from ``names`` in shuffled rounds, so neighbouring tiles rarely repeat a photo
    and no two tiles are the same crop (SfM must not confuse them).
    """
    order: list[str] = []
    while len(order) < rows * cols:
        order += [names[i] for i in rng.permutation(len(names))]
    tiles = [photo_crop(order[k], (tile, tile), rng) for k in range(rows * cols)]
    return np.concatenate([np.concatenate(tiles[r * cols : (r + 1) * cols], axis=1) for r in range(rows)], axis=0)


def mosaic(names: list[str] | tuple[str, ...], grid: int, tile: int) -> np.ndarray:
    """A ``grid`` x ``grid`` mosaic of distinct photos (linear RGB), each ``tile`` pixels wide."""
    if len(names) < grid * grid:
        raise ValueError(f"mosaic needs {grid * grid} photos, got {len(names)}")
    rows = []
    for r in range(grid):
        rows.append(np.concatenate([load_photo(names[r * grid + c], tile) for c in range(grid)], axis=1))
    return np.concatenate(rows, axis=0)


def environment_map(
    height: int = 256,
    *,
    band_photos: tuple[str, ...] = (
        "coffee",
        "astronaut",
        "rocket",
        "chelsea",
        "motorcycle",
        "hubble",
        "ihc",
        "retina",
    ),
    sky_radiance: float = 1.6,
    band_gain: float = 2.0,
    ground_radiance: float = 0.15,
    band_elevation: tuple[float, float] = (-15.0, 30.0),
) -> np.ndarray:
    """Equirectangular environment (linear RGB, [height, 2*height, 3]), y-up like Mitsuba's envmap.

    Top: a bright sky gradient; a horizon band (``band_elevation``, degrees) of photographs side by
    side around the horizon (each used once, no repeats), so that glass shows structured, clearly
    visible reflections and the background has features; below: a dark ground. The band reaches
    below the horizon so that no featureless strip shows between the floor's edge and the band.
    """
    width = 2 * height
    rows = (np.arange(height) + 0.5) / height
    elevation = 90.0 - 180.0 * rows  # degrees, +90 at the top row
    env = np.zeros((height, width, 3), dtype=np.float32)
    t = np.clip((elevation - 30.0) / 60.0, 0.0, 1.0)[:, None]
    sky = (1 - t) * np.array([0.85, 0.9, 1.0]) + t * np.array([0.45, 0.6, 1.0])
    env[:] = (sky_radiance * sky)[:, None, :]
    env[elevation < band_elevation[0]] = ground_radiance
    band = (elevation <= band_elevation[1]) & (elevation >= band_elevation[0])
    band_rows = int(band.sum())
    if band_rows > 0 and band_photos:
        n = len(band_photos)
        edges = np.linspace(0, width, n + 1).round().astype(int)
        tiles = [
            _resize(
                _center_crop(_decoded(name), band_rows / (edges[k + 1] - edges[k])),
                (band_rows, int(edges[k + 1] - edges[k])),
            )
            for k, name in enumerate(band_photos)
        ]
        env[band] = band_gain * srgb_to_linear(np.concatenate(tiles, axis=1))
    return env.astype(np.float32)


def _center_crop(img: np.ndarray, aspect_hw: float) -> np.ndarray:
    """The largest centred crop of ``img`` with height / width = ``aspect_hw``."""
    h, w = img.shape[:2]
    ch, cw = (h, int(round(h / aspect_hw))) if h / w < aspect_hw else (int(round(w * aspect_hw)), w)
    ch, cw = min(ch, h), min(cw, w)
    top, left = (h - ch) // 2, (w - cw) // 2
    return img[top : top + ch, left : left + cw]
