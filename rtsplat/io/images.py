"""Image and mask I/O.

Every image is returned as ``float32`` ``[H, W, 3]`` RGB, display-referred sRGB in ``[0, 1]``:

* 8- and 16-bit files (PNG, JPEG, TIFF) are scaled by their integer range, so 16-bit precision is kept;
* float files (EXR, HDR, float TIFF) hold linear radiance; they are clipped to ``[0, 1]`` and
  encoded with the sRGB transfer function, so every prepared image is sRGB;
* grey images are repeated to RGB, an alpha channel is dropped. OpenImageIO would premultiply
  RGBA PNGs on read; we open them with ``oiio:UnassociatedAlpha=1`` so colours are not darkened.

OpenImageIO is used when installed (EXR, 16-bit, TIFF, ...), OpenCV otherwise. Unreadable or
truncated files raise :class:`~rtsplat.errors.PipelineError` naming the file.

Pixels are taken as the file stores them, by every stage: COLMAP (pycolmap 4.2) extracts features from
the stored pixels and ignores the EXIF ``Orientation`` tag, so a file whose tag says it is displayed
turned or mirrored (what phones write for photos held sideways) is refused by :func:`read_header` and
every reader here, naming the file and the fix (rotate the pixels upright: ``exiftran -ai``, or
``mogrify -auto-orient``). Nothing then disagrees on which way up an image is: SfM, the masks,
prepare and the metrics all see the pixels a viewer shows.

Masks are single-channel: ``read_mask`` returns ``bool [H, W]`` (white = transparent surface),
``write_mask`` writes 8-bit 0/255 PNGs.
"""

from __future__ import annotations

import struct
import zlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from rtsplat.errors import PipelineError
from rtsplat.io.atomic import write_bytes_atomic

IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".exr", ".hdr", ".bmp", ".webp")
FLOAT_EXTENSIONS = (".exr", ".hdr")
# photo formats that are not read (not decoded by COLMAP, or needing a raw developer): named when found
UNSUPPORTED_PHOTO_FORMATS = {
    **{ext: "HEIC/HEIF" for ext in (".heic", ".heif", ".hif")},
    ".avif": "AVIF",
    ".jxl": "JPEG XL",
    **{ext: "camera RAW" for ext in (".dng", ".cr2", ".cr3", ".crw", ".nef", ".nrw", ".arw", ".srf", ".sr2",
                                     ".orf", ".rw2", ".raf", ".pef", ".srw", ".raw", ".3fr", ".erf", ".kdc",
                                     ".dcr", ".mrw", ".x3f", ".iiq", ".rwl", ".gpr")},
}
# EXIF Orientation values (TIFF tag 274) and how a viewer turns the stored pixels for display
ORIENTATIONS = {
    2: "mirrored left-right", 3: "turned 180 degrees", 4: "mirrored top-bottom",
    5: "mirrored and turned 90 degrees", 6: "turned 90 degrees clockwise",
    7: "mirrored and turned 90 degrees", 8: "turned 90 degrees counter-clockwise",
}
ORIENTATION_FIX = (
    "rotate the pixels upright and reset the tag, e.g. `exiftran -ai *.jpg` in the folder (lossless, JPEG) "
    "or `mogrify -auto-orient *.jpg` (ImageMagick), then re-run; SfM (COLMAP) reads the stored pixels and "
    "ignores the tag"
)


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


def check_orientation(path: Path, orientation: int) -> None:
    """Refuse a file whose EXIF orientation says it is displayed turned or mirrored (see the module docstring)."""
    if orientation in (0, 1):
        return
    how = ORIENTATIONS.get(orientation, "an unknown orientation")
    raise PipelineError(
        f"the image is stored sideways or mirrored: its EXIF Orientation tag is {orientation} (displayed "
        f"{how}); rtsplat reads every image as stored, so its pixels must be upright",
        path=path,
        fix=ORIENTATION_FIX,
    )


def _exif_orientation_pil(path: Path) -> int:
    """The EXIF orientation of ``path`` read with Pillow (the OpenCV path's source of the tag); 1 without Pillow."""
    try:
        from PIL import Image
    except ImportError:  # pragma: no cover - Pillow comes with the pipeline's dependencies
        return 1
    try:
        with Image.open(path) as im:
            return int(im.getexif().get(0x0112, 1))
    except Exception:  # unreadable: the decoder names the problem
        return 1


