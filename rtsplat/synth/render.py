"""Rendering of one view: full image, see-through mask and ground-truth layers.

* The **full image** is Mitsuba's ``volpath`` integrator through a ``perspective`` sensor converted
  from the ground-truth :class:`~rtsplat.camera.Camera` (box pixel filter, stratified
  ``multijitter`` sampler).
* The **mask** marks pixels whose centre ray first hits a see-through surface: one whose BSDF
  has a null or delta transmission lobe (``thindielectric`` and blends of it).
* The **layers** split the radiance at the *first* see-through hit by BSDF lobe:
  ``reflection`` (delta reflection lobe: what the surface reflects), ``transmission`` (delta
  transmission / null lobe: what comes through it) and ``scatter`` (any other lobe, e.g. the
  diffuse scattering of the ``film``; it is *included* in ``transmission``, which is what
  ``C_sub = tau C_trans + (1 - tau) C_scatter`` models). Every lobe is sampled explicitly with
  Mitsuba's own BSDF (``BSDFContext.component``) and the radiance along the sampled direction
  comes from the same path integrator (one bounce shorter), so
  ``reflection + transmission`` is an unbiased estimate of the full image, independent of it
  (its own samples, stratified inside the pixel). Pixels that see no see-through surface (the
  mask grown by one pixel) have ``reflection = 0`` and ``transmission = full image``.

The layer split is a per-sample Python loop over pixels near a see-through surface (the scalar
Mitsuba variants have no vectorised ray API; the LLVM variants need LLVM >= 17, which this
project's CI machines lack); the rest of the image reuses the full render.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from rtsplat.camera import Camera
from rtsplat.synth.cameras import effective_spp, mitsuba_sensor, pixel_rays

VARIANT = "scalar_rgb"


def set_variant() -> str:
    """Select the Mitsuba variant used by rtsplat.synth and return its name."""
    import mitsuba as mi

    if mi.variant() != VARIANT:
        mi.set_variant(VARIANT)
    return VARIANT


@dataclass
class ViewRender:
    """Linear RGB float32 [H, W, 3] images of one view and its boolean [H, W] mask."""

    full: np.ndarray
    reflection: np.ndarray | None  # None when the layer split was skipped
    transmission: np.ndarray | None
    scatter: np.ndarray | None
    mask: np.ndarray
    layer_stderr: np.ndarray | None  # [H, W] standard error of (reflection + transmission), 0 off the split


def integrator_dict(max_depth: int) -> dict:
    """Mitsuba's ``volpath``: unlike ``path`` its shadow rays pass through the null-transmission
    lobe of thin dielectrics, so objects behind glass get direct light (far less noise)."""
    return {"type": "volpath", "max_depth": int(max_depth), "rr_depth": 5}


def see_through_flags() -> int:
    """BSDF flags that make a surface see-through (thin dielectrics have a null-transmission lobe)."""
    import mitsuba as mi

    return int(mi.BSDFFlags.Null) | int(mi.BSDFFlags.DeltaTransmission)


def is_see_through(si, flags: int) -> bool:
    """Whether a (scalar) surface interaction hit a see-through surface."""
    return bool(si.is_valid()) and bool(int(si.bsdf().flags()) & flags)


def first_hit_mask(scene, camera: Camera) -> np.ndarray:
    """Boolean [H, W]: the ray through the pixel centre first hits a see-through surface."""
    import mitsuba as mi

    h, w = int(camera.height), int(camera.width)
    mask = np.zeros((h, w), dtype=bool)
    jj, ii = np.mgrid[0:h, 0:w]
    o, d = pixel_rays(camera, ii.ravel() + 0.5, jj.ravel() + 0.5)
    origin = mi.Point3f(*o.tolist())
    flags = see_through_flags()
    flat = mask.ravel()
    for k, dk in enumerate(d.tolist()):
        si = scene.ray_intersect(mi.Ray3f(origin, mi.Vector3f(*dk)))
        if is_see_through(si, flags):
            flat[k] = True
    return mask


def _dilate(mask: np.ndarray) -> np.ndarray:
    out = mask.copy()
    out[1:] |= mask[:-1]
    out[:-1] |= mask[1:]
    out[:, 1:] |= out[:, :-1].copy()
    out[:, :-1] |= out[:, 1:].copy()
    return out


def split_layers(
    scene,
    camera: Camera,
    pixels: np.ndarray,
    spp: int,
    seed: int,
    max_depth: int,
) -> tuple[np.ndarray, np.ndarray]:
    """Per-lobe radiance at the first see-through hit for the given pixels.

    ``pixels``: int [P, 2] (row, column). Returns (layers [P, 3 lobes, 3 rgb] = mean over ``spp``
    stratified jittered samples, standard error [P] of the summed layers' luminance).
    """
    import mitsuba as mi

    integrator = mi.load_dict(integrator_dict(max_depth))
    continuation = mi.load_dict(integrator_dict(max(max_depth - 1, 1)))
    sampler = mi.load_dict({"type": "independent"})
    sampler.seed(seed)
    rng = np.random.default_rng(seed)
    see_through = see_through_flags()
    contexts = []
    p = len(pixels)
    # stratified (Latin hypercube) positions inside each pixel: one sample per row and per column stratum
    strata = np.stack([rng.permuted(np.tile(np.arange(spp), (p, 1)), axis=1) for _ in range(2)], axis=-1)
    jitter = (strata + rng.random((p, spp, 2))) / spp
    u = pixels[:, 1, None] + jitter[..., 0]
    v = pixels[:, 0, None] + jitter[..., 1]
    o, d = pixel_rays(camera, u.ravel(), v.ravel())
    directions = d.reshape(p, spp, 3).tolist()  # Python floats: much faster to hand to Mitsuba
    origin = mi.Point3f(*o.tolist())
    reflection_flag = int(mi.BSDFFlags.DeltaReflection)
    transmission_flags = int(mi.BSDFFlags.Null) | int(mi.BSDFFlags.DeltaTransmission)
    acc = np.zeros((p, 3, 3), dtype=np.float64)
    acc_sq = np.zeros(p, dtype=np.float64)
    for k in range(p):
        totals = [[0.0, 0.0, 0.0], [0.0, 0.0, 0.0], [0.0, 0.0, 0.0]]  # lobe x rgb
        sum_sq = 0.0
        for s in range(spp):
            ray = mi.Ray3f(origin, mi.Vector3f(*directions[k][s]))
            si = scene.ray_intersect(ray)
            r = g = b = 0.0  # this sample's total, for the standard error
            if is_see_through(si, see_through):
                if si.shape.is_emitter():  # light emitted by the surface itself counts as scatter
                    e = si.emitter(scene).eval(si)
                    lobe = totals[2]
                    lobe[0] += e[0]
                    lobe[1] += e[1]
                    lobe[2] += e[2]
                    r, g, b = r + e[0], g + e[1], b + e[2]
                bsdf = si.bsdf()
                n_comp = bsdf.component_count()
                while len(contexts) < n_comp:
                    ctx = mi.BSDFContext()
                    ctx.component = len(contexts)
                    contexts.append(ctx)
                for c in range(n_comp):
                    bs, weight = bsdf.sample(contexts[c], si, sampler.next_1d(), sampler.next_2d())
                    if not bs.pdf > 0 or not max(weight) > 0:
                        continue
                    radiance, _, _ = continuation.sample(scene, sampler, si.spawn_ray(si.to_world(bs.wo)))
                    flags = int(bs.sampled_type)
                    lobe = totals[0 if flags & reflection_flag else 1 if flags & transmission_flags else 2]
                    cr, cg, cb = weight[0] * radiance[0], weight[1] * radiance[1], weight[2] * radiance[2]
                    lobe[0] += cr
                    lobe[1] += cg
                    lobe[2] += cb
                    r, g, b = r + cr, g + cg, b + cb
            else:
                radiance, _, _ = integrator.sample(scene, sampler, ray)
                lobe = totals[1]
                r, g, b = radiance[0], radiance[1], radiance[2]
                lobe[0] += r
                lobe[1] += g
                lobe[2] += b
            sum_sq += ((r + g + b) / 3.0) ** 2
        acc[k] = totals
        acc_sq[k] = sum_sq
    mean = acc / spp
    lum = mean.sum(axis=1).mean(axis=1)
    var = np.maximum(acc_sq / spp - lum**2, 0.0) / max(spp - 1, 1)
    return mean.astype(np.float32), np.sqrt(var).astype(np.float32)


def load_scene(scene_dict: dict, cameras: list[Camera], spp: int, max_depth: int = 32):
    """Load a scene dict (no sensor, no integrator) once, with one sensor per camera."""
    import mitsuba as mi

    set_variant()
    full_scene = dict(scene_dict)
    full_scene["type"] = "scene"
    full_scene["integrator"] = integrator_dict(max_depth)
    for i, camera in enumerate(cameras):
        full_scene[f"sensor_{i:04d}"] = mitsuba_sensor(camera, spp)
    return mi.load_dict(full_scene)


def render_view(
    scene,
    view: int,
    camera: Camera,
    spp: int,
    seed: int,
    max_depth: int = 32,
    layer_spp: int | None = None,
) -> ViewRender:
    """Render view ``view`` of a scene from :func:`load_scene` with its layers and mask.

    ``layer_spp``: samples per pixel of the layer split (default ``spp``); 0 skips the split
    (the layers are then None).
    """
    import mitsuba as mi

    full = np.array(mi.render(scene, sensor=view, spp=effective_spp(spp), seed=seed), dtype=np.float32)[..., :3]
    h, w = full.shape[:2]
    mask = first_hit_mask(scene, camera)
    layer_spp = spp if layer_spp is None else layer_spp
    if layer_spp == 0:
        return ViewRender(full, None, None, None, mask, None)
    reflection = np.zeros_like(full)
    transmission = full.copy()
    scatter = np.zeros_like(full)
    stderr = np.zeros((h, w), dtype=np.float32)
    if mask.any():
        near = _dilate(mask)
        pixels = np.argwhere(near)
        layers, se = split_layers(scene, camera, pixels, layer_spp, seed + 0x5EED, max_depth)
        rows, cols = pixels[:, 0], pixels[:, 1]
        reflection[rows, cols] = layers[:, 0]
        transmission[rows, cols] = layers[:, 1] + layers[:, 2]
        scatter[rows, cols] = layers[:, 2]
        stderr[rows, cols] = se
    return ViewRender(full, reflection, transmission, scatter, mask, stderr)
