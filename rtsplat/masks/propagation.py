"""Transparent masks carried from a few marked views to every view through the SfM cameras.

The marks are carried through the marked views' visual hull (below) or, for flat glass seen from one side,
through the glass's plane (:mod:`rtsplat.masks.plane`); :func:`carry_marks` chooses (``masks.propagate.method``)
and says why, and both paths share the refinements and the per-view loop of :func:`propagate_masks`.

The masks of the marked views (at least :data:`MIN_MARKED`) carve a voxel grid: a voxel stays when every
marked view that has it in frame sees it inside its mask (dilated by half a voxel's footprint), at least
two marked views have it in frame, and every marked view whose mask does not touch the image border (the
whole object is in frame) has it in frame. The grid covers the box that holds most SfM points; a coarse
pass finds the hull, a finer grid over the hull's box refines it (:func:`visual_hull`). Connected parts
much smaller than the largest are dropped. With ``occlusion`` on, opaque things in front of the object hide
it: a marked view does not carve a voxel they hide, and a propagated silhouette leaves out the pixels they
cover. What is opaque is read from the SfM points, and only from points on a surface (:func:`surface_points`:
neighbours in the image at about the same depth), each covering a disc of the points' mean spacing
(:func:`opaque_depth`): points triangulated from what is seen through glass scatter in depth and would punch
scattered holes into the masks.

Every other registered view gets the hull's silhouette: the hull's boundary voxels projected with the
view's camera (COLMAP models with distortion through pycolmap), each splatted as a disc of half its
projected size, holes filled and the outline shrunk by the discs' median radius, so that the discs fill
the gaps between voxel centres without growing the silhouette past them (:func:`project_hull`). A visual
hull holds the object, so the silhouette is the object's mask plus the excess of the few marked directions,
and its outline errs outwards by a pixel or two. Two refinements on the view's image can cut some of it:
OpenCV's GrabCut, seeded with the silhouette as probable foreground, a ring around it as probable background
and the rest as background, where the object's colours differ from the background's
(:func:`refine_with_grabcut`; when it keeps less than ``min_kept`` of the silhouette the silhouette is kept);
and OpenCV's watershed, which moves the outline to the image's strongest edges within a narrow band
(``snap_band``), where the glass has a frame or an edge (:func:`snap_to_edges`). Which helps depends on how
much the glass differs from what it shows: ``refine: auto`` decides per scene by leaving each marked view
out in turn and comparing the projection and both refinements with its given mask
(:func:`choose_refinement`). A prompted segmenter (the ONNX SAM/SAM2 model of ``masks.onnx``) can take
their place: it gets the silhouette's bounding box as its box prompt (:func:`prompted_mask`).

A marked view is a mask, or boxes and polygons drawn on the photo (their union): a polygon is filled
(:func:`polygon_mask`), a box is cut out with GrabCut started from the rectangle (:func:`box_mask`).

Each mask's source is recorded: ``given`` (a marked view), ``propagated``, ``empty`` (the hull does not
project into the view) or ``unregistered`` (SfM has no pose for the photo: empty mask). Large images are
processed at ``work_size`` pixels on their longest side and the mask is scaled back."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from rtsplat.config import MaskPropagationConfig
from rtsplat.errors import PipelineError
from rtsplat.io.colmap import ColmapModel, ColmapView

if TYPE_CHECKING:
    from rtsplat.masks.panes import Pane
    from rtsplat.masks.plane import GlassPlane

MIN_MARKED = 3  # fewer marked views do not bound the object in depth
COARSE_GRID = 48  # voxels along the longest side of the first pass
ONE_SIDE_DEGREES = 10.0  # marked views whose directions differ by less do not bound a hull in depth
AGREEMENT_SIZE = 256  # longest image side the marks' agreement through a plane is measured at
MIN_BOX_KEPT = 0.2  # a box mark's GrabCut cut keeping less of the box is taken for a failure (the box is kept)
# an SfM point occludes only on a surface: this many points within this many mean point spacings in the image, and
# within this fraction of its depth (surface_points)
SURFACE_NEIGHBOURS = 4
SURFACE_RADIUS = 2.0
SURFACE_DEPTH = 0.02


@dataclass
class PropagatedMask:
    name: str
    mask: np.ndarray  # bool [H, W] at the photo's size
    source: str  # "given" | "propagated" | "empty" | "unregistered"
    refinement: str = ""  # propagated and refined: what refined it (grabcut | watershed | onnx); empty: the projection

    @property
    def refined(self) -> bool:
        return bool(self.refinement)


@dataclass
class Hull:
    """Boundary voxels of the visual hull: centres [N, 3] and the voxel size."""

    points: np.ndarray
    step: float
    num_voxels: int


# ----------------------------------------------------------------------------------------------
# cameras


def project_points(view: ColmapView, xyz: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Pixel coordinates [N, 2] (pixel corner at (0, 0)), depth [N] and in-front [N] bool of world
    points in ``view``, with the camera model's distortion."""
    cam = xyz @ view.world_to_camera[:3, :3].T + view.world_to_camera[:3, 3]
    z = cam[:, 2]
    front = z > 1e-9
    uv = np.full((len(xyz), 2), -1e9)
    if not front.any():
        return uv, z, front
    if view.has_distortion:
        import pycolmap

        camera = pycolmap.Camera.create_from_model_name(1, view.model, 1.0, view.width, view.height)
        camera.params = view.params.tolist()
        uv[front] = np.asarray(camera.img_from_cam(np.ascontiguousarray(cam[front])), dtype=np.float64)[:, :2]
    else:
        K = view.K
        uv[front] = cam[front, :2] / z[front, None] * np.diag(K)[:2] + K[:2, 2]
    return uv, z, front


