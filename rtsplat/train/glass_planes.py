"""The glass's mirror planes fitted to the model's own see-through surface, once, as the near reflections
start (:func:`fit_near_planes`, which :meth:`rtsplat.train.trainer.Trainer.fit_mirror_planes` calls;
:mod:`rtsplat.train.planes` refines them from the images afterwards).

The points are the surface depth of every training view's transparent pixels (mask > 0.5, surface alpha
> 0.5) with the surface normals (:func:`glass_samples`); the planes are fitted within ``PLANE_TOLERANCE`` of
the points' diagonal (:func:`rtsplat.model.mirror.fit_planes`) and kept where they are glass
(:func:`glass_planes`); :func:`near_coverage` says how much of the model they would reflect.
"""

from __future__ import annotations

import time

import torch
from torch import Tensor

from rtsplat.model.mirror import empty_planes, fit_planes, is_bent
from rtsplat.model.rtmodel import RTModel, image_ray_directions
from rtsplat.raster import RasterSettings, rasterize
from rtsplat.scene import PreparedScene
from rtsplat.train import losses
from rtsplat.train.data import ViewSet
from rtsplat.train.effects import NEAR_COVERAGE_VIEWS, decide_near_planes, planes_seen_edge_on, see_through_planes
from rtsplat.train_config import TrainConfig

PLANE_TOLERANCE = 0.01  # mirror planes: thickness tolerance, a fraction of the glass points' diagonal
MAX_PLANE_POINTS = 50_000  # glass points the mirror planes are fitted to (a random subset beyond)


