"""How far away is what the glass reflects, on a synthetic scene: ``python -m rtsplat.bench.reflection_reach``.

:mod:`rtsplat.synth.reach` follows every glass pixel's reflection in the Mitsuba scene a dataset was
rendered from. Printed per dataset: the share of the glass pixels and of the true reflection layer (its
luminance, linear) that reflect something near, and the median distance to it. Datasets synthesized now
carry the same numbers in their ``scene.json`` (``reflection_reach``); this recomputes them, for any stride.

    python -m rtsplat.bench.reflection_reach --dataset demo/data/dome --dataset demo/data/cabin
"""

from __future__ import annotations

import argparse
import json
import tempfile
from pathlib import Path

import numpy as np

from rtsplat.errors import PipelineError
from rtsplat.synth.reach import LUMINANCE, ReflectionReach, reflection_reach


def dataset_reach(dataset: Path, stride: int = 1) -> ReflectionReach:
    """:func:`reflection_reach` on the views of a ``rtsplat synth`` dataset that have ground-truth layers,
    weighted by the luminance of the true reflection layer."""
    import torch

    from rtsplat.camera import Camera
    from rtsplat.io.images import read_mask
    from rtsplat.synth.family import build_member, is_family_name
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
        weights.append(reflection @ LUMINANCE)
    set_variant()
    with tempfile.TemporaryDirectory() as workdir:
        texture_scale = float(description.get("texture_scale", 1.0))
        if is_family_name(name):  # a family member is rebuilt from the kind and seed in its name
            spec = build_member(name, Path(workdir), texture_scale)
        else:
            spec = build_scene(name, int(description["seed"]), Path(workdir),
                               params_from_dict(name, description["params"]), texture_scale)
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
    from rtsplat.errors import run_command

    raise SystemExit(run_command("python -m rtsplat.bench.reflection_reach", main))