def read_header(path: str | Path) -> ImageHeader:
    """Width, height and channel count without decoding the pixels; a file stored sideways
    (EXIF orientation other than 1) raises :class:`PipelineError` (:func:`check_orientation`)."""
    path = Path(path)
    oiio = _oiio()
    if oiio is not None:
        inp = oiio.ImageInput.open(str(path))
        if inp is None:
            raise _bad(path, oiio.geterror())
        spec = inp.spec()
        inp.close()
        check_orientation(path, int(spec.get_int_attribute("Orientation", 1)))
        return ImageHeader(path, int(spec.width), int(spec.height), int(spec.nchannels))
    arr = _read_cv2(path)
    return ImageHeader(path, arr.shape[1], arr.shape[0], 1 if arr.ndim == 2 else arr.shape[2])


def _read_cv2(path: Path) -> np.ndarray:
    import cv2

    arr = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)  # the stored pixels: no EXIF rotation
    if arr is None:
        raise _bad(path, "OpenCV could not decode it")
    check_orientation(path, _exif_orientation_pil(path))
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
        check_orientation(path, int(spec.get_int_attribute("Orientation", 1)))
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


PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
PNG_SOFTWARE = b"Software"  # the tEXt keyword that names the program that wrote a PNG


def _png_chunk(kind: bytes, data: bytes) -> bytes:
    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))


def png_software(path: str | Path) -> str | None:
    """The ``Software`` text of the PNG ``path`` (what :func:`write_png` records as ``software``), None when
    it has none or is no readable PNG."""
    try:
        with open(path, "rb") as fh:
            if fh.read(8) != PNG_SIGNATURE:
                return None
            while True:
                head = fh.read(8)
                if len(head) < 8:
                    return None
                length, kind = struct.unpack(">I", head[:4])[0], head[4:]
                if kind in (b"IDAT", b"IEND"):  # text chunks that name the writer come before the pixels
                    return None
                data = fh.read(length + 4)[:length]
                if kind == b"tEXt" and data.startswith(PNG_SOFTWARE + b"\0"):
                    return data[len(PNG_SOFTWARE) + 1:].decode("latin-1")
    except OSError:
        return None


def write_png(path: str | Path, image: np.ndarray, bits: int = 8, software: str | None = None) -> None:
    """Write a float image in [0, 1] (``[H, W]`` or ``[H, W, 3]``), a uint8/uint16 image (as is) or a
    bool mask as PNG, atomically (:func:`rtsplat.io.atomic.write_bytes_atomic`). ``software``: the
    command that wrote it, kept as the PNG's ``Software`` text (:func:`png_software` reads it back), so
    that command can tell its own file from one of the user's."""
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
    ok, encoded = cv2.imencode(".png", data)
    if not ok:
        raise PipelineError(f"cannot encode a {data.dtype} image of shape {data.shape} as PNG", path=path,
                            fix="pass an [H, W] or [H, W, 3] image")
    data = encoded.tobytes()
    if software is not None:  # a tEXt chunk right after the header (IHDR: 8 + 13 + 4 bytes)
        end = len(PNG_SIGNATURE) + 25
        data = data[:end] + _png_chunk(b"tEXt", PNG_SOFTWARE + b"\0" + software.encode("latin-1")) + data[end:]
    write_bytes_atomic(path, data)


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


def unsupported_photos(directory: str | Path) -> list[Path]:
    """Files directly inside ``directory`` in a photo format that is not read (:data:`UNSUPPORTED_PHOTO_FORMATS`)."""
    directory = Path(directory)
    if not directory.is_dir():
        return []
    return sorted((p for p in directory.iterdir() if p.is_file() and p.suffix.lower() in UNSUPPORTED_PHOTO_FORMATS),
                  key=lambda p: p.name)


def _convert_fix(formats: set[str]) -> str:
    ways = []
    if "HEIC/HEIF" in formats or "AVIF" in formats or "JPEG XL" in formats:
        ways.append("convert HEIC/AVIF/JPEG XL photos to JPEG, e.g. `heif-convert IMG_0001.HEIC IMG_0001.jpg` "
                    "(libheif) or `mogrify -format jpg *.HEIC` (ImageMagick built with HEIC support)")
    if "camera RAW" in formats:
        ways.append("develop RAW files to 16-bit TIFF or JPEG, e.g. `darktable-cli IMG_0001.DNG IMG_0001.tif` or "
                    "`dcraw -T -6 *.CR2`")
    return "; ".join(ways) + f" (readable: {', '.join(IMAGE_EXTENSIONS)}), or move them out of the folder"


