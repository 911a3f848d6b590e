"""Scene lookup for ``rtsplat synth``: a named scene (:data:`rtsplat.synth.scenes.SCENES`) or a member of the
scene family (``family/<kind>-<seed>``, :mod:`rtsplat.synth.family`)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from rtsplat.synth import family
from rtsplat.synth.family import KINDS, PREFIX, build_member, is_family_name, parse_name
from rtsplat.synth.scenes import SCENES, SceneSpec, build_scene, params_from_dict, see_through_samples

SCENE_HELP = f"one of: {', '.join(SCENES)}, or {PREFIX}<kind>-<seed> with a kind of: {', '.join(KINDS)}"


def check_scene_name(name: str) -> None:
    """``ValueError`` naming the choices when ``name`` is neither a named scene nor a family member."""
    if is_family_name(name):
        parse_name(name)
    elif name not in SCENES:
        raise ValueError(f"unknown scene {name!r}; choose {SCENE_HELP}")


def build_any(name: str, seed: int, workdir: Path, texture_scale: float = 1.0) -> SceneSpec:
    """Scene ``name`` built for rendering. A named scene takes its textures and objects from ``seed``; a family
    member from the seed in its name (``seed`` then only seeds the render's noise)."""
    check_scene_name(name)
    if is_family_name(name):
        return build_member(name, workdir, texture_scale)
    return build_scene(name, seed, workdir, texture_scale=texture_scale)


def see_through_any(name: str, params: dict, spacing: float = 0.02) -> tuple[np.ndarray, np.ndarray]:
    """Points [N, 3] on scene ``name``'s see-through surfaces and their unit normals (up to sign): a named
    scene's from its parameters as ``scene.json`` records them (:func:`rtsplat.synth.scenes.see_through_samples`),
    a family member's sampled from the geometry its images were rendered with
    (:func:`rtsplat.synth.family.see_through_samples`; ``params`` is not needed there, the name draws them)."""
    check_scene_name(name)
    if is_family_name(name):
        return family.see_through_samples(name, spacing=spacing)
    return see_through_samples(name, params_from_dict(name, params), spacing=spacing)