def focal(view: ColmapView) -> float:
    return float(0.5 * (view.K[0, 0] + view.K[1, 1]))


def suggest_views(model: ColmapModel, count: int = 5, exclude: tuple[str, ...] = ()) -> list[str]:
    """``count`` registered views spread around the capture: farthest-point sampling over the camera
    centres, starting from the view farthest from their mean (views in ``exclude`` count as chosen)."""
    names = [v.name for v in model.views]
    centres = np.stack([v.center for v in model.views]) if names else np.zeros((0, 3))
    if not names:
        return []
    chosen = [names.index(n) for n in exclude if n in names]
    if not chosen:
        chosen = [int(np.argmax(np.linalg.norm(centres - centres.mean(0), axis=1)))]
    dist = np.min(np.linalg.norm(centres[:, None] - centres[chosen][None], axis=2), axis=1)
    picks = [] if exclude else list(chosen)
    while len(picks) < min(count, len(names) - len(exclude)):
        i = int(np.argmax(dist))
        picks.append(i)
        dist = np.minimum(dist, np.linalg.norm(centres - centres[i], axis=1))
    return [names[i] for i in picks]


# ----------------------------------------------------------------------------------------------
# the hull


def _grid(lo: np.ndarray, hi: np.ndarray, cells: int) -> tuple[np.ndarray, tuple[int, int, int], float]:
    step = float((hi - lo).max()) / cells
    shape = tuple(int(max(1, np.ceil((hi[i] - lo[i]) / step))) for i in range(3))
    axes = [lo[i] + step * (np.arange(shape[i]) + 0.5) for i in range(3)]
    points = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    return points, shape, step


def _dilate(mask: np.ndarray, radius: int) -> np.ndarray:
    import cv2

    if radius <= 0:
        return mask
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * radius + 1, 2 * radius + 1))
    return cv2.dilate(mask.astype(np.uint8), kernel) > 0


def opaque_depth(view: ColmapView, xyz: np.ndarray, scale: float = 1.0) -> np.ndarray:
    """Depth of the nearest occluding SfM point at each pixel of ``view`` (its size times ``scale``; inf where
    none): each point on a surface (:func:`surface_points`) covers a disc of the mean spacing of the points in
    frame, so a sparse surface hides what lies behind it and a scattered point hides nothing."""
    import cv2

    h, w = int(round(view.height * scale)), int(round(view.width * scale))
    depth = np.full((h, w), np.inf, np.float32)
    if not len(xyz):
        return depth
    uv, z, front = project_points(view, xyz)
    uv = uv * scale
    ok = front & (uv[:, 0] >= 0) & (uv[:, 0] < w) & (uv[:, 1] >= 0) & (uv[:, 1] < h)
    if not ok.any():
        return depth
    spacing = float(np.sqrt(h * w / ok.sum()))
    on_surface = surface_points(uv[ok], z[ok], spacing)
    u = np.floor(uv[ok][on_surface, 0]).astype(np.int64)
    v = np.floor(uv[ok][on_surface, 1]).astype(np.int64)
    np.minimum.at(depth, (v, u), z[ok][on_surface].astype(np.float32))
    radius = int(max(1, round(spacing)))
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * radius + 1, 2 * radius + 1))
    return cv2.erode(depth, kernel)


def surface_points(uv: np.ndarray, z: np.ndarray, spacing: float) -> np.ndarray:
    """bool [N]: which projected points (pixels ``uv`` [N, 2], depths ``z`` [N]) lie on a surface seen in the view:
    at least :data:`SURFACE_NEIGHBOURS` other points within :data:`SURFACE_RADIUS` times the mean point
    ``spacing`` (pixels) lie within :data:`SURFACE_DEPTH` of its depth. An opaque object hides a region, which
    SfM samples with neighbouring points at neighbouring depths; points triangulated from what is seen through
    glass lie scattered in depth (refraction moves each one by its own amount) and hide nothing."""
    from scipy.spatial import cKDTree

    if len(uv) <= SURFACE_NEIGHBOURS:
        return np.zeros(len(uv), bool)
    tree = cKDTree(uv)
    pairs = tree.query_pairs(SURFACE_RADIUS * spacing, output_type="ndarray")
    if not len(pairs):
        return np.zeros(len(uv), bool)
    i, j = pairs[:, 0], pairs[:, 1]
    near_depth = np.abs(z[i] - z[j]) <= SURFACE_DEPTH * np.minimum(z[i], z[j])
    counts = np.bincount(i[near_depth], minlength=len(uv)) + np.bincount(j[near_depth], minlength=len(uv))
    return counts >= SURFACE_NEIGHBOURS


