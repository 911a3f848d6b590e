"""``effects: auto``: decide per scene which branches the model runs, and say why."""

from __future__ import annotations

from rtsplat.model.rtmodel import ActiveEffects
from rtsplat.train_config import Effects


def decide_effects(
    config: Effects, transparent_fraction: float, roi_source: str | None
) -> tuple[ActiveEffects, dict]:
    """Transmission (auto): on iff the training masks mark transparent pixels.

    Specular (auto): on iff reflections are asked for, i.e. the scene has transparent pixels (a
    see-through surface reflects) or the user gave a region of interest in the config
    (``roi_source == "config"``). A region of interest that ``prepare`` merely estimated from the
    SfM points (``"estimated"``) on a scene without glass does not ask for reflections: that scene
    is trained as plain 2DGS radiance, without environment map or specular network.
    """
    reasons = {}
    if config.transmission == "auto":
        transmission = transparent_fraction > 0
        reasons["transmission"] = (
            f"auto: {transparent_fraction:.2%} of training pixels are marked transparent"
            if transmission else "auto: the training masks have no transparent pixel"
        )
    else:
        transmission = config.transmission == "on"
        reasons["transmission"] = f"config: {config.transmission}"
    if config.specular == "auto":
        if transparent_fraction > 0:
            specular, why = True, "auto: the scene has transparent (reflecting) surfaces"
        elif roi_source == "config":
            specular, why = True, "auto: a region of interest for reflections is given in the config"
        else:
            specular = False
            why = ("auto: no transparent pixel and no region of interest given in the config "
                   f"(roi: {roi_source or 'none'})")
        reasons["specular"] = why
    else:
        specular = config.specular == "on"
        reasons["specular"] = f"config: {config.specular}"
    return ActiveEffects(transmission=transmission, specular=specular), reasons
