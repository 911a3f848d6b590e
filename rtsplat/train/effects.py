"""``effects: auto``: decide per scene which branches the model runs, and say why."""

from __future__ import annotations

from rtsplat.model.rtmodel import ActiveEffects
from rtsplat.train.config import Effects


def decide_effects(config: Effects, transparent_fraction: float, has_roi: bool) -> tuple[ActiveEffects, dict]:
    """Transmission: on when the training masks have transparent pixels (auto), specular: on when
    the scene has a region of interest, i.e. reflections are requested (auto)."""
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
        specular = has_roi
        reasons["specular"] = "auto: the scene has a region of interest" if has_roi else "auto: no region of interest"
    else:
        specular = config.specular == "on"
        reasons["specular"] = f"config: {config.specular}"
    return ActiveEffects(transmission=transmission, specular=specular), reasons