def _occluded(depth: np.ndarray, z: np.ndarray, step: float) -> np.ndarray:
    """Whether an opaque depth lies clearly in front of ``z`` (two voxels and 2% of the depth)."""
    with np.errstate(invalid="ignore"):  # inf - inf where neither has a depth: not hidden
        return depth < z - 2.0 * step - 0.02 * z


def _votes(points: np.ndarray, step: float, marked: list[tuple[ColmapView, np.ndarray]],
           xyz: np.ndarray) -> tuple[np.ndarray, ...]:
    """[views, N] bool: whether each marked view has the point in frame, whether it sees it inside its mask
    (dilated by half the voxels' footprint), and whether SfM points ``xyz`` hide it there."""
    inside = np.zeros((len(marked), len(points)), bool)
    seen = np.zeros((len(marked), len(points)), bool)
    hidden = np.zeros((len(marked), len(points)), bool)
    for k, (view, mask) in enumerate(marked):
        uv, z, front = project_points(view, points)
        if not front.any():
            continue
        half_voxel = 0.5 * focal(view) * step / np.median(z[front])  # pixels
        grown = _dilate(mask, int(np.round(half_voxel)))
        u = np.floor(uv[:, 0]).astype(np.int64)
        v = np.floor(uv[:, 1]).astype(np.int64)
        h, w = mask.shape
        visible = front & (u >= 0) & (u < w) & (v >= 0) & (v < h)
        seen[k] = visible
        inside[k, visible] = grown[v[visible], u[visible]]
        if len(xyz):
            depth = opaque_depth(view, xyz)
            hidden[k, visible] = _occluded(depth[v[visible], u[visible]], z[visible], step)
    return seen, inside, hidden


def _whole_in_frame(mask: np.ndarray) -> bool:
    """Whether the marked object lies inside the frame (its mask does not touch the image border)."""
    return not (mask[0].any() or mask[-1].any() or mask[:, 0].any() or mask[:, -1].any())


def _carve(points, step, marked, xyz) -> tuple[np.ndarray, np.ndarray]:
    """Voxels no marked view rules out, and [views, N] bool of "this view does not rule the voxel out". A view
    rules a voxel out when it has it in frame outside its mask with no SfM point of ``xyz`` in front, or when
    the voxel is out of frame (or behind) and the view's mask shows the whole object. A kept voxel is seen
    unhidden inside the masks of at least two views."""
    seen, inside, hidden = _votes(points, step, marked, xyz)
    whole = np.array([_whole_in_frame(mask) for _, mask in marked])
    agree = np.where(seen, inside | hidden, ~whole[:, None])
    keep = agree.all(0) & ((seen & inside & ~hidden).sum(0) >= min(2, len(marked)))
    return keep, agree


def scene_bound(model: ColmapModel, marked: list[tuple[ColmapView, np.ndarray]]) -> tuple[np.ndarray, np.ndarray]:
    """The box the hull is searched in: the 1st-99th percentile box of the SfM points grown by half its
    size, or without points a box of the median camera distance around the marked views' common look-at
    point."""
    centres = np.stack([v.center for v, _ in marked])
    if len(model.xyz) >= 20:
        lo, hi = np.percentile(model.xyz, 1, axis=0), np.percentile(model.xyz, 99, axis=0)
        pad = 0.5 * (hi - lo) + 1e-6
        return lo - pad, hi + pad
    dirs = np.stack([v.forward for v, _ in marked])
    A = sum(np.eye(3) - np.outer(d, d) for d in dirs)
    b = sum((np.eye(3) - np.outer(d, d)) @ c for d, c in zip(dirs, centres, strict=True))
    target = np.linalg.lstsq(A, b, rcond=None)[0]
    radius = float(np.median(np.linalg.norm(centres - target, axis=1)))
    return target - radius, target + radius


def _disagreeing(agree: np.ndarray, names: list[str]) -> tuple[list[str], int]:
    """The marked views that rule out the voxels most views keep, and how many views keep those."""
    votes = agree.sum(0)
    best = int(votes.max(initial=0))
    top = votes == best
    return [n for k, n in enumerate(names) if not agree[k, top].all()], best


def visual_hull(model: ColmapModel, marked: list[tuple[ColmapView, np.ndarray]], settings: MaskPropagationConfig,
                source: str = "") -> Hull:
    """The hull's boundary voxels (coarse pass over :func:`scene_bound`, fine pass over its box)."""
    from scipy import ndimage

    names = [v.name for v, _ in marked]
    lo, hi = scene_bound(model, marked)
    points, shape, step = _grid(lo, hi, COARSE_GRID)
    occluders = model.xyz if settings.occlusion else np.zeros((0, 3))
    keep, agree = _carve(points, step, marked, occluders)
    if not keep.any():
        views, best = _disagreeing(agree, names)
        raise PipelineError(
            f"the marked views' masks share no 3D region (at most {best} of {len(names)} marked views agree on a "
            f"point; views that disagree: {', '.join(views)})",
            path=source or None,
            fix="check those masks mark the same object (same polarity, the whole see-through surface), or "
            "remove them from the marked views",
        )
    part = points[keep]
    lo, hi = part.min(0) - 1.5 * step, part.max(0) + 1.5 * step
    points, shape, step = _grid(lo, hi, settings.grid)
    keep, _ = _carve(points, step, marked, occluders)
    occupied = keep.reshape(shape)
    labels, count = ndimage.label(occupied)
    if count > 1:
        sizes = np.bincount(labels.ravel())[1:]
        occupied = np.isin(labels, 1 + np.flatnonzero(sizes >= settings.min_part * sizes.max()))
    boundary = occupied & ~ndimage.binary_erosion(occupied)
    return Hull(points=points[boundary.ravel()], step=step, num_voxels=int(occupied.sum()))


