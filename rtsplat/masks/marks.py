"""Marked views drawn in the config (``masks.marks``): boxes and polygons checked against the photos
(:func:`check_marks`) and turned into the masks that :mod:`rtsplat.masks.propagation` carries to the other
photos (:func:`marks_to_masks`)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from rtsplat.config import MaskMark, MaskPropagationConfig, MasksConfig
from rtsplat.errors import PipelineError
from rtsplat.io.images import read_header, read_image


def _shapes(mark: MaskMark) -> list[tuple[str, str, list]]:
    """A mark's boxes and polygons as (kind, config key below the photo's, corners or edges), in the order
    box, polygon, boxes, polygons."""
    shapes = [("box", "box", mark.box)] if mark.box is not None else []
    shapes += [("polygon", "polygon", mark.polygon)] if mark.polygon is not None else []
    shapes += [("box", f"boxes.{i}", box) for i, box in enumerate(mark.boxes or [])]
    shapes += [("polygon", f"polygons.{i}", polygon) for i, polygon in enumerate(mark.polygons or [])]
    return shapes


def check_marks(marks: dict[str, MaskMark | dict], images: list[Path]) -> dict[str, MaskMark]:
    """``masks.marks`` as :class:`MaskMark` by photo name, checked against the photos: a name that is no photo
    (the closest names suggested), no box or polygon, a polygon of fewer than 3 corners or no area, a box with
    x1 <= x0 or y1 <= y0, coordinates outside the photo. Errors name the photo and the shape's key (``box``,
    ``polygon``, ``boxes.<index>``, ``polygons.<index>``)."""
    import difflib

    from rtsplat.schema import from_dict, plain

    by_name = {img.name: img for img in images}
    checked = {}
    for name, mark in marks.items():
        key = f"config: masks.marks.{name}"
        if name not in by_name:
            close = difflib.get_close_matches(name, list(by_name), n=3, cutoff=0.5)
            raise PipelineError(
                f"marked view {name!r} is not a photo of the scene ({len(by_name)} photos"
                + (f"; closest names: {', '.join(close)})" if close else f", e.g. {', '.join(sorted(by_name)[:3])})"),
                path=key, fix="use the photo's file name as it is in images/ (with its extension)",
            )
        mark = mark if isinstance(mark, MaskMark) else from_dict(MaskMark, plain(mark), root=f"masks.marks.{name}")
        if not _shapes(mark):
            raise PipelineError(
                "a mark needs a box or a polygon", path=key,
                fix="give box: [x0, y0, x1, y1], polygon: [[x, y], ...], or several as boxes: [...] and "
                "polygons: [...] (pixels of the photo)",
            )
        header = read_header(by_name[name])
        w, h = header.width, header.height
        for kind, where, shape in _shapes(mark):
            if kind == "box":
                x0, y0, x1, y1 = (list(shape) + [0.0] * 4)[:4]
                if len(shape) != 4 or not (x1 > x0 and y1 > y0):
                    raise PipelineError(
                        f"box {list(shape)} is not [x0, y0, x1, y1] with x1 > x0 and y1 > y0", path=f"{key}.{where}",
                        fix="give the left, top, right and bottom edges in pixels (x to the right, y down)",
                    )
                corners = np.array([[x0, y0], [x1, y1]], np.float64)
            else:
                corners = np.asarray(shape, np.float64)
                if corners.ndim != 2 or corners.shape[1] != 2 or len(corners) < 3:
                    raise PipelineError(
                        f"polygon of {len(shape)} point(s): a polygon needs at least 3 corners [x, y]",
                        path=f"{key}.{where}", fix="give the outline's corners [[x, y], ...] in pixels of the photo",
                    )
                x, y = corners[:, 0], corners[:, 1]
                if abs(float(np.dot(x, np.roll(y, 1)) - np.dot(y, np.roll(x, 1)))) < 1.0:
                    raise PipelineError(
                        "the polygon has no area (its corners lie on a line)", path=f"{key}.{where}",
                        fix="give the outline's corners in order around the see-through surface",
                    )
            outside = (corners[:, 0] < 0) | (corners[:, 0] > w) | (corners[:, 1] < 0) | (corners[:, 1] > h)
            if outside.any():
                raise PipelineError(
                    f"{kind} corner {corners[outside][0].tolist()} lies outside the photo ({w}x{h} pixels: x in "
                    f"0..{w}, y in 0..{h})", path=f"{key}.{where}",
                    fix=f"give coordinates in pixels of {name} as it is in images/ (not of a downsampled copy)",
                )
        checked[name] = mark
    return checked


def mark_to_mask(mark: MaskMark, image: Path, settings: MaskPropagationConfig) -> tuple[np.ndarray, str]:
    """The mask of one view's checked mark at the photo's size, the union of its shapes: a polygon filled, a
    box cut out with GrabCut (:func:`rtsplat.masks.propagation.box_mask`), and the mark's source: its shapes'
    kinds (``polygon``, ``box``, ``filled box`` where GrabCut found no object inside the box) joined by
    commas, e.g. ``polygon, polygon``."""
    from rtsplat.masks.propagation import box_mask, polygon_mask

    header = read_header(image)
    mask = np.zeros((header.height, header.width), bool)
    pixels, kinds = None, []
    for kind, _, shape in _shapes(mark):
        if kind == "polygon":
            mask |= polygon_mask(np.asarray(shape), header.width, header.height)
            kinds.append("polygon")
            continue
        pixels = read_image(image) if pixels is None else pixels
        cut, kept = box_mask(pixels, tuple(shape), settings)
        mask |= cut
        kinds.append("box" if kept else "filled box")
    return mask, ", ".join(kinds)


def marks_to_masks(marks: dict[str, MaskMark], images: list[Path],
                   cfg: MasksConfig) -> tuple[dict[str, np.ndarray], dict[str, str]]:
    """The masks of the config's marks (checked by :func:`check_marks`) at their photos' sizes and each mark's
    source (:func:`mark_to_mask`)."""
    by_name = {img.name: img for img in images}
    masks, sources = {}, {}
    for name, mark in marks.items():
        masks[name], sources[name] = mark_to_mask(mark, by_name[name], cfg.propagate)
    return masks, sources