def check_unsupported_photos(directory: Path, paths: list[Path], log=None) -> None:
    """Photos in an unsupported format beside the readable ``paths``: one with a readable twin of the same
    stem (a RAW+JPEG pair) is skipped and named through ``log``; any other is an error naming it and how to
    convert it, as is a folder of unsupported photos only."""
    others = unsupported_photos(directory)
    if not others:
        return
    stems = {p.stem for p in paths}
    twins = [p for p in others if p.stem in stems]
    alone = [p for p in others if p.stem not in stems]
    formats = {UNSUPPORTED_PHOTO_FORMATS[p.suffix.lower()] for p in others}
    if alone:
        shown = ", ".join(p.name for p in alone[:5]) + (f" and {len(alone) - 5} more" if len(alone) > 5 else "")
        kinds = " and ".join(sorted({UNSUPPORTED_PHOTO_FORMATS[p.suffix.lower()] for p in alone}))
        where = "beside the readable ones" if paths else "and no readable images"
        raise PipelineError(
            f"{len(alone)} photo(s) in a format rtsplat does not read ({kinds}) {where}: {shown}",
            path=directory,
            fix=_convert_fix(formats),
        )
    if log is not None:
        shown = ", ".join(p.name for p in twins[:5]) + (f" and {len(twins) - 5} more" if len(twins) > 5 else "")
        log(f"{directory}: skipped {len(twins)} file(s) in an unsupported format that have a readable copy of "
            f"the same name (e.g. RAW beside JPEG): {shown}")


def duplicate_photos(paths: list[Path]) -> tuple[Path, Path] | None:
    """The first pair of byte-identical files among ``paths`` (same size, then same SHA-256), or None.
    Only files that share their size with another are read."""
    import hashlib
    from collections import defaultdict

    by_size: dict[int, list[Path]] = defaultdict(list)
    for p in paths:
        by_size[p.stat().st_size].append(p)
    for group in by_size.values():
        if len(group) < 2:
            continue
        seen: dict[str, Path] = {}
        for p in group:
            digest = hashlib.sha256()
            with open(p, "rb") as fh:
                for chunk in iter(lambda: fh.read(1 << 20), b""):
                    digest.update(chunk)
            key = digest.hexdigest()
            if key in seen:
                return seen[key], p
            seen[key] = p
    return None


def validate_image_set(directory: str | Path, decode: bool = True, progress: bool = False,
                       log=None) -> list[ImageHeader]:
    """Check a scene's image folder: not empty, no photo in an unsupported format without a readable copy
    (:func:`check_unsupported_photos`; ``log`` is told of those skipped), no two byte-identical files, every
    file readable (fully decoded when ``decode``) and stored upright (:func:`check_orientation`), all the
    same size. Returns the headers in name order; raises :class:`PipelineError` otherwise."""
    from collections import Counter

    from tqdm import tqdm

    directory = Path(directory)
    paths = list_images(directory)
    check_unsupported_photos(directory, paths, log)
    if not paths:
        raise PipelineError(
            "no images found" if directory.is_dir() else "image folder does not exist",
            path=directory,
            fix=f"put the scene's photos ({', '.join(IMAGE_EXTENSIONS[:4])}, ...) in this folder",
        )
    twins = duplicate_photos(paths)
    if twins is not None:
        raise PipelineError(
            f"{twins[0].name} and {twins[1].name} are the same file (byte-identical): one photo would count as "
            "two views",
            path=twins[1],
            fix=f"delete one of the two copies ({twins[1].name}, say) from {directory}",
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
        turned = (odd.width, odd.height) == (h, w)
        raise PipelineError(
            f"images of mixed sizes: this one is {odd.width}x{odd.height}, most are {w}x{h} "
            f"({len(sizes)} different sizes in {directory})"
            + ("; it is the others turned sideways (portrait and landscape photos mixed)" if turned else ""),
            path=odd.path,
            fix="use images from one camera at one resolution (resize or remove the odd ones)"
            + ("; photos must be stored the same way up: remove the portrait (or landscape) ones" if turned else ""),
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