# ----------------------------------------------------------------------------------------------
# per view


def project_hull(hull: Hull, view: ColmapView, scale: float = 1.0, occluders: np.ndarray | None = None) -> np.ndarray:
    """The hull's silhouette in ``view`` (bool, the view's size times ``scale``): every boundary voxel
    splatted as a disc of half its projected size, holes filled, then shrunk by the discs' median radius (the
    discs close the gaps between voxel centres without growing the outline past them); with ``occluders``
    (SfM points) the pixels where those lie clearly in front of the hull's nearest voxel are left out."""
    import cv2
    from scipy import ndimage

    h, w = int(round(view.height * scale)), int(round(view.width * scale))
    nearest = np.full((h, w), np.inf, np.float32)
    uv, z, front = project_points(view, hull.points)
    uv = uv * scale
    radius = np.zeros(len(z), np.int64)
    radius[front] = np.round(0.5 * focal(view) * scale * hull.step / z[front]).astype(np.int64)
    u = np.floor(uv[:, 0]).astype(np.int64)
    v = np.floor(uv[:, 1]).astype(np.int64)
    near = front & (u >= -radius) & (u < w + radius) & (v >= -radius) & (v < h + radius)
    if not near.any():
        return np.zeros((h, w), bool)
    for r in np.unique(radius[near]):
        sel = near & (radius == r)
        pad = int(r) + 1
        canvas = np.full((h + 2 * pad, w + 2 * pad), np.inf, np.float32)
        np.minimum.at(canvas, (v[sel] + pad, u[sel] + pad), z[sel].astype(np.float32))
        kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * int(r) + 1, 2 * int(r) + 1))
        nearest = np.minimum(nearest, cv2.erode(canvas, kernel)[pad:-pad, pad:-pad])
    covered = np.isfinite(nearest)
    out = ndimage.binary_fill_holes(covered)
    typical = int(np.median(radius[near]))
    if typical > 0:
        kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * typical + 1, 2 * typical + 1))
        out = cv2.erode(out.astype(np.uint8), kernel, borderType=cv2.BORDER_REPLICATE) > 0
    if occluders is None or not len(occluders) or not covered.any():
        return out
    nearest[out & ~covered] = np.median(nearest[covered])
    return out & ~_occluded(opaque_depth(view, occluders, scale), nearest, hull.step)


def _grabcut(image: np.ndarray, labels: np.ndarray, rect: tuple[int, int, int, int] | None,
             iterations: int) -> np.ndarray | None:
    """OpenCV GrabCut of ``image`` (float RGB [H, W, 3]), started from the seed ``labels`` [H, W] (uint8
    ``GC_*`` values) when ``rect`` is None, else from the rectangle ``rect`` (x, y, width, height; outside it
    is background); the foreground (sure or probable) as a bool [H, W] mask, or None when OpenCV refuses the
    seeds."""
    import cv2

    pixels = np.ascontiguousarray((np.clip(image[..., :3], 0, 1) * 255).astype(np.uint8)[..., ::-1])
    bgd, fgd = np.zeros((1, 65), np.float64), np.zeros((1, 65), np.float64)
    mode = cv2.GC_INIT_WITH_MASK if rect is None else cv2.GC_INIT_WITH_RECT
    try:
        cv2.grabCut(pixels, labels, rect, bgd, fgd, iterations, mode)
    except cv2.error:
        return None
    return (labels == cv2.GC_FGD) | (labels == cv2.GC_PR_FGD)


def _size(silhouette: np.ndarray) -> int | None:
    """The longest side of the silhouette's bounding box in pixels; None for a silhouette of under 16
    pixels (too small to refine)."""
    if int(silhouette.sum()) < 16:
        return None
    ys, xs = np.nonzero(silhouette)
    return int(max(ys.max() - ys.min(), xs.max() - xs.min())) + 1


def _frame(silhouette: np.ndarray, margin: int) -> tuple[slice, slice]:
    """The silhouette's bounding box grown by ``margin`` pixels on each side, within the image."""
    ys, xs = np.nonzero(silhouette)
    h, w = silhouette.shape
    return (slice(max(0, ys.min() - margin), min(h, ys.max() + margin + 1)),
            slice(max(0, xs.min() - margin), min(w, xs.max() + margin + 1)))


