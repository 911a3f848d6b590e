"""``rtsplat prepare``: turn a scene (images + COLMAP model + masks) into the trainer's prepared scene.

Steps (function API :func:`prepare_scene`):

1. read the SfM result (``rtsplat sfm`` output: its ``summary.json`` says where the model and the
   images it belongs to are) and match model views to image files by name;
2. downsample images by an integer factor with an area (box) filter, or take ``images_<factor>/``
   when the dataset has it, and scale the intrinsics exactly (see :func:`rtsplat.io.images.area_downsample`);
   the factor is ``prepare.downsample``, or, when ``prepare.resolution`` is set, the smallest one that
   brings the images' longest side to at most that many pixels (:func:`downsample_factor`);
3. downsample the transparent masks the same way and binarise them;
4. define the spherical region of interest: from the config; on a scene with transparent masks, the
   sphere around the masks' visual hull (:func:`roi_from_masks`, the see-through object and what it
   encloses); otherwise estimated from the SfM points and the point the cameras look at
   (:func:`estimate_roi`); saved with its source. A masks' sphere that misses the masked rays gives way to
   the estimated one (:func:`checked_mask_roi`), and ``scene.json`` records why (``roi_warning``). The
   hull is carved with each propagated mask (``masks.source: propagate``) less its outline pixels
   (:func:`hull_mask`);
5. split train/test: every ``test_every``-th image of the name-sorted list is a test view;
6. on a scene with masks, the points of the masks' visual hull that face the cameras, with their
   normals (:func:`hull_surface`, ``transparent_surface.npz``): where the see-through surface is,
   which the SfM points miss (glass has no features of its own);
7. write ``prepared/`` atomically (see :mod:`rtsplat.scene` for the format), with the content
   fingerprints of what it was made from (``inputs`` in ``scene.json``: the photos, the SfM model, the
   masks folder; :mod:`rtsplat.io.manifest`).

Before anything is read, the SfM and masks outputs must belong to the scene's photos: each records the
fingerprint of the photos it was made from, and one made from other photos is refused, naming both.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from rtsplat import __version__
from rtsplat.config import PrepareConfig, add_config_arguments, stage_config_from_args
from rtsplat.errors import PipelineError
from rtsplat.io.colmap import ColmapModel, ColmapView, load_model
from rtsplat.io.images import (
    area_downsample,
    linear_to_srgb,
    read_header,
    read_image,
    read_mask,
    write_mask,
    write_png,
)
from rtsplat.io.manifest import check_made_from_photos, folder_fingerprint, photo_fingerprints, photos_fingerprint
from rtsplat.io.outputs import check_output_dir, output_dir
from rtsplat.io.ply import write_points_ply
from rtsplat.pose_eval import camera_center
from rtsplat.scene import (
    GT_LAYERS_DIR,
    IMAGES_DIR,
    MASKS_DIR,
    POINTS_FILE,
    REFLECTION_REACH_FILE,
    TRANSPARENT_SURFACE_FILE,
    CameraRecord,
    PreparedScene,
    Roi,
)

if TYPE_CHECKING:
    from rtsplat.model.appearance import GainEstimate


@dataclass
class PrepareSummary:
    num_train: int
    num_test: int
    width: int
    height: int
    downsample: int
    roi: Roi
    has_transparency: bool
    mask_coverage: float
    num_points: int
    used_prescaled: bool
    gt_layer_views: int = 0  # test views with ground-truth layers (synthetic scenes)
    resolution: int | None = None  # the requested longest side (prepare.resolution), when it chose the factor
    downsample_reason: str = ""  # how the factor was chosen, in words
    roi_warning: str = ""  # why the masks' region of interest was not used (checked_mask_roi), in words


def load_stage_summary(directory: str | Path, stage: str) -> dict:
    path = Path(directory) / "summary.json"
    if not path.is_file():
        raise PipelineError(
            f"no {stage} result here (summary.json missing)",
            path=directory,
            fix=f"run 'rtsplat {stage}' for this scene first",
        )
    return json.loads(path.read_text())


def estimate_roi(model: ColmapModel, percentile: float = 95.0) -> Roi:
    """Sphere around what the cameras look at.

    The centre is the least-squares point closest to all optical axes (the common look-at point);
    when the axes are (nearly) parallel it falls back to the median SfM point. The radius covers
    ``percentile`` % of the SfM points; without points it is half the median camera distance.
    """
    centers = np.stack([v.center for v in model.views])
    dirs = np.stack([v.forward for v in model.views])
    A = np.zeros((3, 3))
    b = np.zeros(3)
    for c, d in zip(centers, dirs, strict=True):
        P = np.eye(3) - np.outer(d, d)
        A += P
        b += P @ c
    eig = np.linalg.eigvalsh(A)
    if len(model.views) >= 2 and eig[0] > 1e-3 * eig[-1]:
        center = np.linalg.solve(A, b)
    elif len(model.xyz):
        center = np.median(model.xyz, axis=0)
    else:
        raise PipelineError(
            "cannot estimate a region of interest: parallel cameras and no SfM points",
            fix="set prepare.roi {center, radius} in the config",
        )
    if len(model.xyz) >= 8:
        radius = float(np.percentile(np.linalg.norm(model.xyz - center, axis=1), percentile))
    else:
        radius = 0.5 * float(np.median(np.linalg.norm(centers - center, axis=1)))
    if not radius > 0:
        radius = 1.0
    return Roi(center=[float(x) for x in center], radius=radius, source="estimated")


@dataclass
class MaskHull:
    """The visual hull of the transparent masks on a regular grid (:func:`mask_hull`)."""

    points: np.ndarray  # [g^3, 3] grid points, C order of ``inside``
    inside: np.ndarray  # [g, g, g] bool: the largest connected part of the hull
    step: float  # grid spacing


def mask_hull(
    views: list[tuple[np.ndarray, np.ndarray, np.ndarray]],
    bound: Roi,
    agreement: float = 0.9,
    grid: int = 96,
    min_seen: float = 0.25,
) -> MaskHull | None:
    """The visual hull of the transparent masks inside the sphere ``bound``, or None when it is empty.

    ``views``: (K [3,3], world_to_camera [4,4], mask [H,W] bool) per view. A grid point (``grid`` per
    axis) belongs to the hull when at least ``min_seen`` of the views have it in frame and, of those,
    at least ``agreement`` see it inside the mask (the margin forgives a few wrong masks). Only the
    largest connected part is kept, so a stray point far away (seen through the glass from the few
    views that agree) cannot count.
    """
    from scipy import ndimage

    center = np.asarray(bound.center, dtype=np.float64)
    axis = np.linspace(-bound.radius, bound.radius, grid)
    points = np.stack(np.meshgrid(axis, axis, axis, indexing="ij"), -1).reshape(-1, 3) + center
    in_frame, inside_mask = _mask_votes(views, points)
    hull = (in_frame >= min_seen * len(views)) & (inside_mask >= agreement * np.maximum(in_frame, 1))
    labels, count = ndimage.label(hull.reshape(grid, grid, grid))
    if count == 0:
        return None
    sizes = np.bincount(labels.ravel())[1:]
    return MaskHull(points=points, inside=labels == 1 + int(np.argmax(sizes)), step=float(axis[1] - axis[0]))


def _mask_votes(views, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per point: how many views have it in frame (in front of the camera), and how many of those
    see it inside their mask."""
    in_frame = np.zeros(len(points))
    inside_mask = np.zeros(len(points))
    for K, world_to_camera, mask in views:
        cam = points @ world_to_camera[:3, :3].T + world_to_camera[:3, 3]
        z = cam[:, 2]
        front = z > 1e-6
        uv = cam[:, :2] / np.where(front, z, 1.0)[:, None] * np.diag(K)[:2] + K[:2, 2]
        u = np.floor(uv[:, 0]).astype(np.int64)
        v = np.floor(uv[:, 1]).astype(np.int64)
        h, w = mask.shape
        visible = front & (u >= 0) & (u < w) & (v >= 0) & (v < h)
        in_frame += visible
        inside_mask[visible] += mask[v[visible], u[visible]]
    return in_frame, inside_mask


