"""``effects: auto``: decide per scene which branches the model runs, and say why."""

from __future__ import annotations

import math

import torch
from torch import Tensor

from rtsplat.model.mirror import first_plane_hit
from rtsplat.model.rtmodel import ActiveEffects
from rtsplat.train_config import Effects

# near_reflection auto: the share of the see-through points that planes must explain. The points are the
# surface depth of the masked pixels, which is the glass where the glass is opaque enough to hold it and
# what lies behind the glass elsewhere (about a third of them on the cabin half-way through its demo
# training): planar panes explain 40-50% there, curved glass (the dome) 0-5% (docs/fidelity.md, 23)
PLANAR_SHARE = 0.3
# near_reflection auto: the mean coverage of the see-through pixels by the mirrored render (what of the model
# the glass would reflect) below which the near term is not worth its rasterizations: a pane facing an open
# street or a sky shows nothing of the model in it. Measured at the fit on the tuning half: curved-0 (which
# reflects a far environment) 0.003-0.004, curved-2 0.08-0.12 (the term gains 0.1-0.6 dB there), film 0.40
# (docs/fidelity.md, finding 31)
NEAR_COVERAGE = 0.02
NEAR_COVERAGE_VIEWS = 8  # training views the coverage is measured on, spread over the capture
BEHIND_SHARE = 0.5  # a plane is glass when this share of the rays meeting it first see something behind it
EDGE_ON_DEGREES = 3.0  # a plane a marked view sees within this angle of edge-on is a face of the marked views' hull


def decide_effects(
    config: Effects, transparent_fraction: float, roi_source: str | None
) -> tuple[ActiveEffects, dict]:
    """Transmission (auto): on iff the training masks mark transparent pixels.

    Specular (auto): on iff reflections are asked for, i.e. the scene has transparent pixels (a
    see-through surface reflects) or the user gave a region of interest in the config
    (``roi_source == "config"``). A region of interest that ``prepare`` merely estimated from the
    SfM points (``"estimated"``) on a scene without glass does not ask for reflections: that scene
    is trained as plain 2DGS radiance, without environment map or specular network.

    Near reflection (auto): asked for iff transmission and specular are on; whether the glass is
    planar enough is decided once the model has its shape (:func:`decide_near_planes`).
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
    if config.near_reflection == "auto":
        near = transmission and specular
        why = ("auto: the glass's planes decide, as the reflections start" if near
               else "auto: needs transmission and specular")
    elif config.near_reflection == "on":
        near, why = specular, "config: on" if specular else "config: on, but specular is off"
    else:
        near, why = False, "config: off"
    reasons["near_reflection"] = why
    return ActiveEffects(transmission=transmission, specular=specular, near_reflection=near), reasons


def decide_near_planes(mode: str, planes: int, planar_share: float | None,
                       coverage: float | None = None) -> tuple[bool, str]:
    """Whether the fitted mirror planes are used: ``auto`` iff they explain at least :data:`PLANAR_SHARE`
    of the glass's points (panes, flat or bent, whose reflections of the scene a mirrored render places;
    strongly curved glass such as a dome reflects mostly what is far, and the environment lookup stays
    alone) and, where it was measured, the mirrored render covers at least :data:`NEAR_COVERAGE` of the
    see-through pixels (``coverage``: the glass reflects something of the model); ``on`` iff any plane was
    found."""
    if planar_share is None or planes == 0:
        return False, "no plane found in the see-through surface"
    share = f"{planes} plane(s) explain {planar_share:.0%} of the see-through surface"
    if coverage is not None:
        share += f", their mirrored render covers {coverage:.0%} of it"
    if mode == "on":
        return True, f"config: on; {share}"
    if planar_share < PLANAR_SHARE:
        return False, f"auto: the glass is not planar; {share}, needs {PLANAR_SHARE:.0%}"
    if coverage is not None and coverage < NEAR_COVERAGE:
        return False, f"auto: the glass reflects little of the scene near it; {share}, needs {NEAR_COVERAGE:.0%}"
    return True, f"auto: planar glass; {share}"


def planes_seen_edge_on(planes: Tensor, centres: Tensor, degrees: float = EDGE_ON_DEGREES) -> Tensor:
    """Which planes [K,12] (:func:`rtsplat.model.mirror.fit_planes` rows) one of the camera centres [C,3] sees
    within ``degrees`` of edge-on when it looks at the plane's centre: [K] bool, true where a camera's
    distance from the plane is at most sin(degrees) times its distance from the plane's centre.

    With masks propagated from a few marked views the glass is seeded on the marked views' visual hull,
    whose faces are pieces of their silhouette cones; every plane tangent to a cone holds its apex, so a
    plane fitted to such a face passes through a marked camera, where glass seen in that view would be a
    line, not a surface."""
    if planes.shape[0] == 0 or centres.shape[0] == 0:
        return torch.zeros(planes.shape[0], dtype=torch.bool)
    normal, centre = planes[:, 0:3], planes[:, 3:6]
    centres = centres.to(planes.dtype)
    off_plane = ((centres[None] - centre[:, None]) * normal[:, None]).sum(-1).abs()  # [K, C]
    reach = (centres[None] - centre[:, None]).norm(dim=-1)
    return (off_plane <= math.sin(math.radians(degrees)) * reach).any(1)


def see_through_planes(planes: Tensor, rays: Tensor) -> Tensor:
    """Which planes [K,12] are see-through [K] (bool): of the see-through pixels' rays [P,7] (origin,
    unit direction, distance to what the transmission shows) that meet a plane first, at least
    :data:`BEHIND_SHARE` see something beyond it by more than its thickness. A plane that no ray meets
    first is kept out."""
    if planes.shape[0] == 0:
        return torch.zeros(0, dtype=torch.bool)
    index, distance = first_plane_hit(rays[:, :3], rays[:, 3:6], planes.to(rays.dtype))
    thickness = planes[:, 11].to(rays.dtype)
    behind = torch.zeros(planes.shape[0], dtype=rays.dtype)
    hits = torch.zeros(planes.shape[0], dtype=rays.dtype)
    first = index >= 0
    k = index[first]
    hits.index_add_(0, k, torch.ones_like(k, dtype=rays.dtype))
    beyond = (rays[first, 6] > distance[first] + thickness[k]).to(rays.dtype)
    behind.index_add_(0, k, beyond)
    return (hits > 0) & (behind >= BEHIND_SHARE * hits)
