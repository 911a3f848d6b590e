"""Procedural benchmark scenes: thin see-through surfaces over photo-textured content.

Each scene is a function of a small parameter dataclass and a seed and returns a
:class:`SceneSpec`: the Mitsuba scene dictionary (without sensor and integrator), the ids of
the shapes that are *see-through* (their first hit is what ``transparent_masks`` marks), and the
camera orbit. World units are metres, z is up, the floor is the plane z = 0.

Scenes:

* ``dome``   - a thin glass dome (``thindielectric``) over textured objects on a textured floor;
* ``cabin``  - a closed car-like shell whose objects are visible only through glass windows;
* ``film``   - a curved, tinted, partly scattering plastic film in front of a textured wall
  (a ``blendbsdf`` of a tinted ``thindielectric`` and ``diffuse`` dots far below pixel size);
* ``opaque`` - the ``dome`` content without the dome (control scene, no see-through surface).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from rtsplat.synth.cameras import CameraPath, OrbitPath
from rtsplat.synth.textures import FLOOR_PHOTOS, OBJECT_PHOTOS, environment_map, photo_crop, tile_mosaic


@dataclass
class SceneSpec:
    """A built scene: Mitsuba elements, see-through shape ids, camera path, parameters, and for a member
    of the scene family (:mod:`rtsplat.synth.family`) its kind, seed, half and drawn parameters."""

    name: str
    elements: dict
    transparent: tuple[str, ...]
    orbit: CameraPath
    params: dict = field(default_factory=dict)
    family: dict | None = None


@dataclass(frozen=True)
class ContentParams:
    """Textured objects on a textured floor, shared by all scenes."""

    n_objects: int = 4
    placement_radius: float = 0.7  # objects' centres lie within this distance of the centre
    object_size: tuple[float, float] = (0.16, 0.28)  # half size of cubes / radius of spheres
    floor_half_size: float = 6.0
    floor_tiles: int = 8  # the floor is floor_tiles x floor_tiles random photo crops
    env_radiance: float = 1.0  # scale of the environment map
    # Texture resolutions (pixels) at texture_scale 1 (200-pixel-wide renders). Mitsuba's bitmap
    # texture has no MIP-mapping: textures much finer than the pixels alias into noise, so their
    # resolution follows the render's (texture_scale = width / 200).
    floor_tile_px: int = 64
    object_texture_px: int = 48
    env_height_px: int = 512


@dataclass(frozen=True)
class DomeParams:
    content: ContentParams = ContentParams()
    dome_radius: float = 1.5
    dome_center_z: float = -0.4  # the dome is the part of this sphere above the floor
    eta: float = 1.5


@dataclass(frozen=True)
class CabinParams:
    content: ContentParams = ContentParams(n_objects=3, placement_radius=0.55, object_size=(0.12, 0.2))
    half_length: float = 1.2
    half_width: float = 0.7
    body_height: float = 0.6  # opaque lower body; the cabin floor is its top
    window_height: float = 0.7
    pillar_half: float = 0.04
    eta: float = 1.5
    tint: tuple[float, float, float] = (1.0, 1.0, 1.0)  # the windows' transmittance (RGB)


@dataclass(frozen=True)
class FilmParams:
    content: ContentParams = ContentParams(n_objects=2, placement_radius=0.4, object_size=(0.15, 0.25))
    curvature_radius: float = 2.4
    arc_deg: float = 70.0
    height: float = 1.5
    tint: tuple[float, float, float] = (0.95, 0.78, 0.5)
    scatter_weight: float = 0.25  # fraction of the film covered by diffuse dots (rounded to 1/16)
    dot_pitch: float = 0.001  # texel size of the dot pattern (m) at texture_scale 1; a pixel sees ~2 cm
    scatter_albedo: tuple[float, float, float] = (0.85, 0.85, 0.9)
    eta: float = 1.5
    wall_distance: float = 1.6


@dataclass(frozen=True)
class OpaqueParams:
    content: ContentParams = ContentParams()


def _xf(matrix: np.ndarray):
    import mitsuba as mi

    return mi.ScalarTransform4f(np.asarray(matrix, dtype=np.float64).tolist())


def _trs(translate=(0.0, 0.0, 0.0), yaw_deg: float = 0.0, scale=(1.0, 1.0, 1.0), pitch_deg: float = 0.0):
    """4x4 = translate @ rotate_z(yaw) @ rotate_x(pitch) @ scale."""
    c, s = math.cos(math.radians(yaw_deg)), math.sin(math.radians(yaw_deg))
    rz = np.array([[c, -s, 0, 0], [s, c, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]], dtype=np.float64)
    c, s = math.cos(math.radians(pitch_deg)), math.sin(math.radians(pitch_deg))
    rx = np.array([[1, 0, 0, 0], [0, c, -s, 0], [0, s, c, 0], [0, 0, 0, 1]], dtype=np.float64)
    m = np.diag([*np.broadcast_to(np.asarray(scale, dtype=np.float64), (3,)), 1.0])
    t = np.eye(4)
    t[:3, 3] = translate
    return t @ rz @ rx @ m


def _textured(image: np.ndarray, tiles: float = 1.0) -> dict:
    import mitsuba as mi

    tex = {"type": "bitmap", "bitmap": mi.Bitmap(np.ascontiguousarray(image, dtype=np.float32))}
    if tiles != 1.0:
        tex["to_uv"] = mi.ScalarTransform4f().scale([tiles, tiles, 1.0])
    return {"type": "diffuse", "reflectance": tex}


def _px(base: int, texture_scale: float) -> int:
    return int(min(max(8, round(base * texture_scale)), 4096))


def _environment(content: ContentParams, texture_scale: float) -> dict:
    import mitsuba as mi

    env = environment_map(_px(content.env_height_px, texture_scale)) * content.env_radiance
    # Mitsuba's envmap is y-up; rotating +90 degrees about x maps local +y to world +z.
    return {
        "type": "envmap",
        "bitmap": mi.Bitmap(env),
        "to_world": _xf(_trs(pitch_deg=90.0)),
    }


def _floor(content: ContentParams, rng: np.random.Generator, texture_scale: float) -> dict:
    """A square floor textured with a mosaic of random crops of photographs."""
    h, n = content.floor_half_size, content.floor_tiles
    return {
        "type": "rectangle",
        "to_world": _xf(_trs(scale=(h, h, 1.0))),
        "bsdf": _textured(tile_mosaic(FLOOR_PHOTOS, n, n, _px(content.floor_tile_px, texture_scale), rng)),
    }


def _objects(
    content: ContentParams,
    rng: np.random.Generator,
    texture_scale: float,
    base_z: float = 0.0,
    center=(0.0, 0.0),
    box: tuple[float, float] | None = None,
) -> dict:
    """Random photo-textured spheres and cubes resting on the plane z = base_z.

    Centres lie within ``content.placement_radius`` of ``center``, or, when ``box`` (half extents
    in x and y around ``center``) is given, anywhere such that the whole object stays inside the box.
    Objects never overlap; ``ValueError`` when they cannot be placed.
    """
    out: dict = {}
    placed: list[tuple[float, float, float]] = []
    lo, hi = content.object_size
    for k in range(content.n_objects):
        for _attempt in range(500):
            size = float(rng.uniform(lo, hi))
            reach = size * math.sqrt(2.0)  # a yawed cube's half diagonal (>= a sphere's radius)
            if box is None:
                r = content.placement_radius * math.sqrt(float(rng.uniform(0.0, 1.0)))
                a = float(rng.uniform(0.0, 2 * math.pi))
                x, y = center[0] + r * math.cos(a), center[1] + r * math.sin(a)
            else:
                fx, fy = box[0] - reach, box[1] - reach
                if fx <= 0 or fy <= 0:
                    continue
                x = center[0] + float(rng.uniform(-fx, fx))
                y = center[1] + float(rng.uniform(-fy, fy))
            if all(math.hypot(x - px, y - py) > 1.1 * (reach + pr) for px, py, pr in placed):
                break
        else:
            raise ValueError(
                f"could not place {content.n_objects} objects without overlap; "
                "lower n_objects or object_size, or enlarge the placement area"
            )
        placed.append((x, y, reach))
        photo = OBJECT_PHOTOS[int(rng.integers(len(OBJECT_PHOTOS)))]
        t = _px(content.object_texture_px, texture_scale)
        bsdf = _textured(photo_crop(photo, (t, t), rng))
        if k % 2 == 0:
            yaw = float(rng.uniform(0.0, 90.0))
            out[f"object_{k}"] = {
                "type": "cube",
                "to_world": _xf(_trs((x, y, base_z + size), yaw, size)),
                "bsdf": bsdf,
            }
        else:
            out[f"object_{k}"] = {
                "type": "sphere",
                "to_world": _xf(_trs((x, y, base_z + size), float(rng.uniform(0, 360)), size, 90.0)),
                "bsdf": bsdf,
            }
    return out


def _photo_order(rng: np.random.Generator) -> list[str]:
    return [OBJECT_PHOTOS[i] for i in rng.permutation(len(OBJECT_PHOTOS))]


def _glass(eta: float, tint: tuple[float, float, float] = (1.0, 1.0, 1.0)) -> dict:
    """Thin glass (``thindielectric``); ``tint``: its transmittance per RGB channel (1: clear)."""
    glass = {"type": "thindielectric", "int_ior": float(eta), "ext_ior": 1.0}
    if tuple(tint) != (1.0, 1.0, 1.0):
        glass["specular_transmittance"] = {"type": "rgb", "value": [float(t) for t in tint]}
    return glass


def build_dome(params: DomeParams, seed: int, workdir: Path, texture_scale: float = 1.0) -> SceneSpec:
    rng = np.random.default_rng(seed)
    c = params.content
    elements = {"env": _environment(c, texture_scale), "floor": _floor(c, rng, texture_scale)}
    elements.update(_objects(c, rng, texture_scale))
    r = params.dome_radius
    elements["dome"] = {
        "type": "sphere",
        "center": [0.0, 0.0, float(params.dome_center_z)],
        "radius": float(r),
        "bsdf": _glass(params.eta),
    }
    top = params.dome_center_z + r
    orbit = OrbitPath(target=(0.0, 0.0, 0.45 * top), radius=4.0, height_mid=2.0, height_amplitude=0.6)
    return SceneSpec("dome", elements, ("dome",), orbit, asdict(params))


def build_opaque(params: OpaqueParams, seed: int, workdir: Path, texture_scale: float = 1.0) -> SceneSpec:
    dome = build_dome(DomeParams(content=params.content), seed, workdir, texture_scale)
    elements = {k: v for k, v in dome.elements.items() if k != "dome"}
    return SceneSpec("opaque", elements, (), dome.orbit, asdict(params))


def _cabin_panes(params: CabinParams) -> dict[str, np.ndarray]:
    """The cabin's four glass panes: 4x4 transforms of Mitsuba's rectangle, which spans [-1, 1]^2 in its
    local xy plane with normal +z. They reach slightly into body and roof: no cracks."""
    L, W, B, H = params.half_length, params.half_width, params.body_height, params.window_height
    zc, hz = B + H / 2, H / 2 + 0.01
    return {
        "window_front": _trs((L, 0, zc), 90.0, (W, hz, 1.0), 90.0),
        "window_back": _trs((-L, 0, zc), 90.0, (W, hz, 1.0), 90.0),
        "window_left": _trs((0, W, zc), 0.0, (L, hz, 1.0), 90.0),
        "window_right": _trs((0, -W, zc), 0.0, (L, hz, 1.0), 90.0),
    }


def build_cabin(params: CabinParams, seed: int, workdir: Path, texture_scale: float = 1.0) -> SceneSpec:
    rng = np.random.default_rng(seed)
    c = params.content
    photos = _photo_order(rng)
    L, W, B, H, p = (
        params.half_length,
        params.half_width,
        params.body_height,
        params.window_height,
        params.pillar_half,
    )
    elements = {"env": _environment(c, texture_scale), "floor": _floor(c, rng, texture_scale)}
    tb = _px(128, texture_scale)  # body and roof faces are up to 2.5 m wide
    elements["body"] = {
        "type": "cube",
        "to_world": _xf(_trs((0, 0, B / 2), 0.0, (L, W, B / 2))),
        "bsdf": _textured(photo_crop(photos[0], (tb, tb), rng)),
    }
    roof_t = 0.04
    elements["roof"] = {
        "type": "cube",
        "to_world": _xf(_trs((0, 0, B + H + roof_t), 0.0, (L + 0.05, W + 0.05, roof_t))),
        "bsdf": _textured(photo_crop(photos[1], (tb, tb), rng)),
    }
    dark = {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.08, 0.08, 0.09]}}
    for i, (sx, sy) in enumerate([(1, 1), (1, -1), (-1, 1), (-1, -1)]):
        elements[f"pillar_{i}"] = {
            "type": "cube",
            "to_world": _xf(_trs((sx * L, sy * W, B + H / 2), 0.0, (p, p, H / 2 + 0.01))),
            "bsdf": dark,
        }
    panes = _cabin_panes(params)
    for name, m in panes.items():
        elements[name] = {"type": "rectangle", "to_world": _xf(m), "bsdf": _glass(params.eta, params.tint)}
    # objects stand on the cabin floor (the body's top) and stay clear of the panes and pillars
    margin = 0.03
    elements.update(_objects(c, rng, texture_scale, base_z=B, box=(L - 2 * p - margin, W - margin)))
    orbit = OrbitPath(target=(0.0, 0.0, B + 0.3), radius=3.6, height_mid=1.5, height_amplitude=0.35)
    return SceneSpec("cabin", elements, tuple(panes), orbit, asdict(params))


def _film_sheet(params: FilmParams, n_u: int, n_v: int) -> tuple[np.ndarray, np.ndarray]:
    """Vertices [n_v * n_u, 3] (row by row, rising in z) and unit normals of the film: a cylindrical sheet
    bulging towards -y, its axis at y = R so that its apex is at y = 0; normals face -y (the cameras'
    side)."""
    R, half = params.curvature_radius, math.radians(params.arc_deg) / 2
    phi = np.tile(np.linspace(-half, half, n_u), n_v)
    z = np.repeat(np.linspace(0.0, params.height, n_v), n_u)
    points = np.stack([R * np.sin(phi), R - R * np.cos(phi), z], 1)
    normals = np.stack([np.sin(phi), -np.cos(phi), np.zeros_like(phi)], 1)
    return points, normals


def _write_film_obj(path: Path, params: FilmParams, n_u: int = 48, n_v: int = 2) -> None:
    """A cylindrical sheet bulging towards -y; normals face -y (the cameras' side)."""
    points, normals = _film_sheet(params, n_u, n_v)
    lines = [f"v {x:.6f} {y:.6f} {z:.6f}" for x, y, z in points]
    for j in range(n_v):
        for i in range(n_u):
            lines.append(f"vt {i / (n_u - 1):.6f} {j / (n_v - 1):.6f}")
    lines += [f"vn {x:.6f} {y:.6f} {z:.1f}" for x, y, z in normals]
    for j in range(n_v - 1):
        for i in range(n_u - 1):
            a, b = j * n_u + i + 1, j * n_u + i + 2
            c, d = a + n_u, b + n_u
            # counter-clockwise seen from -y, consistent with the normals
            lines.append(f"f {a}/{a}/{a} {c}/{c}/{c} {b}/{b}/{b}")
            lines.append(f"f {b}/{b}/{b} {c}/{c}/{c} {d}/{d}/{d}")
    path.write_text("\n".join(lines) + "\n")


def _dot_pattern(params: FilmParams, texture_scale: float) -> dict:
    """The film's blend weight: an ordered-dither pattern of diffuse dots (weight 1) on clear film
    (weight 0), ``nearest`` filtered so that every point is *either* film or dot.

    A per-point blend (0 < weight < 1) of a delta and a smooth lobe is mis-weighted by Mitsuba
    3.9's ``blendbsdf.sample`` (it divides the mixed eval by a mixed pdf in which the delta
    lobe's discrete probability stands for a density: the reflection gets ~0.91 instead of 1), so
    its renders would not add up with the lobe-by-lobe ground-truth layers. With a binary weight
    ``blendbsdf`` is exact, and at pixel scale the dots still mix scattering into the film
    (like a perforated window film).
    """
    import mitsuba as mi

    bayer = np.array([[0, 8, 2, 10], [12, 4, 14, 6], [3, 11, 1, 9], [15, 7, 13, 5]], dtype=np.float64)
    dots = (bayer < round(16 * params.scatter_weight)).astype(np.float32)  # a 4 x 4 cell
    R, half = params.curvature_radius, math.radians(params.arc_deg) / 2
    pitch = params.dot_pitch / texture_scale
    cells_u = min(max(1, round(2 * half * R / (4 * pitch))), 2048)  # the film's u runs along the arc
    cells_v = min(max(1, round(params.height / (4 * pitch))), 2048)
    pattern = np.tile(dots, (cells_v, cells_u))[..., None]
    return {"type": "bitmap", "bitmap": mi.Bitmap(np.ascontiguousarray(pattern)), "filter_type": "nearest", "raw": True}


def build_film(params: FilmParams, seed: int, workdir: Path, texture_scale: float = 1.0) -> SceneSpec:
    rng = np.random.default_rng(seed)
    c = params.content
    photos = _photo_order(rng)
    elements = {"env": _environment(c, texture_scale), "floor": _floor(c, rng, texture_scale)}
    wall_w, wall_h = 3.0, 1.6
    elements["wall"] = {
        "type": "rectangle",
        # local +z normal -> world -y (facing the film and the cameras)
        "to_world": _xf(_trs((0, params.wall_distance, wall_h), 0.0, (wall_w, wall_h, 1.0), 90.0)),
        "bsdf": _textured(tile_mosaic(photos, 2, 4, _px(64, texture_scale), rng)),
    }
    elements.update(_objects(c, rng, texture_scale, center=(0.0, 0.5 * (params.wall_distance + 0.3))))
    obj = workdir / "film.obj"
    _write_film_obj(obj, params)
    elements["film"] = {
        "type": "obj",
        "filename": str(obj),
        "face_normals": False,
        "bsdf": {
            "type": "blendbsdf",
            "weight": _dot_pattern(params, texture_scale),
            "bsdf_0": {
                "type": "thindielectric",
                "int_ior": float(params.eta),
                "ext_ior": 1.0,
                "specular_transmittance": {"type": "rgb", "value": list(params.tint)},
            },
            "bsdf_1": {"type": "diffuse", "reflectance": {"type": "rgb", "value": list(params.scatter_albedo)}},
        },
    }
    orbit = OrbitPath(
        target=(0.0, 0.5, 0.7),
        radius=3.6,
        height_mid=1.3,
        height_amplitude=0.35,
        azimuth_start=-145.0,
        azimuth_span=110.0,
    )
    return SceneSpec("film", elements, ("film",), orbit, asdict(params))


@dataclass(frozen=True)
class SceneKind:
    builder: Callable[..., SceneSpec]
    params: type


SCENES: dict[str, SceneKind] = {
    "dome": SceneKind(build_dome, DomeParams),
    "cabin": SceneKind(build_cabin, CabinParams),
    "film": SceneKind(build_film, FilmParams),
    "opaque": SceneKind(build_opaque, OpaqueParams),
}


def build_scene(name: str, seed: int, workdir: Path, params=None, texture_scale: float = 1.0) -> SceneSpec:
    """Build scene ``name`` (one of :data:`SCENES`) with default or given parameters.

    ``texture_scale``: texture resolution relative to 200-pixel-wide renders (use width / 200).
    """
    if name not in SCENES:
        raise ValueError(f"unknown scene {name!r}; choose from {', '.join(SCENES)}")
    kind = SCENES[name]
    return kind.builder(params if params is not None else kind.params(), seed, workdir, texture_scale)


def params_from_dict(name: str, data: dict):
    """Scene ``name``'s parameter dataclass from its ``scene.json`` form (``params``: nested dicts, lists)."""
    if name not in SCENES:
        raise ValueError(f"unknown scene {name!r}; choose from {', '.join(SCENES)}")
    kind = SCENES[name].params

    def build(cls, values: dict):
        out = {}
        for f in dataclasses.fields(cls):
            if f.name not in values:
                continue
            v = values[f.name]
            out[f.name] = build(ContentParams, v) if f.name == "content" else (tuple(v) if isinstance(v, list) else v)
        return cls(**out)

    return build(kind, data)


def see_through_samples(name: str, params=None, spacing: float = 0.02) -> tuple[np.ndarray, np.ndarray]:
    """Points [N, 3] on scene ``name``'s see-through surfaces, about ``spacing`` apart (world units), and
    their unit normals: the geometry its transparent masks mark, to measure a reconstruction against.
    Sign of the normals: outward (dome), the rectangle's +z (cabin), towards the cameras (film); compare
    them up to sign. ``params``: the scene's parameter dataclass (default: its defaults)."""
    params = params if params is not None else SCENES[name].params()
    if name == "dome":
        r, c = params.dome_radius, np.array([0.0, 0.0, params.dome_center_z])
        n = int(4 * math.pi * r * r / spacing**2)
        i = np.arange(n) + 0.5  # a Fibonacci lattice: near-uniform points on the sphere
        z = 1 - 2 * i / n
        theta = math.pi * (1 + 5**0.5) * i
        normals = np.stack([np.sqrt(1 - z * z) * np.cos(theta), np.sqrt(1 - z * z) * np.sin(theta), z], 1)
        points = c + r * normals
        above = points[:, 2] > 0  # the dome is the part above the floor
        return points[above], normals[above]
    if name == "cabin":
        points, normals = [], []
        for m in _cabin_panes(params).values():
            nu = max(int(2 * np.linalg.norm(m[:3, 0]) / spacing), 2)
            nv = max(int(2 * np.linalg.norm(m[:3, 1]) / spacing), 2)
            u, v = np.meshgrid(np.linspace(-1, 1, nu), np.linspace(-1, 1, nv))
            local = np.stack([u.ravel(), v.ravel(), np.zeros(u.size), np.ones(u.size)], 1)
            points.append((local @ m.T)[:, :3])
            normal = np.linalg.inv(m[:3, :3]).T @ np.array([0.0, 0.0, 1.0])
            normals.append(np.broadcast_to(normal / np.linalg.norm(normal), (u.size, 3)))
        return np.concatenate(points), np.concatenate(normals)
    if name == "film":
        arc = params.curvature_radius * math.radians(params.arc_deg)
        return _film_sheet(params, max(int(arc / spacing), 2), max(int(params.height / spacing), 2))
    return np.zeros((0, 3)), np.zeros((0, 3))