def hull_mask(mask: np.ndarray, propagated: bool) -> np.ndarray:
    """The mask a view carves the visual hull with (:func:`mask_hull`, the region of interest and the
    seeded see-through surface): a propagated mask (``masks.source: propagate``, the marked views' hull
    projected) less its outline pixels, a drawn one as it is.

    A visual hull holds the object, so its projection holds the object's silhouette: a propagated outline
    errs outwards, about a pixel of the prepared image where the marked views' cones are tangent to the
    object and more between them (docs/benchmarks.md, "Training on propagated masks"). Carved with those
    outlines the hull, and the glass seeded on it, would stand that far off the glass all round. A mask
    refined on its photo loses its outline too: glass seeded a little inside the true surface trains
    better than glass seeded a little outside it (the same benchmark)."""
    if not propagated:
        return mask
    from scipy import ndimage

    return ndimage.binary_erosion(mask)


def roi_around(hull: MaskHull) -> Roi:
    """The sphere centred on the hull's bounding box that reaches 10% and one grid step beyond its
    farthest point: the agreement rule erodes the hull at the silhouettes, where one view's mask
    edge decides."""
    part = hull.points[hull.inside.ravel()]
    mid = 0.5 * (part.min(0) + part.max(0))
    radius = 1.1 * float(np.linalg.norm(part - mid, axis=1).max()) + hull.step
    return Roi(center=[float(x) for x in mid], radius=radius, source="masks")


def roi_from_masks(
    views: list[tuple[np.ndarray, np.ndarray, np.ndarray]], bound: Roi, agreement: float = 0.9, grid: int = 96
) -> Roi | None:
    """Sphere around the visual hull of the transparent masks (:func:`mask_hull`, :func:`roi_around`),
    or None when the masks carve nothing."""
    hull = mask_hull(views, bound, agreement, grid)
    return None if hull is None else roi_around(hull)


