"""How far away is what the glass reflects, on a synthetic scene: ``python -m rtsplat.bench.reflection_reach``.

The specular branch looks a reflection up by direction alone (the environment map at the reflected
direction), so it can show what lies far from the glass, not what is near it: a near reflection moves
against the reflected direction as the viewer moves. For a scene made by ``rtsplat synth`` the scene is
known, so each glass pixel's reflection can be followed: the ray through the pixel centre goes to its
first hit, which must be a see-through surface (the pixel is in the dataset's mask), is mirrored about
that surface's shading normal (what Mitsuba reflects about), and goes on. Where the mirrored ray meets a
surface, the pixel reflects something at that finite distance; where it leaves the scene, it reflects the
environment at infinity. Printed per scene: the share of the glass pixels and of the true reflection
layer (its luminance, linear) that reflect something near, and the median distance to it.

    python -m rtsplat.bench.reflection_reach --dataset demo/data/dome --dataset demo/data/cabin
"""

from __future__ import annotations

import argparse
import json
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from rtsplat.errors import PipelineError


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


def dataset_reach(dataset: Path, stride: int = 1) -> ReflectionReach:
    """:func:`reflection_reach` on the views of a ``rtsplat synth`` dataset that have ground-truth layers,
    weighted by the luminance of the true reflection layer."""
    import torch

    from rtsplat.camera import Camera
    from rtsplat.io.images import read_mask
    from rtsplat.synth.render import load_scene, set_variant
    from rtsplat.synth.scenes import build_scene, params_from_dict

    description_file = dataset / "scene.json"
    if not description_file.is_file():
        raise PipelineError("not a synthetic dataset", path=description_file,
                            fix="pass a folder written by `rtsplat synth`")
    description = json.loads(description_file.read_text())
    name = description["scene"]
    records = {Path(c["name"]).stem: c for c in json.loads((dataset / "cameras.json").read_text())["cameras"]}
    layers = dataset / "layers" / "linear"
    views = [stem for stem in sorted(records) if (layers / f"{stem}.npz").is_file()]
    if not views:
        raise PipelineError("no view has ground-truth layers", path=layers,
                            fix="synthesize with --layers-every N")
    cameras, masks, weights = [], [], []
    for stem in views:
        c = records[stem]
        cameras.append(Camera(K=torch.tensor(c["K"], dtype=torch.float64),
                              world_to_camera=torch.tensor(c["world_to_camera"], dtype=torch.float64),
                              width=int(c["width"]), height=int(c["height"])))
        masks.append(read_mask(dataset / "transparent_masks" / f"{stem}.png"))
        with np.load(layers / f"{stem}.npz") as z:
            reflection = z["reflection"].astype(np.float64)
        weights.append(reflection @ np.array([0.2126, 0.7152, 0.0722]))  # luminance, linear RGB
    set_variant()
    with tempfile.TemporaryDirectory() as workdir:
        spec = build_scene(name, int(description["seed"]), Path(workdir), params_from_dict(name, description["params"]),
                           float(description.get("texture_scale", 1.0)))
        scene = load_scene(spec.elements, [], spp=1)
        return reflection_reach(scene, cameras, masks, weights, stride)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--dataset", type=Path, action="append", required=True,
                        help="a dataset written by `rtsplat synth` with ground-truth layers (repeatable)")
    parser.add_argument("--stride", type=int, default=1, help="follow every N-th pixel in each direction (default 1)")
    args = parser.parse_args(argv)
    header = f"{'dataset':<28} {'glass px':>9} {'near px':>8} {'near share':>10} {'of reflection':>13}"
    print(f"{header} {'median dist':>11}")
    for dataset in args.dataset:
        reach = dataset_reach(dataset, args.stride)
        print(f"{str(dataset):<28} {reach.glass_pixels:>9} {reach.near_pixels:>8} {reach.near_share:>10.2f} "
              f"{reach.near_weight:>13.2f} {reach.median_distance:>11.2f}")


if __name__ == "__main__":
    main()
