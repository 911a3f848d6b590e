"""Render a synthetic scene into the dataset layout real users have (and ground truth beside it).

Output directory (``<stem>`` = ``0000`` ... for view 0 ...)::

    images/<stem>.png                   full render, sRGB 8-bit
    transparent_masks/<stem>.png        8-bit, 255 where a see-through surface is the first hit
    sparse/0/{cameras,images,points3D}.{bin,txt}   ground-truth COLMAP model (PINHOLE)
    cameras.json                        the same cameras: K and world_to_camera (OpenCV axes)
    layers/reflection/<stem>.png        ground-truth reflection layer, sRGB 8-bit (display only)
    layers/transmission/<stem>.png      ground-truth transmission layer, sRGB 8-bit (display only)
    layers/linear/<stem>.npz            float16 linear RGB: full, reflection, transmission, scatter
    scene.json                          generator, parameters, seed, Mitsuba version, file list, and
                                        with layers, what the glass of those views reflects
                                        (``reflection_reach``, :mod:`rtsplat.synth.reach`)

Everything is written into a hidden temporary directory beside ``out_dir`` that is renamed into
place at the end (:func:`rtsplat.io.outputs.output_dir`), so a failure or ctrl-C never leaves a
partial dataset, and an existing dataset being overwritten survives a failed run. Only a folder that
synth wrote itself (its marker file) or an empty one is ever replaced.
"""

from __future__ import annotations

import json
import shutil
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from rtsplat.camera import Camera
from rtsplat.errors import ConfigError, PipelineError
from rtsplat.io.colmap import ColmapImage, ColmapPoints, write_sparse_model
from rtsplat.io.images import linear_to_srgb, to_uint, write_png
from rtsplat.io.outputs import output_dir
from rtsplat.synth.cameras import SAMPLER, effective_spp
from rtsplat.synth.catalog import build_any, check_scene_name
from rtsplat.synth.reach import LUMINANCE, reach_record, reflection_reach
from rtsplat.synth.render import VARIANT, ViewRender, load_scene, render_view, set_variant
from rtsplat.synth.scenes import SceneSpec

FORMAT = "rtsplat-synth/1"
VIEW_RANGE = (40, 200)


@dataclass(frozen=True)
class SynthConfig:
    """What to render. ``views`` must lie in 40-200 unless ``allow_any_views`` (tests, debugging)."""

    scene: str = "dome"
    views: int = 48
    width: int = 200
    height: int = 150
    spp: int = 36  # multijitter: rounded up to a grid of strata (cameras.effective_spp)
    layer_spp: int = 8  # samples per pixel of the layer split; 0 = no layers
    layers_every: int = 1  # layers for views 0, k, 2k, ... only (k = 8 matches prepare's default test split)
    seed: int = 0
    max_depth: int = 32
    point_stride: int = 10  # one ground-truth 3D point per stride x stride pixels per view
    allow_any_views: bool = False

    def validate(self) -> None:
        """Raise :class:`~rtsplat.errors.ConfigError` with a clear message for any bad setting."""
        try:
            check_scene_name(self.scene)
        except ValueError as exc:
            raise ConfigError(str(exc)) from None
        lo, hi = VIEW_RANGE
        if self.allow_any_views:
            if not 1 <= self.views <= 1000:
                raise ConfigError(f"views must be in 1-1000, got {self.views}")
        elif not lo <= self.views <= hi:
            raise ConfigError(f"views must be in {lo}-{hi}, got {self.views} (tests may override this)")
        for name, value, vlo, vhi in (
            ("width", self.width, 16, 4096),
            ("height", self.height, 16, 4096),
            ("spp", self.spp, 1, 65536),
            ("layer_spp", self.layer_spp, 0, 65536),
            ("layers_every", self.layers_every, 1, 1000),
            ("max_depth", self.max_depth, 2, 128),
            ("point_stride", self.point_stride, 1, 1024),
        ):
            if not vlo <= value <= vhi:
                raise ConfigError(f"{name} must be in {vlo}-{vhi}, got {value}")
        if not 0 <= self.seed < 2**31:
            raise ConfigError(f"seed must be in 0-{2**31 - 1}, got {self.seed}")