MIN_MASK_RAYS_IN_ROI = 0.5  # median share of see-through pixels whose ray must meet a masks' region of interest


def mask_rays_in_roi(roi: Roi, views: list[tuple[np.ndarray, np.ndarray, np.ndarray]]) -> float:
    """The median, over the views with a see-through pixel, of the share of those pixels whose ray (through
    the pixel centre, :func:`rtsplat.camera.pixel_rays`) meets the sphere ``roi`` in front of the camera.

    A region of interest around the glass meets nearly all of them. Glass set in an opaque body (a car's
    windows) can leave its visual hull without the part inside the body, since each view sees the body
    where another sees through a window; the largest part left can then lie away from the glass, and a
    region of interest around it meets none of the masked rays."""
    import torch

    from rtsplat.camera import PIXEL_CENTER_OFFSET, Camera, pixel_rays

    center = torch.as_tensor(roi.center, dtype=torch.float64)
    shares = []
    for K, world_to_camera, mask in views:
        v, u = np.nonzero(mask)
        if len(u) == 0:
            continue
        camera = Camera(torch.as_tensor(K, dtype=torch.float64), torch.as_tensor(world_to_camera, dtype=torch.float64),
                        mask.shape[1], mask.shape[0])
        origin, dirs = pixel_rays(camera, torch.as_tensor(u + PIXEL_CENTER_OFFSET),
                                  torch.as_tensor(v + PIXEL_CENTER_OFFSET))
        to_center = center - origin
        along = dirs @ to_center
        miss2 = float(to_center @ to_center) - along**2
        shares.append(float(((miss2 <= roi.radius**2) & (along > 0)).double().mean()))
    return float(np.median(shares)) if shares else 0.0


def checked_mask_roi(mask_roi: Roi | None, fallback: Roi,
                     views: list[tuple[np.ndarray, np.ndarray, np.ndarray]]) -> tuple[Roi, str]:
    """The masks' region of interest when its sphere meets the masked rays (:func:`mask_rays_in_roi`), else
    ``fallback``; with a warning in words when it fell back, else ''."""
    if mask_roi is None:
        return fallback, ""
    share = mask_rays_in_roi(mask_roi, views)
    if share >= MIN_MASK_RAYS_IN_ROI:
        return mask_roi, ""
    return fallback, (f"the masks' visual hull lies away from the glass (its sphere meets {100 * share:.0f}% of the "
                      f"see-through pixels' rays in the median view, needs {100 * MIN_MASK_RAYS_IN_ROI:.0f}%): the "
                      f"region of interest is the {fallback.source} one instead; set prepare.roi to place it")


def hull_surface(
    hull: MaskHull,
    views: list[tuple[np.ndarray, np.ndarray, np.ndarray]],
    min_facing: float = 0.25,
    neighbours: int = 64,
) -> tuple[np.ndarray, np.ndarray]:
    """Points on the hull's boundary that face the cameras, with their outward normals.

    The boundary is the hull's grid points with a neighbour outside; outward is the direction in which
    the smoothed hull indicator falls. A point is kept when at least ``min_facing`` of the views that
    have it in frame lie on its outward side, so the faces no camera looks at (the underside that the
    carving cannot close) are dropped. The normal of a kept point is the least-spread axis of the
    ``neighbours`` nearest kept points (:func:`rtsplat.model.surfels.point_cloud_normals`, a plane fitted
    over about 4.5 grid steps for 64), turned outward: the grid's staircase bends the indicator's
    gradient by several degrees, the fitted plane averages it out. For a see-through object the facing
    boundary is where its surface is: the dome of a glass case, the panes of a window.
    """
    import torch
    from scipy import ndimage

    from rtsplat.model.surfels import point_cloud_normals

    inside = hull.inside
    boundary = inside & ~ndimage.binary_erosion(inside)
    smooth = ndimage.gaussian_filter(inside.astype(np.float64), 1.0)
    gradient = np.stack(np.gradient(smooth, hull.step), -1).reshape(-1, 3)
    idx = np.flatnonzero(boundary.ravel())
    points = hull.points[idx]
    outward = -gradient[idx]
    facing = np.zeros(len(points))
    in_frame, _ = _mask_votes(views, points)
    for _, world_to_camera, _ in views:
        facing += ((camera_center(world_to_camera) - points) * outward).sum(1) > 0
    keep = (in_frame > 0) & (facing >= min_facing * len(views))
    points, outward = points[keep], outward[keep]
    if len(points) < 3:
        return points, outward / np.maximum(np.linalg.norm(outward, axis=1, keepdims=True), 1e-12)
    normals = point_cloud_normals(torch.from_numpy(points), k=neighbours).numpy()
    return points, normals * np.where((normals * outward).sum(1) < 0, -1.0, 1.0)[:, None]