def refine_with_grabcut(image: np.ndarray, silhouette: np.ndarray,
                        settings: MaskPropagationConfig) -> np.ndarray | None:
    """GrabCut of ``image`` (float RGB [H, W, 3]) seeded by ``silhouette``: probable foreground inside, probable
    background in a ring around it, background beyond; None when the result keeps less than ``min_kept``."""
    import cv2

    size = _size(silhouette)
    if size is None:
        return None
    ring = max(3, int(round(settings.ring * size)))
    frame = _frame(silhouette, 2 * ring)
    crop = silhouette[frame]
    seeds = np.full(crop.shape, cv2.GC_BGD, np.uint8)
    seeds[_dilate(crop, ring)] = cv2.GC_PR_BGD
    seeds[crop] = cv2.GC_PR_FGD
    if not (seeds == cv2.GC_BGD).any():  # GrabCut needs background samples: the crop's border
        seeds[[0, -1], :] = cv2.GC_BGD
        seeds[:, [0, -1]] = cv2.GC_BGD
    foreground = _grabcut(image[frame], seeds, None, settings.grabcut_iterations)
    if foreground is None:
        return None
    cut = np.zeros_like(silhouette)
    cut[frame] = foreground
    if cut.sum() < settings.min_kept * silhouette.sum():
        return None
    return cut


def snap_to_edges(image: np.ndarray, silhouette: np.ndarray, settings: MaskPropagationConfig) -> np.ndarray | None:
    """``silhouette``'s outline moved to the strongest edges of ``image`` (float RGB [H, W, 3]) within a narrow
    band: OpenCV's watershed floods the image's colour gradient from two seeds, the silhouette eroded by
    ``snap_band`` of its size (the object) and everything beyond it dilated by one pixel (not the object), and
    each band pixel joins the seed it is reached from first (holes in the silhouette, where SfM points hide
    the object, seed the outside too). None when the eroded silhouette is empty (a
    silhouette thinner than the band) or the result keeps less than ``min_kept`` of it."""
    import cv2

    size = _size(silhouette)
    if size is None:
        return None
    band = max(1, int(round(settings.snap_band * size)))
    # a crop with room for outside seeds beyond the one-pixel frame that cv2.watershed sets aside as lines
    frame = _frame(silhouette, 4)
    crop = silhouette[frame].astype(np.uint8)
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * band + 1, 2 * band + 1))
    inside = cv2.erode(crop, kernel) > 0  # beyond the image counts as inside: its edge is no outline
    outside = ~(cv2.dilate(crop, np.ones((3, 3), np.uint8)) > 0)
    if not inside.any() or not outside.any():
        return None
    seeds = np.zeros(crop.shape, np.int32)
    seeds[outside] = 1
    seeds[inside] = 2
    pixels = np.ascontiguousarray((np.clip(image[frame][..., :3], 0, 1) * 255).astype(np.uint8)[..., ::-1])
    cv2.watershed(pixels, seeds)  # labels the band 1 or 2, the lines between basins -1
    cut = np.zeros_like(silhouette)
    cut[frame] = seeds == 2
    if cut.sum() < settings.min_kept * silhouette.sum():
        return None
    return cut


REFINERS = {"grabcut": refine_with_grabcut, "watershed": snap_to_edges}


def polygon_mask(points: np.ndarray, width: int, height: int) -> np.ndarray:
    """The inside of a polygon (corners [N, 2] in pixels with the image's corner at (0, 0), x to the right, y down)
    as a bool [height, width] mask; pixels its outline touches count as inside."""
    import cv2

    canvas = np.zeros((height, width), np.uint8)
    shift = 4  # sub-pixel corners: 1/16 pixel; OpenCV puts pixel centres on integer coordinates
    corners = np.round((np.asarray(points, np.float64) - 0.5) * (1 << shift)).astype(np.int32)
    cv2.fillPoly(canvas, [corners.reshape(-1, 1, 2)], 1, lineType=cv2.LINE_8, shift=shift)
    return canvas > 0


def box_mask(image: np.ndarray, box: tuple[float, float, float, float],
             settings: MaskPropagationConfig) -> tuple[np.ndarray, bool]:
    """The object inside a loose ``box`` (x0, y0, x1, y1 in pixels) of ``image`` (float RGB [H, W, 3]): OpenCV's
    GrabCut started from the rectangle (``GC_INIT_WITH_RECT``: outside is background, inside is unknown), at
    ``work_size`` pixels on the longest side. Returns (mask at the image's size, whether GrabCut's cut was kept):
    the filled box when GrabCut fails or keeps less than :data:`MIN_BOX_KEPT` of the box."""
    import cv2

    h, w = image.shape[:2]
    x0, y0, x1, y1 = box
    filled = polygon_mask(np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1]]), w, h)
    scale = min(1.0, settings.work_size / max(w, h))
    sw, sh = max(1, int(round(w * scale))), max(1, int(round(h * scale)))
    small = cv2.resize(image, (sw, sh), interpolation=cv2.INTER_AREA) if scale < 1.0 else image
    left, top = int(np.floor(x0 * scale)), int(np.floor(y0 * scale))
    right, bottom = min(sw, int(np.ceil(x1 * scale))), min(sh, int(np.ceil(y1 * scale)))
    rect = (left, top, right - left, bottom - top)
    if rect[2] < 3 or rect[3] < 3 or (rect[2] >= sw and rect[3] >= sh):  # too small, or no background left
        return filled, False
    foreground = _grabcut(small, np.zeros((sh, sw), np.uint8), rect, settings.grabcut_iterations)
    if foreground is None:
        return filled, False
    cut = _resize_mask(foreground, w, h) & filled
    if cut.sum() < MIN_BOX_KEPT * filled.sum():
        return filled, False
    return cut, True


