"""What the glass of a synthetic scene reflects: near geometry or the environment at infinity.

The specular branch looks a reflection up by direction alone (the environment map at the reflected
direction), so it can show what lies far from the glass, not what is near it: a near reflection moves
against the reflected direction as the viewer moves. In a scene made by ``rtsplat synth`` each glass pixel's
reflection can be followed: the ray through the pixel centre goes to its first hit, which must be a
see-through surface, is mirrored about that surface's shading normal (what Mitsuba reflects about), and goes
on. Where the mirrored ray meets a surface, the pixel reflects something at that finite distance; where it
leaves the scene, the environment at infinity. ``rtsplat synth`` records the result for the views with
ground-truth layers in ``scene.json`` (``reflection_reach``); ``python -m rtsplat.bench.reflection_reach``
measures it on a dataset.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

LUMINANCE = np.array([0.2126, 0.7152, 0.0722])  # linear RGB -> luminance (Rec. 709)


@dataclass
class ReflectionReach:
    """What the glass pixels of some views reflect."""

    glass_pixels: int  # mask pixels whose centre ray first meets a see-through surface
    near_pixels: int  # of those, the ones whose mirrored ray meets a surface
    near_weight: float  # share of the weights (the true reflection's luminance) on those pixels
    median_distance: float  # from the glass to what the mirrored ray meets (nan when nothing is near)

    @property
    def near_share(self) -> float:
        return self.near_pixels / max(self.glass_pixels, 1)


def reflection_reach(scene, cameras: list, masks: list[np.ndarray], weights: list[np.ndarray] | None = None,
                     stride: int = 1) -> ReflectionReach:
    """Follow the reflection of every ``stride``-th glass pixel (row and column) of each camera.

    ``scene``: a loaded Mitsuba scene (scalar variant, :func:`rtsplat.synth.render.set_variant`);
    ``cameras``: :class:`rtsplat.camera.Camera`; ``masks``: bool [H, W] per camera, the pixels to follow;
    ``weights``: float [H, W] per camera (default 1), e.g. the true reflection's luminance.
    """
    import mitsuba as mi

    from rtsplat.synth.cameras import pixel_rays
    from rtsplat.synth.render import is_see_through, see_through_flags

    flags = see_through_flags()
    glass = near = 0
    weight_all = weight_near = 0.0
    distances: list[float] = []
    for index, (camera, mask) in enumerate(zip(cameras, masks, strict=True)):
        rows, cols = np.nonzero(mask[::stride, ::stride])
        rows, cols = rows * stride, cols * stride
        if not len(rows):
            continue
        origin, directions = pixel_rays(camera, cols + 0.5, rows + 0.5)
        o = mi.Point3f(*origin.tolist())
        w = np.ones(len(rows)) if weights is None else np.asarray(weights[index], dtype=np.float64)[rows, cols]
        for d, wk in zip(directions.tolist(), w.tolist(), strict=True):
            si = scene.ray_intersect(mi.Ray3f(o, mi.Vector3f(*d)))
            if not is_see_through(si, flags):
                continue
            n = np.array(si.sh_frame.n, dtype=np.float64)
            v = np.array(d, dtype=np.float64)
            r = v - 2.0 * float(v @ n) * n
            hit = scene.ray_intersect(si.spawn_ray(mi.Vector3f(*r.tolist())))
            glass += 1
            weight_all += wk
            if hit.is_valid():
                near += 1
                weight_near += wk
                distances.append(float(hit.t))
    return ReflectionReach(glass_pixels=glass, near_pixels=near, near_weight=weight_near / max(weight_all, 1e-12),
                           median_distance=float(np.median(distances)) if distances else float("nan"))


def reach_record(reach: ReflectionReach) -> dict:
    """``reach`` as the ``reflection_reach`` block of a dataset's ``scene.json`` (JSON: no NaN)."""
    record = asdict(reach)
    record["near_share"] = reach.near_share
    if not np.isfinite(record["median_distance"]):
        record["median_distance"] = None
    return record