def undistort_mask(mask: np.ndarray, distorted: ColmapView, size: tuple[int, int]) -> np.ndarray:
    """Warp a mask of a distorted image exactly like ``rtsplat sfm`` undistorted the image."""
    import pycolmap

    cam = pycolmap.Camera.create_from_model_name(1, distorted.model, 1.0, distorted.width, distorted.height)
    cam.params = distorted.params.tolist()
    bitmap = pycolmap.Bitmap.from_array(np.ascontiguousarray(mask.astype(np.uint8) * 255))
    out, _ = pycolmap.undistort_image(pycolmap.UndistortCameraOptions(), bitmap, cam)
    arr = np.asarray(out.to_array())
    arr = arr[..., 0] if arr.ndim == 3 else arr
    if arr.shape != (size[1], size[0]):
        raise PipelineError(
            f"undistorted mask is {arr.shape[1]}x{arr.shape[0]}, the undistorted image {size[0]}x{size[1]}",
            fix="re-run 'rtsplat sfm' (the undistorted model and the distorted one do not match)",
        )
    return arr >= 128


def ground_truth_layers(linear_npz: Path, image: np.ndarray, factor: int) -> dict[str, np.ndarray] | None:
    """Ground-truth reflection/transmission of a synthetic view in the prepared image's space.

    The synth writes linear-RGB layers at full resolution (``layers/linear/<stem>.npz``). The model adds
    its layers in the display space of the training images, so the truth is brought there too:
    transmission = sRGB of the area-downsampled linear transmission (the scene behind the glass,
    scatter included), reflection = prepared image - transmission (clipped at 0), so that the two add
    up to the training target. None when the layers do not match the image size.
    """
    with np.load(linear_npz) as z:
        transmission = area_downsample(z["transmission"].astype(np.float32), factor)
    if transmission.shape != image.shape:
        return None
    transmission = linear_to_srgb(transmission)
    return {"reflection": np.clip(image - transmission, 0.0, 1.0), "transmission": transmission}


def downsample_factor(sizes: set[tuple[int, int]], cfg: PrepareConfig, images: Path) -> tuple[int, str]:
    """The integer downsample factor for images of ``sizes`` ((width, height) pairs) and how it was chosen.

    With ``cfg.resolution`` set: the smallest factor after which the longest side is at most that many
    pixels (area downsampling crops to a multiple of the factor, so the side becomes ``side // factor``);
    1 when the images are that small already. Otherwise ``cfg.downsample``. A factor larger than the
    images' shorter side (nothing would be left) raises :class:`PipelineError` naming the size.
    """
    longest = max(max(size) for size in sizes)
    shortest = min(min(size) for size in sizes)
    size_text = " and ".join(f"{w}x{h}" for w, h in sorted(sizes))
    if cfg.resolution is not None:
        target = int(cfg.resolution)
        factor = longest // (target + 1) + 1
        if factor == 1:
            why = f"prepare.resolution {target} is not smaller than the images ({size_text}): factor 1, full size"
        else:
            why = (f"factor {factor} for prepare.resolution {target}: the smallest that takes the longest side "
                   f"{longest} to at most {target} ({longest // factor})")
        if factor > shortest:
            raise PipelineError(
                f"prepare.resolution {target} is too small for the images ({size_text}): it needs the factor "
                f"{factor}, more than their shorter side {shortest}",
                path=images,
                fix=f"set prepare.resolution to at least {longest // shortest}",
            )
        return factor, why
    factor = int(cfg.downsample)
    if factor > shortest:
        raise PipelineError(
            f"prepare.downsample {factor} is larger than the images ({size_text}): not one pixel would be left",
            path=images,
            fix=f"set prepare.downsample to at most {shortest} (the images' shorter side), or set "
            "prepare.resolution to the longest side you want in pixels",
        )
    return factor, f"prepare.downsample {factor}"


def _exposure(image: np.ndarray, observed: tuple[np.ndarray, np.ndarray] | None, size: tuple[int, int],
              mask: np.ndarray | None) -> GainEstimate:
    """The photo's log gain per channel against the SfM points it observed (the colour at each of its
    keypoints that SfM tied to a 3D point, against that point's colour: its mean over every photo that saw
    it), off the transparent mask, with how many observations it used and its standard error; no gain with
    too few observations (:func:`rtsplat.model.appearance.observed_log_gain`). ``image`` may be smaller than
    the camera's ``size`` (pre-scaled): the keypoints are scaled to it."""
    import torch

    from rtsplat.model.appearance import GainEstimate, observed_log_gain

    if observed is None or len(observed[0]) == 0:
        return GainEstimate(None, 0)
    xy, rgb = observed
    h, w = image.shape[:2]
    u = np.clip((xy[:, 0] * w / size[0]).astype(np.int64), 0, w - 1)
    v = np.clip((xy[:, 1] * h / size[1]).astype(np.int64), 0, h - 1)
    keep = np.ones(len(u), dtype=bool)
    if mask is not None:  # the mask has the camera's size
        row = np.clip(xy[:, 1].astype(np.int64), 0, mask.shape[0] - 1)
        keep = ~mask[row, np.clip(xy[:, 0].astype(np.int64), 0, mask.shape[1] - 1)].astype(bool)
    return observed_log_gain(torch.as_tensor(image[v[keep], u[keep]], dtype=torch.float32),
                             torch.as_tensor(rgb[keep], dtype=torch.float32) / 255)