def _resize_mask(mask: np.ndarray, width: int, height: int) -> np.ndarray:
    import cv2

    if mask.shape == (height, width):
        return mask
    return cv2.resize(mask.astype(np.float32), (width, height), interpolation=cv2.INTER_LINEAR) >= 0.5


@dataclass
class Carrier:
    """How the marks reach the other views: ``method`` (``hull`` | ``plane``), why it was chosen, the marked views
    (view, mask) and ``carry(marked, view, scale)``, the silhouette in ``view`` (bool, its size times ``scale``)
    of some marked views (the refinement's choice leaves each out in turn), None where they bound nothing;
    ``plane`` is the fitted plane of method ``plane``, ``panes`` the marks' panes, each with its plane
    (:mod:`rtsplat.masks.panes`)."""

    method: str
    reason: str
    marked: list[tuple[ColmapView, np.ndarray]]
    carry: Callable[[list[tuple[ColmapView, np.ndarray]], ColmapView, float], np.ndarray | None]
    plane: GlassPlane | None = None
    panes: list[Pane] = field(default_factory=list)

    def silhouette(self, view: ColmapView, scale: float = 1.0) -> np.ndarray:
        """The silhouette of every marked view in ``view``."""
        return self.carry(self.marked, view, scale)

    def record(self) -> dict:
        """The choice as the masks summary records it."""
        return {"method": self.method, "reason": self.reason,
                "plane": self.plane.record() if self.plane is not None else None,
                "panes": [pane.record() for pane in self.panes] if len(self.panes) > 1 else []}


def _names(marked: list[tuple[ColmapView, np.ndarray]]) -> tuple[str, ...]:
    return tuple(v.name for v, _ in marked)


def _hull_carrier(model: ColmapModel, marked: list[tuple[ColmapView, np.ndarray]], settings: MaskPropagationConfig,
                  reason: str, source: str) -> Carrier:
    """The visual hull's :class:`Carrier` (the hull of ``marked`` carved at once, which refuses marks that share
    no 3D region; the hull of fewer marked views when asked for)."""
    occluders = model.xyz if settings.occlusion else None
    hulls = {_names(marked): visual_hull(model, marked, settings, source)}

    def carry(views, view, scale):
        if _names(views) not in hulls:
            try:
                hulls[_names(views)] = visual_hull(model, views, settings)
            except PipelineError:
                hulls[_names(views)] = None
        hull = hulls[_names(views)]
        return None if hull is None else project_hull(hull, view, scale, occluders)

    return Carrier("hull", reason, marked, carry)


def _plane_carrier(model: ColmapModel, marked: list[tuple[ColmapView, np.ndarray]], settings: MaskPropagationConfig,
                   why: str, refine: bool = True) -> Carrier:
    """The glass plane's :class:`Carrier` (``why`` says why the plane was chosen; ``refine``: whether the plane
    may be moved to where the marks agree, :func:`rtsplat.masks.plane.glass_plane`);
    :class:`rtsplat.masks.plane.PlaneFitError` when no plane fits."""
    from rtsplat.masks.panes import cast_panes, glass_panes, panes_text
    from rtsplat.masks.plane import glass_plane

    scale = min(1.0, AGREEMENT_SIZE / max(max(v.width, v.height) for v, _ in marked))
    plane = glass_plane(model.xyz, marked, settings.plane_band, scale, refine=refine, agree=False)
    panes = glass_panes(model.xyz, marked, plane, settings.plane_band, scale)
    occluders = model.xyz if settings.occlusion else None
    placed = "placed where the marks agree best near the plane of" if plane.refined else "fitted to"
    reason = (f"{why}: the marks are cast through the glass's plane, {placed} the SfM points on their outlines "
              f"({plane.inliers} of {plane.outline_points} within 1% of their depth of it, RMS residual "
              f"{plane.relative_residual:.2%}; the marked views agree through it at mean IoU {plane.agreement:.2f})"
              f"{panes_text(panes)}")
    return Carrier("plane", reason, marked,
                   lambda views, view, scale: cast_panes(panes, views, view, scale, occluders), plane, panes)


def _left_out(carrier: Carrier, settings: MaskPropagationConfig) -> Iterator[tuple[ColmapView, np.ndarray, np.ndarray]]:
    """Each marked view in turn left out: (view, its mask, its silhouette carried from the others), both at the
    work size; views the others bound nothing in are skipped."""
    for k, (view, mask) in enumerate(carrier.marked):
        silhouette = carrier.carry(carrier.marked[:k] + carrier.marked[k + 1:], view, _work_scale(view, settings))
        if silhouette is not None and silhouette.any():
            yield view, _resize_mask(mask, *silhouette.shape[::-1]), silhouette


def _left_out_iou(carrier: Carrier, settings: MaskPropagationConfig) -> float:
    """The mean IoU of each marked view's mask and its silhouette carried from the others (0 when none is)."""
    scores = [_iou(silhouette, truth) for _, truth, silhouette in _left_out(carrier, settings)]
    return float(np.mean(scores)) if scores else 0.0


def _other_sides(model: ColmapModel, marked: dict[str, np.ndarray]) -> str:
    """What to mark so that a visual hull bounds the object: views to add, named where the capture has some that
    look from other sides."""
    views = {v.name: v for v in model.views}
    others = suggest_views(model, 2, tuple(marked))
    if others and direction_spread([views[n] for n in [*marked, *others] if n in views]) >= ONE_SIDE_DEGREES:
        return "mark views from other sides too, e.g. " + ", ".join(others)
    return "photograph the object from other sides too and mark some of those views"


