"""Image and mask I/O.

Every image is returned as ``float32`` ``[H, W, 3]`` RGB, display-referred sRGB in ``[0, 1]``:

* 8- and 16-bit files (PNG, JPEG, TIFF) are scaled by their integer range, so 16-bit precision is kept;
* float files (EXR, HDR, float TIFF) hold linear radiance; they are clipped to ``[0, 1]`` and
  encoded with the sRGB transfer function, so every prepared image is sRGB;
* grey images are repeated to RGB, an alpha channel is dropped. OpenImageIO would premultiply
  RGBA PNGs on read; we open them with ``oiio:UnassociatedAlpha=1`` so colours are not darkened.

OpenImageIO is used when installed (EXR, 16-bit, TIFF, ...), OpenCV otherwise. Unreadable or
truncated files raise :class:`~rtsplat.errors.PipelineError` naming the file.

Masks are single-channel: ``read_mask`` returns ``bool [H, W]`` (white = transparent surface),
``write_mask`` writes 8-bit 0/255 PNGs.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from rtsplat.errors import PipelineError

IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".exr", ".hdr", ".bmp", ".webp")
FLOAT_EXTENSIONS = (".exr", ".hdr")


@dataclass(frozen=True)
class ImageHeader:
    path: Path
    width: int
    height: int
    channels: int


def list_images(directory: str | Path) -> list[Path]:
    """Image files directly inside ``directory``, sorted by name (the order of the train/test split)."""
    directory = Path(directory)
    if not directory.is_dir():
        return []
    return sorted(
        (p for p in directory.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_EXTENSIONS),
        key=lambda p: p.name,
    )


def linear_to_srgb(x: np.ndarray) -> np.ndarray:
    """Linear values -> sRGB-encoded values in [0, 1] (clipped; float32; IEC 61966-2-1)."""
    x = np.clip(np.asarray(x, dtype=np.float32), 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1.0 / 2.4) - 0.055).astype(np.float32)


def srgb_to_linear(x: np.ndarray) -> np.ndarray:
    """sRGB-encoded values in [0, 1] -> linear values (float32; the inverse of :func:`linear_to_srgb`)."""
    x = np.asarray(x, dtype=np.float32)
    return np.where(x <= 0.04045, x / 12.92, ((x + 0.055) / 1.055) ** 2.4).astype(np.float32)


def _oiio():
    try:
        import OpenImageIO as oiio
    except ImportError:  # pragma: no cover - the pipeline extra installs it
        return None
    return oiio


def _bad(path: Path, why: str) -> PipelineError:
    return PipelineError(
        f"cannot read image ({why.strip() or 'unknown error'})",
        path=path,
        fix="re-export or re-copy the file (it may be truncated or not an image), or delete it from the scene",
    )


def read_header(path: str | Path) -> ImageHeader:
    """Width, height and channel count without decoding the pixels."""
    path = Path(path)
    oiio = _oiio()
    if oiio is not None:
        inp = oiio.ImageInput.open(str(path))
        if inp is None:
            raise _bad(path, oiio.geterror())
        spec = inp.spec()
        inp.close()
        return ImageHeader(path, int(spec.width), int(spec.height), int(spec.nchannels))
    arr = _read_cv2(path)
    return ImageHeader(path, arr.shape[1], arr.shape[0], 1 if arr.ndim == 2 else arr.shape[2])


def _read_cv2(path: Path) -> np.ndarray:
    import cv2

    arr = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if arr is None:
        raise _bad(path, "OpenCV could not decode it")
    if arr.ndim == 3:
        order = [2, 1, 0] + list(range(3, arr.shape[2]))
        arr = arr[..., order[: arr.shape[2]]] if arr.shape[2] >= 3 else arr
    return arr


def _read_raw(path: Path) -> tuple[np.ndarray, bool]:
    """Pixels [H, W, C] as float32 in the file's own range; bool: the file stores float data."""
    oiio = _oiio()
    if oiio is None:
        arr = _read_cv2(path)
        is_float = arr.dtype.kind == "f"
        if arr.dtype == np.uint8:
            out = arr.astype(np.float32) / 255.0
        elif arr.dtype == np.uint16:
            out = arr.astype(np.float32) / 65535.0
        else:
            out = arr.astype(np.float32)
        return (out[..., None] if out.ndim == 2 else out), is_float
    config = oiio.ImageSpec()
    config.attribute("oiio:UnassociatedAlpha", 1)
    inp = oiio.ImageInput.open(str(path), config)
    if inp is None:
        raise _bad(path, oiio.geterror())
    try:
        spec = inp.spec()
        is_float = spec.format.basetype in (oiio.FLOAT, oiio.HALF, oiio.DOUBLE)
        pixels = inp.read_image(0, 0, 0, spec.nchannels, "float")
        if pixels is None or inp.has_error:
            raise _bad(path, inp.geterror())
    finally:
        inp.close()
    pixels = np.asarray(pixels, dtype=np.float32)
    if pixels.ndim == 2:
        pixels = pixels[..., None]
    return pixels, is_float


def read_image(path: str | Path) -> np.ndarray:
    """RGB float32 ``[H, W, 3]`` sRGB in [0, 1] (see the module docstring for the conversions)."""
    path = Path(path)
    pixels, is_float = _read_raw(path)
    c = pixels.shape[2]
    if c == 1 or c == 2:  # grey or grey + alpha
        rgb = np.repeat(pixels[..., :1], 3, axis=2)
    else:
        rgb = pixels[..., :3]
    if is_float or path.suffix.lower() in FLOAT_EXTENSIONS:
        if not np.all(np.isfinite(rgb)):
            rgb = np.nan_to_num(rgb, nan=0.0, posinf=1.0, neginf=0.0)
        rgb = linear_to_srgb(rgb)
    return np.ascontiguousarray(np.clip(rgb, 0.0, 1.0), dtype=np.float32)