def _dataset_reflection_reach(scene_dir: Path) -> dict | None:
    """What a synthetic dataset's glass reflects (``reflection_reach`` of its ``scene.json``, written by
    ``rtsplat synth``), or None for other datasets."""
    description = scene_dir / "scene.json"
    try:
        reach = json.loads(description.read_text()).get("reflection_reach") if description.is_file() else None
    except (OSError, ValueError, AttributeError):
        return None  # not a synth description: nothing to carry
    return reach if isinstance(reach, dict) else None


def _test_split(names: list[str], test_every: int) -> dict[str, str]:
    return {n: ("test" if i % test_every == 0 else "train") for i, n in enumerate(sorted(names))}


@dataclass
class _Inputs:
    """What prepare reads and checks before it writes anything (:func:`_read_inputs`)."""

    sfm: dict  # the summary.json of rtsplat sfm
    masks: dict  # the summary.json of rtsplat masks; {"has_masks": False} without a masks folder
    model: ColmapModel  # the SfM model, with each photo's observations (they measure its exposure)
    image_dir: Path  # the photos the model belongs to
    views: list[ColmapView]  # the model's views, each with its photo in image_dir
    stems: list[str]  # their names without extension (unique): the prepared views' names
    made_from: dict[str, str | None]  # content fingerprints of the photos, the SfM model and the masks folder

    @property
    def has_masks(self) -> bool:
        return bool(self.masks.get("has_masks"))


def _read_inputs(scene_dir: Path, sfm_dir: str | Path, masks_dir: str | Path | None) -> _Inputs:
    """The sfm and masks outputs, checked to belong to the scene's photos, and the SfM model's views."""
    sfm = load_stage_summary(sfm_dir, "sfm")
    masks = load_stage_summary(masks_dir, "masks") if masks_dir is not None else {"has_masks": False}
    photos = photo_fingerprints(scene_dir / "images")
    check_made_from_photos(sfm_dir, sfm, "sfm", scene_dir / "images", photos, "--sfm")
    if masks_dir is not None:
        check_made_from_photos(masks_dir, masks, "masks", scene_dir / "images", photos, "--masks")
    model = load_model(sfm["model_dir"], observations=True)  # the observations measure each photo's exposure
    image_dir = Path(sfm["image_dir"])
    made_from = {
        "images": photos_fingerprint(photos),
        "sfm": folder_fingerprint(sfm["model_dir"]),
        "masks": folder_fingerprint(masks_dir, skip=("summary.json",)) if masks_dir is not None else None,
    }
    views, stems = _registered_views(model, image_dir, sfm["model_dir"])
    return _Inputs(sfm=sfm, masks=masks, model=model, image_dir=image_dir, views=views, stems=stems,
                   made_from=made_from)


def _registered_views(model: ColmapModel, image_dir: Path, model_dir: str) -> tuple[list[ColmapView], list[str]]:
    """The model's views and their file stems; an error when a view's photo is missing, when fewer than
    two views are registered, or when two photos share a stem."""
    missing = [v.name for v in model.views if not (image_dir / v.name).is_file()]
    views = [v for v in model.views if v.name not in missing]
    if missing:
        raise PipelineError(
            f"the COLMAP model lists {len(missing)} image(s) that are not in {image_dir}, e.g. {missing[0]}",
            path=model_dir,
            fix="restore the images or re-run 'rtsplat sfm' so the model matches the image folder",
        )
    if len(views) < 2:
        raise PipelineError(
            "fewer than 2 registered images",
            path=model_dir,
            fix="add more overlapping images and re-run 'rtsplat sfm'",
        )
    stems = [Path(v.name).stem for v in views]
    if len(set(stems)) != len(stems):
        raise PipelineError(
            "two images share a file stem (e.g. a.jpg and a.png)",
            path=image_dir,
            fix="rename the images so their names without extension are unique",
        )
    return views, stems


@dataclass
class _Sources:
    """Where each prepared view's image, mask and ground-truth layers come from (:func:`_sources`)."""

    image_dir: Path
    factor: int  # the downsample factor
    prescaled_dir: Path | None  # the dataset's images_<factor>/ when its images are used, else None
    masks_dir: Path | None  # None: the scene has no masks
    # masks belong to the original images: when SfM undistorted those, the distorted views undistort the masks too
    distorted: dict[str, ColmapView] | None
    propagated: set[str]  # the photos whose masks were propagated (masks.source: propagate)
    layer_dir: Path | None  # ground-truth layers of a synthetic dataset; None when SfM undistorted the images
    split: dict[str, str]  # "train" or "test" by view name


