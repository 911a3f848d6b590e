"""A dataset's mask files: each photo's mask found by name (:func:`match_masks`), read whatever its kind
(:func:`interpret_mask`) and written as the stage's ``<stem>.png`` (:func:`ingest_masks`)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from rtsplat.config import MasksConfig
from rtsplat.errors import PipelineError
from rtsplat.io.images import IMAGE_EXTENSIONS, list_images, read_header, write_mask

MASK_NAMING = "<photo name> (IMG_0001.JPG), <photo stem>.<image extension> (IMG_0001.png) or <photo name>.png"


def check_unique_stems(images: list[Path]) -> None:
    """Refuse photos that share a stem (``a.jpg``, ``a.png``): the stage writes one ``<stem>.png`` per photo."""
    by_stem: dict[str, Path] = {}
    for img in images:
        if img.stem in by_stem:
            raise PipelineError(
                f"two photos share a file stem: {by_stem[img.stem].name} and {img.name} "
                f"(their masks would both be {img.stem}.png)",
                path=img.parent,
                fix="rename the photos so their names without extension are unique",
            )
        by_stem[img.stem] = img


def match_masks(images: list[Path], mask_dir: Path) -> dict[Path, Path | None]:
    """Each photo's mask file in ``mask_dir`` (None: it has none); the one lookup of dataset masks by name.

    A mask file belongs to a photo when its name without the extension is the photo's stem or the photo's
    full name, with any image extension in any case (:data:`MASK_NAMING`): ``IMG_0001.JPG``,
    ``IMG_0001.jpg``, ``IMG_0001.png`` and ``IMG_0001.JPG.png`` all belong to ``IMG_0001.JPG``. Stems are
    compared exactly (case-sensitive, like the file system). Raises :class:`PipelineError` when two files
    belong to one photo, when a mask belongs to no photo (naming one expected and one found name), and when
    two photos share a stem (their masks would both be written as ``<stem>.png``).
    """
    images = sorted(images, key=lambda p: p.name)
    check_unique_stems(images)
    files = list_images(mask_dir)
    by_key: dict[str, list[Path]] = {}
    for mask in files:
        by_key.setdefault(mask.stem, []).append(mask)
    found: dict[Path, Path | None] = {}
    owner: dict[Path, Path] = {}
    for img in images:
        candidates = by_key.get(img.stem, []) + (by_key.get(img.name, []) if img.name != img.stem else [])
        if len(candidates) > 1:
            names = " and ".join(m.name for m in candidates)
            raise PipelineError(
                f"photo {img.name} has {len(candidates)} masks: {names}",
                path=mask_dir,
                fix=f"keep one mask per photo (delete or move {candidates[-1].name})",
            )
        mask = candidates[0] if candidates else None
        if mask is not None and mask in owner:
            raise PipelineError(
                f"mask {mask.name} belongs to two photos: {owner[mask].name} and {img.name}",
                path=mask,
                fix="rename the photos so no photo's name is another photo's stem",
            )
        if mask is not None:
            owner[mask] = img
        found[img] = mask
    unmatched = [m for m in files if m not in owner]
    if unmatched and not owner:
        photo = images[0]
        expected = photo.name if photo.suffix == ".png" else f"{photo.name} or {photo.stem}.png"
        raise PipelineError(
            f"none of the {len(files)} masks matches a photo: expected e.g. {expected} (for photo {photo.name}), "
            f"found e.g. {unmatched[0].name}",
            path=mask_dir,
            fix=f"name each mask after its photo: {MASK_NAMING}; or point masks.dir at the right folder",
        )
    if unmatched:
        stem = unmatched[0].stem
        photos = f"images/{stem}.*" + (f" or images/{stem}" if Path(stem).suffix.lower() in IMAGE_EXTENSIONS else "")
        raise PipelineError(
            f"mask has no matching image (expected a photo {photos})",
            path=unmatched[0],
            fix=f"name each mask after its photo ({MASK_NAMING}) or remove masks of deleted photos",
        )
    return found


MIDTONE_LIMIT = 0.25  # a colour mask with more pixels strictly between dark and bright is refused as a photo
LOSSY_EXTENSIONS = (".jpg", ".jpeg", ".webp")  # mask files whose pixels may carry compression noise
# lossy masks: largest difference between the colour channels of a pixel that still counts as grey. The
# black-and-white JPEG masks of a real capture (119 masks) have colour fringes of up to 0.14 on their
# edges (median 0.09); a coloured mask (one colour on black) differs by the brightness of its colour, far more
LOSSY_GREY_TOLERANCE = 0.25


def interpret_mask(pixels: np.ndarray, threshold: float, path: Path, lossy: bool = False) -> tuple[np.ndarray, str]:
    """A mask file's pixels (float [H, W, C] in the file's range scaled to [0, 1]) as (bool [H, W], kind):

    - ``label map``: the values 0 and 1 stored as integers (1/255 or 1/65535 once scaled): 1 is the surface;
    - ``alpha``: a flat colour with the mask in the alpha channel;
    - ``colour``: a coloured mask (e.g. green on black): the brightest colour channel against ``threshold``;
    - ``grey``: the first channel against ``threshold``.

    ``lossy`` (JPEG, WebP): compression leaves values near black and white and slightly coloured fringes at
    the edges, so channels that differ by up to :data:`LOSSY_GREY_TOLERANCE` still make a grey mask, read as
    the mean of the colour channels; ``threshold`` (``masks.threshold``, 0.5 by default: halfway between
    black and white) then cuts the ringing off on both sides. A 0/1 label map does not survive lossy
    compression; save those as PNG.

    A colour image that is mostly mid-tones (a photo saved as a mask) raises :class:`PipelineError`.
    """
    colour = pixels[..., :3] if pixels.shape[2] >= 3 else pixels[..., :1]
    values = np.unique(colour)
    if len(values) == 2 and values[0] == 0 and values[1] <= 1 / 255 + 1e-6:
        return colour.max(-1) > 0, "label map"
    channel, kind = pixels[..., 0], "grey"
    grey_tolerance = LOSSY_GREY_TOLERANCE if lossy else 1 / 255
    if pixels.shape[2] in (2, 4) and float(channel.max(initial=0.0)) == float(channel.min(initial=0.0)):
        channel, kind = pixels[..., -1], "alpha"
    elif pixels.shape[2] >= 3 and np.abs(colour - colour[..., :1]).max(initial=0.0) > grey_tolerance:
        channel, kind = colour.max(-1), "colour"
    elif lossy and pixels.shape[2] >= 3:
        channel = colour.mean(-1)
    midtones = float(((channel > 0.1) & (channel < 0.9)).mean())
    if kind == "colour" and midtones > MIDTONE_LIMIT:
        raise PipelineError(
            f"this does not look like a mask: {100 * midtones:.0f}% of its pixels are neither dark nor bright "
            f"({kind} image)", path=path,
            fix="save masks as black and white (white = see-through surface), a 0/1 label map, or one colour on black",
        )
    return channel >= threshold, kind


def ingest_masks(
    images: list[Path], mask_dir: Path, out: Path, cfg: MasksConfig, progress: bool
) -> tuple[dict[str, float], dict[str, int], list[str]]:
    """Masks of ``images`` found in ``mask_dir`` by :func:`match_masks`, written to ``out`` as ``<stem>.png``
    as they are (white = the value :func:`interpret_mask` finds). Returns the per-image coverage, how many
    masks of each kind, and the photos without a mask (empty masks; an error unless ``masks.allow_missing``)."""
    from tqdm import tqdm

    from rtsplat.io.images import read_raw_pixels

    masks = match_masks(images, mask_dir)
    missing = [img.name for img in images if masks[img] is None]
    if missing and not cfg.allow_missing:
        first = Path(missing[0])
        raise PipelineError(
            f"no mask for image {first.name} ({len(missing)} of {len(images)} photos have none): looked for "
            f"{first.name}, {first.stem}.<image extension> and {first.name}.png",
            path=mask_dir,
            fix="add the missing masks, set masks.allow_missing: true to read those photos as having no "
            "see-through surface (empty masks), or masks.source: propagate to carry the given masks to them "
            "through the SfM cameras",
        )
    coverage, kinds = {}, {}
    for img in tqdm(images, desc="masks", unit="img", disable=not progress):
        header = read_header(img)
        mpath = masks[img]
        if mpath is None:
            mask = np.zeros((header.height, header.width), bool)
        else:
            lossy = mpath.suffix.lower() in LOSSY_EXTENSIONS
            mask, kind = interpret_mask(read_raw_pixels(mpath), cfg.threshold, mpath, lossy)
            kinds[kind] = kinds.get(kind, 0) + 1
            if mask.shape != (header.height, header.width):
                raise PipelineError(
                    f"mask is {mask.shape[1]}x{mask.shape[0]} but image {img.name} is {header.width}x{header.height}",
                    path=mpath,
                    fix="export the mask at the image's resolution (masks of images_N folders do not fit images/)",
                )
        write_mask(out / f"{img.stem}.png", mask)
        coverage[img.stem] = float(mask.mean())
    return coverage, kinds, missing