def read_raw_pixels(path: str | Path) -> np.ndarray:
    """Pixels ``float32 [H, W, C]`` of an integer or float file, integers scaled to [0, 1] by their type's
    maximum, no colour conversion (what masks are read as)."""
    return _read_raw(Path(path))[0]


def read_mask(path: str | Path, threshold: float = 0.5) -> np.ndarray:
    """Binary mask ``bool [H, W]``: the first channel (or the alpha of a grey+alpha file) >= threshold.

    Masks are read raw (no sRGB conversion): 128/255 counts as white with the default threshold.
    """
    path = Path(path)
    pixels, _ = _read_raw(path)
    channel = pixels[..., 0]
    if pixels.shape[2] in (2, 4) and float(channel.max(initial=0.0)) == float(channel.min(initial=0.0)):
        channel = pixels[..., -1]  # a flat colour with the mask in alpha
    return channel >= threshold


def to_uint(image: np.ndarray, bits: int = 8) -> np.ndarray:
    if bits not in (8, 16):
        raise ValueError(f"bits must be 8 or 16, got {bits}")
    top = 255 if bits == 8 else 65535
    out = np.round(np.clip(image, 0.0, 1.0) * top)
    return out.astype(np.uint8 if bits == 8 else np.uint16)


def write_png(path: str | Path, image: np.ndarray, bits: int = 8) -> None:
    """Write a float image in [0, 1] (``[H, W]`` or ``[H, W, 3]``), a uint8/uint16 image (as is) or a
    bool mask as PNG."""
    import cv2

    path = Path(path)
    if image.dtype == bool:
        data = image.astype(np.uint8) * 255
    elif image.dtype in (np.uint8, np.uint16):
        data = image
    else:
        data = to_uint(image, bits)
    if data.ndim == 3:
        data = np.ascontiguousarray(data[..., ::-1])  # RGB -> BGR for OpenCV
    if not cv2.imwrite(str(path), data):
        raise PipelineError("cannot write PNG", path=path, fix="check that the directory is writable")


def write_mask(path: str | Path, mask: np.ndarray) -> None:
    write_png(path, np.asarray(mask, dtype=bool))


def area_downsample(image: np.ndarray, factor: int) -> np.ndarray:
    """Box-filter downsampling by an integer ``factor`` ("area" filter).

    The image is first cropped at the right/bottom to a multiple of ``factor``; every output pixel
    is then the exact mean of a ``factor x factor`` block. With the corner-at-(0, 0) pixel
    convention this makes ``K[:2] / factor`` the exact intrinsics of the result (cropping at the
    right/bottom edge does not move the principal point).
    """
    if factor == 1:
        return image
    h, w = image.shape[:2]
    h2, w2 = h // factor, w // factor
    if h2 == 0 or w2 == 0:
        raise ValueError(f"image {w}x{h} is smaller than the downsample factor {factor}")
    crop = image[: h2 * factor, : w2 * factor].astype(np.float32)
    shape = (h2, factor, w2, factor) + crop.shape[2:]
    return crop.reshape(shape).mean(axis=(1, 3)).astype(np.float32)


def validate_image_set(directory: str | Path, decode: bool = True, progress: bool = False) -> list[ImageHeader]:
    """Check a scene's image folder: not empty, every file readable (fully decoded when ``decode``),
    all the same size. Returns the headers in name order; raises :class:`PipelineError` otherwise."""
    from collections import Counter

    from tqdm import tqdm

    directory = Path(directory)
    paths = list_images(directory)
    if not paths:
        raise PipelineError(
            "no images found" if directory.is_dir() else "image folder does not exist",
            path=directory,
            fix=f"put the scene's photos ({', '.join(IMAGE_EXTENSIONS[:4])}, ...) in this folder",
        )
    headers = []
    for p in tqdm(paths, desc=f"checking {directory.parent.name}/{directory.name}", unit="img", disable=not progress):
        if decode:
            arr = read_image(p)
            headers.append(ImageHeader(p, arr.shape[1], arr.shape[0], 3))
        else:
            headers.append(read_header(p))
    sizes = Counter((h.width, h.height) for h in headers)
    if len(sizes) > 1:
        (w, h), _ = sizes.most_common(1)[0]
        odd = next(x for x in headers if (x.width, x.height) != (w, h))
        raise PipelineError(
            f"images of mixed sizes: this one is {odd.width}x{odd.height}, most are {w}x{h} "
            f"({len(sizes)} different sizes in {directory})",
            path=odd.path,
            fix="use images from one camera at one resolution (resize or remove the odd ones)",
        )
    return headers


def capture_time(path: str | Path) -> str | None:
    """The EXIF capture time of an image ("YYYY:MM:DD HH:MM:SS", with sub-seconds when recorded), None without one."""
    from PIL import Image

    try:
        with Image.open(path) as im:
            exif = im.getexif()
            sub = exif.get_ifd(0x8769)  # the Exif sub-IFD: DateTimeOriginal, SubsecTimeOriginal
    except (OSError, ValueError, SyntaxError):
        return None
    when = sub.get(0x9003) or exif.get(0x0132)  # DateTimeOriginal, else DateTime
    if not isinstance(when, str) or not when.strip():
        return None
    subsec = sub.get(0x9291)
    return when.strip() + (f".{str(subsec).strip()}" if subsec else "")