def _sources(scene_dir: Path, sfm_dir: str | Path, masks_dir: str | Path | None, read: _Inputs, factor: int,
             cfg: PrepareConfig) -> _Sources:
    undistorted = bool(read.sfm.get("undistorted", False))
    distorted = None
    if read.has_masks and read.sfm.get("undistorted"):
        distorted = {v.name: v for v in load_model(Path(sfm_dir) / "sparse" / "0").views}
    prescaled_dir = scene_dir / f"images_{factor}"
    use_prescaled = (
        factor > 1
        and cfg.use_prescaled
        and not undistorted
        and prescaled_dir.is_dir()
        and all((prescaled_dir / v.name).is_file() for v in read.views)
    )
    return _Sources(
        image_dir=read.image_dir, factor=factor, prescaled_dir=prescaled_dir if use_prescaled else None,
        masks_dir=Path(masks_dir) if read.has_masks else None, distorted=distorted,
        propagated={n for n, src in (read.masks.get("mask_sources") or {}).items() if src == "propagated"},
        layer_dir=None if undistorted else scene_dir / "layers" / "linear",
        split=_test_split(read.stems, cfg.test_every),
    )


def _initial_roi(cfg: PrepareConfig, model: ColmapModel) -> Roi:
    """The configured region of interest, else the one estimated from the cameras and SfM points."""
    if cfg.roi is not None:
        return Roi(center=[float(x) for x in cfg.roi.center], radius=float(cfg.roi.radius), source="config")
    return estimate_roi(model, cfg.roi_percentile)


@dataclass
class _View:
    """One prepared view, as :func:`_write_view` wrote it."""

    camera: CameraRecord
    gain: GainEstimate  # its photo's exposure (:func:`_exposure`)
    gt_layers: bool  # ground-truth layers were written for it
    coverage: float | None = None  # the share of its prepared mask's pixels that are see-through; None: no mask
    # (K, world_to_camera, mask) that carves the masks' visual hull (:func:`hull_mask`); None: no mask
    hull_view: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None


def _write_views(tmp: Path, read: _Inputs, src: _Sources, cfg: PrepareConfig, progress: bool) -> list[_View]:
    from tqdm import tqdm

    (tmp / IMAGES_DIR).mkdir()
    if src.masks_dir is not None:
        (tmp / MASKS_DIR).mkdir()
    views = []
    for view, stem in tqdm(list(zip(read.views, read.stems, strict=True)), desc="prepare", unit="img",
                           disable=not progress):
        views.append(_write_view(tmp, view, stem, read.model, src, cfg))
    return views


def _write_view(tmp: Path, view: ColmapView, stem: str, model: ColmapModel, src: _Sources,
                cfg: PrepareConfig) -> _View:
    """Write the view's image, its ground-truth layers (test views of a synthetic dataset) and its mask."""
    image, full, K = _view_image(view, src)
    h, w = image.shape[:2]
    write_png(tmp / IMAGES_DIR / f"{stem}.png", image, bits=cfg.bit_depth)
    gt_layers = _write_ground_truth_layers(tmp, view, stem, image, src)
    mask, coverage, hull_view = None, None, None
    if src.masks_dir is not None:
        mask = _view_mask(view, stem, src)
        small = _downsample_mask(mask, src.factor, (h, w))
        write_mask(tmp / MASKS_DIR / f"{stem}.png", small)
        coverage = float(small.mean())
        hull_view = (K, view.world_to_camera, hull_mask(small, view.name in src.propagated))
    gain = _exposure(full, model.observations.get(view.name), (view.width, view.height), mask)
    camera = CameraRecord(name=stem, split=src.split[stem], width=int(w), height=int(h), K=K.tolist(),
                          world_to_camera=view.world_to_camera.tolist(), image=view.name)
    return _View(camera=camera, gain=gain, gt_layers=gt_layers, coverage=coverage, hull_view=hull_view)


def _view_image(view: ColmapView, src: _Sources) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The prepared image, the image the exposure is measured on (the full-size photo, or the pre-scaled
    image) and the prepared intrinsics K; an error when the photo does not have its camera's size."""
    path = src.image_dir / view.name
    header = read_header(path)
    if (header.width, header.height) != (view.width, view.height):
        raise PipelineError(
            f"image is {header.width}x{header.height} but its COLMAP camera is {view.width}x{view.height}",
            path=path,
            fix="use the images the model was computed from (or re-run 'rtsplat sfm'); "
            "all images of a scene must have the size of their camera",
        )
    K = view.K.copy()
    f = src.factor
    if src.prescaled_dir is not None:
        image = read_image(src.prescaled_dir / view.name)
        h, w = image.shape[:2]
        if abs(w * f - view.width) >= f or abs(h * f - view.height) >= f:
            raise PipelineError(
                f"pre-scaled image is {w}x{h}, expected about {view.width // f}x{view.height // f}",
                path=src.prescaled_dir / view.name,
                fix=f"delete {src.prescaled_dir} or set prepare.use_prescaled: false",
            )
        K[0] *= w / view.width
        K[1] *= h / view.height
        return image, image, K
    full = read_image(path)
    K[:2] /= f
    return area_downsample(full, f), full, K