def texture_scale(config: SynthConfig) -> float:
    """Texture resolution relative to the defaults, which suit 200-pixel-wide renders."""
    return config.width / 200.0


@dataclass
class SynthSummary:
    out_dir: Path
    views: int
    transparent_pixels: int  # total number of mask pixels over all views
    layer_check: dict  # residual of reflection + transmission against the full render


def view_name(i: int) -> str:
    return f"{i:04d}"


def view_seed(seed: int, i: int) -> int:
    return (seed * 7919 + i * 104729 + 1) % 2**31


def to_srgb8(x: np.ndarray) -> np.ndarray:
    """Linear float image -> 8-bit sRGB image (clipped, rounded)."""
    return to_uint(linear_to_srgb(x), 8)


def _write_png(path: Path, image: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    write_png(path, image)


def _camera_json(name: str, cam: Camera) -> dict:
    return {
        "name": name,
        "width": int(cam.width),
        "height": int(cam.height),
        "K": cam.K.double().tolist(),
        "world_to_camera": cam.world_to_camera.double().tolist(),
    }


def _surface_points(scene, camera: Camera, stride: int):
    """First opaque hits (see-through shapes are skipped) of a grid of pixel-centre rays.

    Returns (points [M, 3], pixel positions [M, 2] (u, v), pixel indices [M, 2] (row, col)).
    """
    import mitsuba as mi

    from rtsplat.synth.cameras import pixel_rays
    from rtsplat.synth.render import is_see_through, see_through_flags

    h, w = int(camera.height), int(camera.width)
    jj, ii = np.mgrid[stride // 2 : h : stride, stride // 2 : w : stride]
    u, v = ii.ravel() + 0.5, jj.ravel() + 0.5
    o, d = pixel_rays(camera, u, v)
    flags = see_through_flags()
    pts, uv, rc = [], [], []
    origin = mi.Point3f(*o.tolist())
    for k, dk in enumerate(d.tolist()):
        ray = mi.Ray3f(origin, mi.Vector3f(*dk))
        si = scene.ray_intersect(ray)
        for _ in range(8):
            if not is_see_through(si, flags):
                break
            si = scene.ray_intersect(si.spawn_ray(ray.d))
        if si.is_valid() and not is_see_through(si, flags):
            pts.append(np.asarray(si.p, dtype=np.float64))
            uv.append((u[k], v[k]))
            rc.append((jj.ravel()[k], ii.ravel()[k]))
    return np.array(pts).reshape(-1, 3), np.array(uv).reshape(-1, 2), np.array(rc, dtype=int).reshape(-1, 2)


def _write_layers(root: Path, stem: str, view: ViewRender) -> None:
    _write_png(root / "layers" / "reflection" / f"{stem}.png", to_srgb8(view.reflection))
    _write_png(root / "layers" / "transmission" / f"{stem}.png", to_srgb8(view.transmission))
    (root / "layers" / "linear").mkdir(parents=True, exist_ok=True)
    np.savez_compressed(
        root / "layers" / "linear" / f"{stem}.npz",
        full=view.full.astype(np.float16),
        reflection=view.reflection.astype(np.float16),
        transmission=view.transmission.astype(np.float16),
        scatter=view.scatter.astype(np.float16),
    )


class _LayerCheck:
    """Accumulates reflection + transmission - full over see-through pixels.

    Means are over pixels x channels; the z score uses per-pixel residuals (the mean over RGB),
    which are independent across pixels, so |z| < ~3 means "zero within Monte-Carlo noise".
    """

    def __init__(self) -> None:
        self.n = 0  # pixels x channels
        self.pixels = 0
        self.sum = 0.0
        self.sum_abs = 0.0
        self.sum_pixel_sq = 0.0
        self.sum_full = 0.0
        self.sum_reflection = 0.0
        self.sum_stderr = 0.0

    def add(self, view: ViewRender) -> None:
        m = view.mask
        if not m.any() or view.reflection is None:
            return
        d = (view.reflection[m] + view.transmission[m] - view.full[m]).astype(np.float64)  # [P, 3]
        self.n += d.size
        self.pixels += len(d)
        self.sum += float(d.sum())
        self.sum_abs += float(np.abs(d).sum())
        self.sum_pixel_sq += float((d.mean(axis=1) ** 2).sum())
        self.sum_full += float(view.full[m].sum())
        self.sum_reflection += float(view.reflection[m].sum())
        self.sum_stderr += float(view.layer_stderr[m].sum())

    def result(self) -> dict:
        if self.n == 0:
            return {"pixels_channels": 0}
        mean = self.sum / self.n
        pixel_std = max(self.sum_pixel_sq / self.pixels - mean**2, 0.0) ** 0.5
        mean_full = self.sum_full / self.n
        return {
            "pixels_channels": self.n,
            "mean_full": mean_full,
            "mean_reflection": self.sum_reflection / self.n,
            "mean_residual": mean,
            "relative_residual": mean / mean_full if mean_full > 0 else 0.0,
            "mean_abs_residual": self.sum_abs / self.n,
            "pixel_residual_std": pixel_std,
            "residual_z": mean / (pixel_std / self.pixels**0.5) if pixel_std > 0 else 0.0,
            "mean_layer_stderr": self.sum_stderr / self.pixels,
            "space": "linear RGB, see-through pixels only (mask), residual = R + T - full",
        }


def _scene_json(config: SynthConfig, spec: SceneSpec, cams: list[Camera], check: dict) -> dict:
    import mitsuba as mi

    from rtsplat import __version__

    return {
        "format": FORMAT,
        "generator": f"rtsplat {__version__} rtsplat.synth",
        "scene": spec.name,
        "seed": config.seed,
        "config": asdict(config),
        "params": spec.params,
        "texture_scale": texture_scale(config),
        "transparent_shapes": list(spec.transparent),
        "camera_path": {"type": spec.orbit.TYPE, **asdict(spec.orbit)},
        "mitsuba_version": mi.__version__,
        "mitsuba_variant": VARIANT,
        "sampler": {"type": SAMPLER, "spp": effective_spp(config.spp)},
        "integrator": {"type": "volpath", "max_depth": config.max_depth, "rr_depth": 5},
        "has_layers": config.layer_spp > 0,
        "layer_views": [
            view_name(i) + ".png" for i in range(len(cams)) if config.layer_spp and i % config.layers_every == 0
        ],
        "images": [view_name(i) + ".png" for i in range(len(cams))],
        "files": {
            "images/<stem>.png": "full render, sRGB 8-bit",
            "transparent_masks/<stem>.png": "8-bit, 255 = a see-through surface is the first hit "
            "of the pixel-centre ray, 0 elsewhere",
            "sparse/0/": "ground-truth COLMAP model (PINHOLE, cam_from_world), .bin and .txt",
            "cameras.json": "ground-truth cameras: K (3x3) and world_to_camera (4x4, OpenCV axes, "
            "pixel centres at i + 0.5)",
            "layers/reflection/<stem>.png": "reflection layer, sRGB 8-bit (display space: PNG layers "
            "do not add up exactly)",
            "layers/transmission/<stem>.png": "transmission layer (includes scatter), sRGB 8-bit",
            "layers/linear/<stem>.npz": "float16 linear RGB [H, W, 3] arrays full, reflection, "
            "transmission, scatter; reflection + transmission = full "
            "up to Monte-Carlo noise",
        },
        "layer_definition": "At the first see-through hit: reflection = delta-reflection lobe, "
        "transmission = delta-transmission lobe + scatter (other lobes, e.g. the "
        "film's diffuse part). Elsewhere reflection = 0, transmission = full.",
        "layer_check": check,
        **({"family": spec.family} if spec.family else {}),
    }


def render_dataset(
    config: SynthConfig, out_dir: Path, *, overwrite: bool = False, progress: bool = True
) -> SynthSummary:
    """Render ``config.scene`` into ``out_dir`` (see the module docstring for the layout)."""
    from tqdm import tqdm

    config.validate()
    out_dir = Path(out_dir)
    if out_dir.exists() and not overwrite:
        raise PipelineError("the output exists", path=out_dir, fix="pass overwrite=True (--overwrite) to replace it")
    # only a folder that synth wrote itself (its marker) or an empty one is replaced; a failure or
    # ctrl-C leaves no partial dataset (nor harms an old one)
    with output_dir(out_dir, "synth") as tmp:
        set_variant()
        work = tmp / "_work"
        work.mkdir()
        spec = build_any(config.scene, config.seed, work, texture_scale=texture_scale(config))
        cams = spec.orbit.cameras(config.views, config.width, config.height)
        scene = load_scene(spec.elements, cams, config.spp, config.max_depth)
        check = _LayerCheck()
        reach_views: tuple[list, list, list] = ([], [], [])  # cameras, masks, reflection luminance
        colmap_images: list[ColmapImage] = []
        xyz, rgb, tracks = [], [], []
        transparent_pixels = 0
        bar = tqdm(range(config.views), desc=f"synth {config.scene}", unit="view", disable=not progress)
        for i in bar:
            stem = view_name(i)
            layer_spp = config.layer_spp if i % config.layers_every == 0 else 0
            view = render_view(scene, i, cams[i], config.spp, view_seed(config.seed, i), config.max_depth, layer_spp)
            image8 = to_srgb8(view.full)
            _write_png(tmp / "images" / f"{stem}.png", image8)
            _write_png(tmp / "transparent_masks" / f"{stem}.png", view.mask.astype(np.uint8) * 255)
            if view.reflection is not None:
                _write_layers(tmp, stem, view)
                for kept, value in zip(reach_views, (cams[i], view.mask, view.reflection @ LUMINANCE), strict=True):
                    kept.append(value)
            check.add(view)
            transparent_pixels += int(view.mask.sum())
            pts, uv, rc = _surface_points(scene, cams[i], config.point_stride)
            first = len(xyz)
            xyz.extend(pts)
            rgb.extend(image8[rc[:, 0], rc[:, 1]])
            tracks.extend([[(i + 1, k)] for k in range(len(pts))])
            colmap_images.append(
                ColmapImage(
                    name=f"{stem}.png",
                    K=cams[i].K.numpy(),
                    world_to_camera=cams[i].world_to_camera.numpy(),
                    width=config.width,
                    height=config.height,
                    points2d=uv,
                    point3d_ids=np.arange(first + 1, first + 1 + len(pts), dtype=np.int64),
                )
            )
        bar.close()
        write_sparse_model(
            tmp / "sparse" / "0",
            colmap_images,
            ColmapPoints(np.array(xyz).reshape(-1, 3), np.array(rgb, dtype=np.uint8).reshape(-1, 3), tracks),
        )
        (tmp / "cameras.json").write_text(
            json.dumps(
                {
                    "convention": "OpenCV axes (x right, y down, z forward), world_to_camera, "
                    "pixel centres at (i + 0.5, j + 0.5)",
                    "cameras": [_camera_json(f"{view_name(i)}.png", c) for i, c in enumerate(cams)],
                },
                indent=1,
            )
        )
        result = check.result()
        description = _scene_json(config, spec, cams, result)
        if reach_views[0]:
            description["reflection_reach"] = reach_record(reflection_reach(scene, *reach_views))
        (tmp / "scene.json").write_text(json.dumps(description, indent=1))
        shutil.rmtree(work)
    return SynthSummary(out_dir, config.views, transparent_pixels, result)