def carry_marks(model: ColmapModel, marked: dict[str, np.ndarray], settings: MaskPropagationConfig,
                source: str = "") -> Carrier:
    """The :class:`Carrier` of ``masks.propagate.method`` for the ``marked`` photos' masks (checked by
    :func:`check_marked`). ``auto``: the glass's plane (:func:`rtsplat.masks.plane.glass_plane`) when the marked
    views' directions differ by less than :data:`ONE_SIDE_DEGREES` (a hull of them is unbounded in depth); else
    the visual hull, or the plane where one fits (as the SfM points propose it) and it carries each marked view's
    mask from the others better (mean IoU). Raises :class:`PipelineError` when the chosen one bounds nothing: a
    hull of views from one side, marks that share no 3D region, or no plane on which the marks agree."""
    from rtsplat.masks.plane import PlaneFitError

    check_marked(model, marked, source)
    views = {v.name: v for v in model.views}
    marked_views = [(views[n], marked[n]) for n in sorted(marked)]
    spread = direction_spread([v for v, _ in marked_views])
    one_side = f"the marked views look from one side (their directions differ by at most {spread:.1f} degrees)"
    if spread < ONE_SIDE_DEGREES and settings.method == "hull":
        raise PipelineError(
            f"{one_side}: the object's depth is not bounded", path=source or None,
            fix=f"{_other_sides(model, marked)}, or, for flat glass, set masks.propagate.method: plane (or auto)",
        )
    if spread < ONE_SIDE_DEGREES or settings.method == "plane":
        why = one_side if settings.method == "auto" else "masks.propagate.method is plane"
        try:
            return _plane_carrier(model, marked_views, settings, why)
        except PlaneFitError as err:
            raise PipelineError(
                f"{why}, and {err}", path=source or None,
                fix="draw each mark on the glass's own edges, with its frame or the wall around it in view (SfM "
                f"points there give the plane), or {_other_sides(model, marked)}",
            ) from None
    around = f"the marked views' directions differ by up to {spread:.1f} degrees"
    hull = _hull_carrier(model, marked_views, settings, f"{around}: their visual hull bounds the object", source)
    if settings.method == "hull":
        return hull
    try:  # the plane as the SfM points propose it: left-out marks judge a looser hull, which favours a moved plane
        plane = _plane_carrier(model, marked_views, settings, around, refine=False)
    except PlaneFitError as err:
        hull.reason += f" (no plane: {err})"
        return hull
    scores = {carrier.method: _left_out_iou(carrier, settings) for carrier in (hull, plane)}
    chosen = plane if scores["plane"] > scores["hull"] else hull
    chosen.reason += (f"; each marked view left out, the others carry its mask at mean IoU {scores['hull']:.2f} "
                      f"through the hull, {scores['plane']:.2f} through the plane")
    return chosen


def propagate_masks(
    model: ColmapModel,
    marked: dict[str, np.ndarray],
    names: list[str],
    read_image: Callable[[str], np.ndarray],
    settings: MaskPropagationConfig | None = None,
    size_of: Callable[[str], tuple[int, int]] | None = None,
    source: str = "",
    segment: Callable[[np.ndarray, tuple[float, float, float, float]], np.ndarray] | None = None,
    carrier: Carrier | None = None,
) -> Iterator[PropagatedMask]:
    """One mask per photo in ``names`` (in that order) from the masks of the ``marked`` photos (bool [H, W]
    at the photo's size), with the registered views of ``model``. ``read_image(name)`` gives a photo as float
    RGB; ``size_of(name)`` (width, height) is asked for photos SfM did not register (empty masks). Raises
    :class:`PipelineError` for too few marked views, marked views without a pose, masks of another size than
    the camera, and marks that bound nothing (:func:`carry_marks`, unless ``carrier`` gives its answer);
    ``source`` names the mask folder in those messages.
    ``segment(image, box)`` (a prompted segmenter: float RGB image, box x0, y0, x1, y1 in its pixels -> bool mask)
    replaces the refinement: each view's mask is its answer to the projected hull's bounding box, or the
    projection where it finds nothing."""
    settings = settings or MaskPropagationConfig()
    views = {v.name: v for v in model.views}
    carrier = carrier or carry_marks(model, marked, settings, source)
    refine = "onnx" if segment is not None else settings.refine
    if refine == "onnx" and segment is None:
        raise PipelineError("masks.propagate.refine is onnx but no segmenter is given", path=source or None,
                            fix="set masks.onnx.model (and encoder), or masks.propagate.refine: auto")
    if refine == "auto":
        refine = choose_refinement(carrier, read_image, settings)
    for name in names:
        if name in marked:
            yield PropagatedMask(name, marked[name], "given")
            continue
        view = views.get(name)
        if view is None:
            w, h = size_of(name) if size_of else (1, 1)
            yield PropagatedMask(name, np.zeros((h, w), bool), "unregistered")
            continue
        scale = _work_scale(view, settings)
        silhouette = carrier.silhouette(view, scale)
        if not silhouette.any():
            yield PropagatedMask(name, np.zeros((view.height, view.width), bool), "empty")
            continue
        refined = None
        if refine in REFINERS:
            refined = REFINERS[refine](_work_image(read_image, view, silhouette.shape), silhouette, settings)
        elif refine == "onnx":
            refined = prompted_mask(segment, read_image(name), silhouette, scale)
        mask = silhouette if refined is None else refined
        yield PropagatedMask(name, _resize_mask(mask, view.width, view.height), "propagated",
                             "" if refined is None else refine)