def _write_ground_truth_layers(tmp: Path, view: ColmapView, stem: str, image: np.ndarray, src: _Sources) -> bool:
    """Write a test view's ground-truth layers (:func:`ground_truth_layers`) when the dataset has them;
    whether it wrote them."""
    if src.layer_dir is None or src.split[stem] != "test":
        return False
    npz = src.layer_dir / f"{Path(view.name).stem}.npz"
    if not npz.is_file():
        return False
    layers = ground_truth_layers(npz, image, src.factor)
    for name, layer in (layers or {}).items():
        (tmp / GT_LAYERS_DIR / name).mkdir(parents=True, exist_ok=True)
        write_png(tmp / GT_LAYERS_DIR / name / f"{stem}.png", layer, bits=16)
    return layers is not None


def _view_mask(view: ColmapView, stem: str, src: _Sources) -> np.ndarray:
    """The view's mask at its camera's size (undistorted when SfM undistorted the photo), checked."""
    path = src.masks_dir / f"{stem}.png"
    if not path.is_file():
        raise PipelineError("mask missing", path=path, fix="re-run 'rtsplat masks'")
    mask = read_mask(path)
    if src.distorted is not None and view.name in src.distorted:
        d = src.distorted[view.name]
        if mask.shape != (d.height, d.width):
            raise PipelineError(
                f"mask is {mask.shape[1]}x{mask.shape[0]}, image is {d.width}x{d.height}",
                path=path,
                fix="re-run 'rtsplat masks' on the scene's images",
            )
        mask = undistort_mask(mask, d, (view.width, view.height))
    if mask.shape != (view.height, view.width):
        raise PipelineError(
            f"mask is {mask.shape[1]}x{mask.shape[0]}, image is {view.width}x{view.height}",
            path=path,
            fix="re-run 'rtsplat masks' on the images the model uses",
        )
    return mask


def _downsample_mask(mask: np.ndarray, factor: int, size: tuple[int, int]) -> np.ndarray:
    """The mask at the prepared image's ``size`` (height, width), binarised."""
    small = area_downsample(mask.astype(np.float32), factor) >= 0.5
    if small.shape != size:  # pre-scaled images rounded differently
        import cv2

        small = cv2.resize(mask.astype(np.uint8), (size[1], size[0]), interpolation=cv2.INTER_AREA) >= 0.5
    return small


def _carry_reflection_reach(tmp: Path, scene_dir: Path) -> None:
    """Carry what a synthetic dataset's glass reflects beside its ground-truth layers."""
    reach = _dataset_reflection_reach(scene_dir)
    if reach is not None:
        (tmp / GT_LAYERS_DIR / REFLECTION_REACH_FILE).write_text(json.dumps(reach, indent=1))


def _masks_kept(tmp: Path, views: list[_View]) -> bool:
    """Whether the prepared scene has masks: written, and not one without a single see-through pixel
    (then the masks folder is removed)."""
    coverage = [v.coverage for v in views if v.coverage is not None]
    if not coverage:
        return False
    if not any(coverage):
        import shutil

        shutil.rmtree(tmp / MASKS_DIR)
        return False
    return True


def _region_of_interest(roi: Roi, hull_views: list, has_masks: bool, cfg: PrepareConfig) -> tuple[Roi, str]:
    """The sphere around the masks' visual hull when the scene has masks and no configured region
    (:func:`checked_mask_roi`), else ``roi``; with why the masks' one was not used, in words ('' when it was)."""
    if has_masks and cfg.roi is None and cfg.roi_from_masks:
        return checked_mask_roi(roi_from_masks(hull_views, roi, cfg.roi_mask_agreement), roi, hull_views)
    return roi, ""


def _write_transparent_surface(tmp: Path, hull_views: list, roi: Roi, cfg: PrepareConfig) -> None:
    """The points of the masks' visual hull that face the cameras, with their normals (:func:`hull_surface`)."""
    hull = mask_hull(hull_views, roi, cfg.roi_mask_agreement, grid=64)
    if hull is not None:
        xyz, normal = hull_surface(hull, hull_views)
        np.savez(tmp / TRANSPARENT_SURFACE_FILE, xyz=xyz.astype(np.float32), normal=normal.astype(np.float32))


def _scene_record(views: list[_View], read: _Inputs, roi: Roi, roi_warning: str, has_masks: bool, scene_dir: Path,
                  factor: int, cfg: PrepareConfig) -> PreparedScene:
    """``scene.json``'s content."""
    cameras = [v.camera for v in views]
    marked = {Path(n).stem for n in read.masks.get("marked") or []}  # set only by masks.source: propagate
    gains = {v.camera.name: v.gain for v in views}
    return PreparedScene(
        cameras=sorted(cameras, key=lambda c: c.name),
        roi=roi,
        downsample=factor,
        resolution=cfg.resolution,
        source=str(scene_dir.resolve()),
        has_transparency=has_masks,
        versions={"rtsplat": __version__, "scene_format": "1"},
        inputs=read.made_from,
        exposure={n: None if g.log_gain is None else [round(float(x), 5) for x in g.log_gain]
                  for n, g in gains.items()},
        exposure_points={n: g.points for n, g in gains.items()},
        exposure_error={n: None if g.error is None else round(g.error, 6) for n, g in gains.items()},
        marked_views=sorted(c.name for c in cameras if c.name in marked),
        roi_warning=roi_warning,
    )