@torch.no_grad()
def glass_samples(model: RTModel, views: ViewSet, raster: RasterSettings, backend: str,
                  generator: torch.Generator) -> tuple[Tensor, Tensor, Tensor, list[tuple]]:
    """The see-through surface as ``model`` renders it in the training ``views``: points [N,3], unit normals
    [N,3] and rays [N,7] (origin, direction, distance to what the transmission shows) in float64, at most
    ``MAX_PLANE_POINTS`` of them (a random subset drawn with ``generator``), and the (camera, see-through
    pixels [H,W], surface depth [H,W]) of the at most ``NEAR_COVERAGE_VIEWS`` views, spread over the
    capture, that :func:`near_coverage` is measured on."""
    points, normals, rays = [], [], []
    masked = [i for i, m in enumerate(views.masks) if m is not None]
    sampled = set(masked[::max(1, len(masked) // NEAR_COVERAGE_VIEWS)][:NEAR_COVERAGE_VIEWS])
    coverage_views = []
    for index in masked:
        camera, mask = views.cameras[index], views.masks[index]
        out = rasterize(model.rasterizer_surfels(camera, channels=()), camera, raster, backend=backend)
        chosen = ((mask > 0.5) & (out.alpha > 0.5))[..., 0]
        if index in sampled:
            coverage_views.append((camera, chosen, out.depth[..., 0]))
        directions = image_ray_directions(camera)[chosen]
        seen_through = losses.depth_to_points(out.volume_depth, camera)[chosen]  # what the transmission shows
        points.append(losses.depth_to_points(out.depth, camera)[chosen])
        normals.append(torch.nn.functional.normalize(out.normal[chosen], dim=-1))
        rays.append(torch.cat([camera.center.expand_as(directions), directions,
                               (seen_through - camera.center).norm(dim=-1, keepdim=True)], -1))
    # in the render's precision until the subset is drawn: all views' transparent pixels of a real
    # capture are millions of points
    xyz, normal, rays = (torch.cat(x).cpu() if x else torch.zeros(0, w)
                         for x, w in ((points, 3), (normals, 3), (rays, 7)))
    ok = torch.isfinite(xyz).all(-1) & torch.isfinite(normal).all(-1) & torch.isfinite(rays).all(-1)
    xyz, normal, rays = xyz[ok], normal[ok], rays[ok]
    if xyz.shape[0] > MAX_PLANE_POINTS:
        keep = torch.randperm(xyz.shape[0], generator=generator)[:MAX_PLANE_POINTS]
        xyz, normal, rays = xyz[keep], normal[keep], rays[keep]
    return xyz.double(), normal.double(), rays.double(), coverage_views


def glass_planes(xyz: Tensor, normal: Tensor, rays: Tensor, marked_centres: Tensor,
                 seed: int) -> tuple[Tensor, float | None, int, int]:
    """The planes fitted to the see-through points (:func:`glass_samples`) that are glass, the share of the
    points they explain (None: too few points to fit), and how many planes were left out: with nothing
    behind them (:func:`rtsplat.train.effects.see_through_planes`), and seen edge-on from one of
    ``marked_centres`` (faces of the marked views' hull, :func:`rtsplat.train.effects.planes_seen_edge_on`)."""
    if xyz.shape[0] < 16:
        return empty_planes(), None, 0, 0
    diagonal = float((xyz.max(0).values - xyz.min(0).values).norm())
    planes, shares = fit_planes(xyz, normal, tolerance=PLANE_TOLERANCE * diagonal, seed=seed)
    glass = see_through_planes(planes, rays)
    faces = planes_seen_edge_on(planes, marked_centres) & glass
    keep = glass & ~faces
    return planes[keep], float(shares[keep].sum()), int((~glass).sum()), int(faces.sum())


@torch.no_grad()
def near_coverage(model: RTModel, planes: Tensor, views: list[tuple], raster: RasterSettings, backend: str) -> float:
    """The mean coverage (volume alpha) of the near reflection in ``planes`` over the see-through pixels
    (mask > 0.5, surface alpha > 0.5) of ``views`` (camera, those pixels [H,W], surface depth [H,W]; at
    most ``NEAR_COVERAGE_VIEWS`` training views spread over the capture, rasterized by the plane fit):
    how much of the model the glass would reflect. The model's own planes are left as they were."""
    held = model.mirror_planes
    model.set_mirror_planes(planes)
    covered, pixels = 0.0, 0
    try:
        for camera, wanted, surface_depth in views:
            _, alpha = model.near_reflection(camera, wanted, raster, backend, surface_depth=surface_depth)
            covered += float(alpha[..., 0][wanted].sum())
            pixels += int(wanted.sum())
    finally:
        model.set_mirror_planes(held)
    return covered / max(pixels, 1)


def marked_centres(scene: PreparedScene) -> Tensor:
    """The camera centres [C,3] of the views whose masks were marked, when the others' were propagated
    from them (``PreparedScene.marked_views``); none otherwise."""
    records = [c for c in scene.cameras if c.name in set(scene.marked_views)]
    if not records:
        return torch.zeros(0, 3, dtype=torch.float64)
    return torch.stack([c.to_camera(dtype=torch.float64).center for c in records])


@torch.no_grad()
def fit_near_planes(model: RTModel, views: ViewSet, scene: PreparedScene, cfg: TrainConfig,
                    generator: torch.Generator) -> tuple[Tensor, dict]:
    """The mirror planes the near reflections use (none where they stay off) and the fit's record: the planes
    fitted to ``model``'s see-through surface in the training ``views`` (:func:`glass_samples`,
    :func:`glass_planes`), and whether the near reflections go on
    (:func:`rtsplat.train.effects.decide_near_planes`, from how planar the glass is and how much of the model
    the planes would reflect, :func:`near_coverage`).

    A plane is glass only if the scene seen through it lies behind it: of the pixels whose ray meets
    the plane first, most must have their volume depth (what the transmission shows) beyond the plane
    by more than its thickness (:data:`rtsplat.train.effects.BEHIND_SHARE`). A floor seen through a dome, or
    the floor inside a cabin, is a plane the see-through pixels hit, but what they show lies on it, not behind
    it. With propagated masks, a plane a marked view sees edge-on is a face of the hull the glass was seeded on,
    not a pane (:func:`rtsplat.train.effects.planes_seen_edge_on`), and is left out too."""
    start = time.perf_counter()
    xyz, normal, rays, coverage_views = glass_samples(model, views, cfg.raster, cfg.backend, generator)
    planes, share, dropped, hull_faces = glass_planes(xyz, normal, rays, marked_centres(scene), cfg.seed)
    coverage = near_coverage(model, planes, coverage_views, cfg.raster, cfg.backend) if planes.shape[0] else None
    use, why = decide_near_planes(cfg.effects.near_reflection, planes.shape[0], share, coverage)
    if dropped:
        why += f" ({dropped} plane(s) with nothing behind them left out)"
    if hull_faces:
        why += f" ({hull_faces} plane(s) seen edge-on by a marked view left out: faces of the marked views' hull)"
    record = {"points": int(xyz.shape[0]), "planes": int(planes.shape[0]), "bent_planes": int(is_bent(planes).sum()),
              "planar_share": share, "coverage": None if coverage is None else round(coverage, 4), "on": use,
              "reason": why, "seconds": round(time.perf_counter() - start, 3)}
    return (planes if use else empty_planes()), record