def silhouette_box(silhouette: np.ndarray, scale: float = 1.0) -> tuple[float, float, float, float]:
    """The bounding box (x0, y0, x1, y1, pixel edges) of a non-empty mask at ``scale`` of the photo, in the
    photo's pixels."""
    ys, xs = np.nonzero(silhouette)
    return (xs.min() / scale, ys.min() / scale, (xs.max() + 1) / scale, (ys.max() + 1) / scale)


def prompted_mask(segment: Callable[[np.ndarray, tuple[float, float, float, float]], np.ndarray], image: np.ndarray,
                  silhouette: np.ndarray, scale: float) -> np.ndarray | None:
    """``segment``'s mask of ``image`` prompted by the box of ``silhouette`` (at ``scale`` of the image), at the
    silhouette's size; None when it finds nothing."""
    mask = np.asarray(segment(image, silhouette_box(silhouette, scale)), bool)
    if not mask.any():
        return None
    return _resize_mask(mask, *silhouette.shape[::-1])


def _iou(a: np.ndarray, b: np.ndarray) -> float:
    union = int((a | b).sum())
    return 1.0 if union == 0 else float((a & b).sum()) / union


def _work_scale(view: ColmapView, settings: MaskPropagationConfig) -> float:
    return min(1.0, settings.work_size / max(view.width, view.height))


def _work_image(read_image: Callable[[str], np.ndarray], view: ColmapView, shape: tuple[int, int]) -> np.ndarray:
    import cv2

    image = read_image(view.name)
    if image.shape[:2] != shape:
        image = cv2.resize(image, shape[::-1], interpolation=cv2.INTER_AREA)
    return image


def choose_refinement(carrier: Carrier, read_image: Callable[[str], np.ndarray],
                      settings: MaskPropagationConfig) -> str:
    """``grabcut``, ``watershed`` or ``none``, whichever matches the marked masks best when each marked view in
    turn is left out and its mask is carried from the others (mean IoU; ties keep the projection, then the order
    of :data:`REFINERS`). The hull of one view fewer is looser, which favours the refinements slightly."""
    scores = {"none": [], **{refine: [] for refine in REFINERS}}
    for view, truth, silhouette in _left_out(carrier, settings):
        image = _work_image(read_image, view, silhouette.shape)
        scores["none"].append(_iou(silhouette, truth))
        for refine, refiner in REFINERS.items():
            cut = refiner(image, silhouette, settings)
            scores[refine].append(_iou(silhouette if cut is None else cut, truth))
    if not scores["none"]:
        return "none"
    means = {refine: float(np.mean(values)) for refine, values in scores.items()}
    return max(means, key=lambda refine: (means[refine], refine == "none"))


def check_marked(model: ColmapModel, marked: dict[str, np.ndarray], source: str = "") -> None:
    """Refuse fewer than :data:`MIN_MARKED` marked views (suggesting views to mark), marked views SfM did not
    register, masks whose size is not the camera's, and empty masks."""
    views = {v.name: v for v in model.views}
    if len(marked) < MIN_MARKED:
        suggestion = suggest_views(model, 5 - len(marked), exclude=tuple(n for n in marked if n in views))
        raise PipelineError(
            f"{len(marked)} marked view(s) ({', '.join(sorted(marked)) or 'none'}); propagating masks needs at "
            f"least {MIN_MARKED}, spread around the object",
            path=source or None,
            fix=f"add masks for {', '.join(suggestion)} (views spread around the capture), or give every photo a "
            "mask (masks.source: ingest)",
        )
    missing = sorted(n for n in marked if n not in views)
    if missing:
        others = suggest_views(model, len(missing), exclude=tuple(n for n in marked if n in views))
        raise PipelineError(
            f"marked view(s) without a camera pose (SfM did not register them): {', '.join(missing)}",
            path=source or None,
            fix=f"mark registered views instead, e.g. {', '.join(others)}, or make SfM register those photos",
        )
    for name in sorted(marked):
        view, mask = views[name], marked[name]
        if mask.shape != (view.height, view.width):
            raise PipelineError(
                f"the mask of {name} is {mask.shape[1]}x{mask.shape[0]} but its camera is {view.width}x{view.height}",
                path=source or None,
                fix="export the mask at the photo's resolution",
            )
        if not mask.any():
            raise PipelineError(
                f"the mask of marked view {name} is empty", path=source or None,
                fix="mark the see-through surface in white, or remove the empty mask",
            )


def direction_spread(views: list[ColmapView]) -> float:
    """The largest angle between two views' directions, in degrees."""
    dirs = np.stack([v.forward for v in views])
    return float(np.degrees(np.arccos(np.clip(dirs @ dirs.T, -1.0, 1.0))).max())