def prepare_scene(
    scene_dir: str | Path,
    sfm_dir: str | Path,
    out_dir: str | Path,
    cfg: PrepareConfig | None = None,
    masks_dir: str | Path | None = None,
    progress: bool = True,
) -> PrepareSummary:
    """Write the prepared scene for ``scene_dir`` into ``out_dir`` (atomically); see the module docstring."""
    cfg = cfg or PrepareConfig()
    scene_dir = Path(scene_dir)
    inputs = [scene_dir, sfm_dir, masks_dir]
    check_output_dir(out_dir, "prepare", inputs=inputs)
    read = _read_inputs(scene_dir, sfm_dir, masks_dir)
    f, downsample_reason = downsample_factor({(v.width, v.height) for v in read.views}, cfg, read.image_dir)
    src = _sources(scene_dir, sfm_dir, masks_dir, read, f, cfg)
    roi = _initial_roi(cfg, read.model)
    with output_dir(Path(out_dir), "prepare", inputs=inputs) as tmp:
        views = _write_views(tmp, read, src, cfg, progress)
        if any(v.gt_layers for v in views):
            _carry_reflection_reach(tmp, scene_dir)
        has_masks = _masks_kept(tmp, views)
        hull_views = [v.hull_view for v in views if v.hull_view is not None]
        roi, roi_warning = _region_of_interest(roi, hull_views, has_masks, cfg)
        if has_masks and cfg.transparent_surface and not roi_warning:  # a hull away from the glass seeds nothing
            _write_transparent_surface(tmp, hull_views, roi, cfg)
        write_points_ply(tmp / POINTS_FILE, read.model.xyz, read.model.rgb)
        scene = _scene_record(views, read, roi, roi_warning, has_masks, scene_dir, f, cfg)
        scene.save(tmp)
        scene.validate(check_files=True, where=tmp / "scene.json")
    return _summary(scene, views, src, read.model, downsample_reason)


def _summary(scene: PreparedScene, views: list[_View], src: _Sources, model: ColmapModel,
             downsample_reason: str) -> PrepareSummary:
    coverage = [v.coverage for v in views if v.coverage is not None]
    return PrepareSummary(
        num_train=len(scene.train_cameras),
        num_test=len(scene.test_cameras),
        width=views[0].camera.width,
        height=views[0].camera.height,
        downsample=scene.downsample,
        roi=scene.roi,
        has_transparency=scene.has_transparency,
        mask_coverage=float(np.mean(coverage)) if coverage else 0.0,
        num_points=len(model.xyz),
        used_prescaled=src.prescaled_dir is not None,
        gt_layer_views=sum(v.gt_layers for v in views),
        resolution=scene.resolution,
        downsample_reason=downsample_reason,
        roi_warning=scene.roi_warning,
    )


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--scene-dir", type=Path, required=True, help="dataset scene (<data>/<scene>)")
    parser.add_argument("--sfm", type=Path, required=True, help="output folder of 'rtsplat sfm'")
    parser.add_argument("--masks", type=Path, help="output folder of 'rtsplat masks' (none: no transparency)")
    parser.add_argument("--out", type=Path, required=True, help="prepared scene folder to write")
    size = parser.add_mutually_exclusive_group()
    size.add_argument(
        "--downsample", type=int, metavar="N",
        help="integer downsample factor (area filter), e.g. 4 for quarter-size images; overrides "
        "prepare.downsample and any prepare.resolution of the config",
    )
    size.add_argument(
        "--resolution", type=int, metavar="PIXELS",
        help="longest side of the prepared images in pixels, at most, e.g. 800: the smallest integer "
        "downsample factor that meets it is used (1 when the images are that small already) and recorded "
        "in scene.json; overrides prepare.resolution",
    )
    add_config_arguments(parser)


def run(args: argparse.Namespace) -> int:
    cfg = stage_config_from_args(args, "prepare", {"downsample": args.downsample, "resolution": args.resolution})
    if args.downsample is not None:  # the factor given on the command line wins over a configured resolution
        cfg = dataclasses.replace(cfg, resolution=None)
    s = prepare_scene(args.scene_dir, args.sfm, args.out, cfg, args.masks)
    print(f"prepare {args.out}: {s.downsample_reason}")
    if s.roi_warning:
        print(f"WARNING: prepare {args.out}: {s.roi_warning}", file=sys.stderr)
    print(
        f"prepared {args.out}: {s.num_train} train + {s.num_test} test views at {s.width}x{s.height} "
        f"(downsample {s.downsample}{', pre-scaled images' if s.used_prescaled else ''}), "
        f"{s.num_points} points, ROI {s.roi.source} center={np.round(s.roi.center, 3).tolist()} "
        f"radius={s.roi.radius:.3f}, transparency={'yes' if s.has_transparency else 'no'}"
        + (f" (mask coverage {100 * s.mask_coverage:.1f}%)" if s.has_transparency else "")
        + (f", ground-truth layers for {s.gt_layer_views} test views" if s.gt_layer_views else "")
    )
    return 0
