"""Settings of the RT-Splatting model: its sizes and initial values, the paper's ablation switches
and the gradient gating. With the active effects and the rasterizer settings they are everything
needed to rebuild a trained model (:mod:`rtsplat.model.checkpoint`); the trainer's config
(:mod:`rtsplat.train_config`) holds them as sections. Every ablation changes only the computation it
names. Defaults follow METHOD.md sections 1-6, except the two extra inputs of the specular network
(``specular_view_angle``, ``specular_background``; docs/fidelity.md, finding 10) and beta's own head
(``attenuation_from``; finding 28).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from rtsplat.schema import setting

# specular_surfaces="see_through": a surface is see-through up to the first blended opacity, opaque from the second
SEE_THROUGH_OPACITY = (0.5, 0.8)


@dataclass
class Ablations:
    """The paper's ablation switches (all on: the full method)."""

    occupancy: bool = setting(True, help="off: one opacity does both jobs (surface weights = volume weights)")
    joint_optimization: bool = setting(
        True, help="off: background first (transparent pixels masked), then frozen"
    )
    scattering: bool = setting(True, help="off: no C_scatter / tau (C_sub = C_trans)")
    attenuation: bool = setting(True, help="off: beta = 1")
    gating: bool = setting(True, help="off: g = 1 (no specular-aware gradient gating)")
    mask_loss: bool = setting(True, help="off: no transparent-mask BCE")


@dataclass
class Gating:
    """Specular-aware gradient gating of C_trans."""

    k: float = setting(4.0, help="gate sharpness: g = exp(-k * local complexity of C_spec)", minimum=0.0)
    mode: Literal["weighted_std", "variance"] = setting(
        "weighted_std",
        help="weighted_std: the reference code's weighted standard deviation (weights 1 - surface alpha, "
        "reflect-padded 3x3 window), the default because it produced the paper's numbers; variance: the "
        "paper's equation, plain 3x3 variance of C_spec",
    )


@dataclass
class ModelSettings:
    """Sizes, initial values and shading constants of the model."""

    sh_degree: int = setting(3, help="highest spherical-harmonics degree of the volume colour", minimum=0, maximum=3)
    view_independent_roi: bool = setting(
        False, help="with the specular branch, surfels inside the region of interest have a view-independent volume "
        "colour (SH degree 0): there the specular branch shades every surface, so the view-dependent light is its "
        "to explain, and SH colour on or behind the glass cannot take a reflection over from it. Outside the region "
        "the volume colour keeps its SH degree. Off: it measured no gain on the dome (docs/fidelity.md, finding 24)"
    )
    env_channels: int = setting(16, help="channels of the environment feature map", minimum=1)
    env_height: int = setting(512, help="environment map height (finest level)", minimum=2)
    env_width: int = setting(1024, help="environment map width (finest level)", minimum=2)
    env_levels: int = setting(9, help="mip levels of the environment map (roughness picks the level)", minimum=1)
    mlp_width: int = setting(256, help="hidden width of the specular network", minimum=1)
    specular_surfaces: Literal["all", "see_through"] = setting(
        "see_through", help="which surfaces inside the region of interest the specular network shades. see_through: "
        "those the mask-trained opacity calls see-through (blended optical opacity up to "
        f"{SEE_THROUGH_OPACITY[0]}, fading out by {SEE_THROUGH_OPACITY[1]}), where a thin surface reflects over what "
        "it lets through; an opaque surface shows its volume colour, view-dependent through its SH degree as in "
        "2DGS, and on the CPU the network's cost follows the glass's share of the image. all: every one (the "
        "paper), for scenes whose opaque surfaces near the glass are shiny. On seven tuning scenes of the glass "
        "family see_through trained the same test PSNR to within 0.2 dB (mean -0.04 dB in the transparent region; "
        "the display cases -0.2) in 2-6% less time, and at 2DGS's training time put RT-Splatting ahead of 2DGS in "
        "the transparent region on four of five seed-0 scenes, even on the fifth (docs/fidelity.md, finding 33). "
        "Only with transmission (the optical opacity); without it every surface, as all"
    )
    specular_view_angle: bool = setting(
        True, help="feed |cos| of the angle between the view ray and the surface normal to the specular network "
        "(with the environment feature), so that C_spec and beta can follow the angle of incidence (Fresnel)"
    )
    specular_background: bool = setting(
        True, help="feed the learned background's radiance B at the reflected direction to the specular network "
        "(with the environment feature; no gradient into B through it): the sky and distant surroundings that "
        "the views see directly, as the reflection's detail. Only with background: learned"
    )
    specular_mirror: bool = setting(
        False, help="C_spec blends, pixel by pixel, a mirror image of the learned background B at the reflected "
        "direction with the network's colour: C_spec = reflectance (m B(w_r) + (1 - m) exp(out + log 0.5)), m a "
        "fifth network output in (0, 1). B holds the sky and the distant surroundings the views see directly, so a "
        "reflection of them gets their detail at once; m falls where the reflection is of something near. No "
        "gradient into B through it. Only with background: learned"
    )
    specular_fresnel: bool = setting(
        False, help="the reflectance is the reflectance at normal incidence F0, raised towards 1 at grazing angles by "
        "Schlick's approximation F0 + (1 - F0)(1 - |cos|)^5, as on a dielectric such as glass: C_spec is weak "
        "where the view meets the surface head-on and strong at grazing angles (docs/fidelity.md, finding 14)"
    )
    attenuation_from: Literal["network", "material"] = setting(
        "material", help="where beta, the attenuation of the light the surface lets through, comes from. material: a "
        "small head of its own on the blended material feature and |cos| of the angle of incidence alone, what "
        "decides how much light a thin surface lets through, starting at 0.9; network: a fourth output of the "
        "specular network, as in the paper, so beta also sees what the surface reflects (the environment feature, "
        "the background at the reflected direction) and the transmission can dim itself wherever the reflection "
        "is too bright, which lets the two layers drift apart as training goes on (docs/fidelity.md, finding 28)"
    )
    specular_precision: Literal["float32", "bfloat16", "auto"] = setting(
        "auto", help="dtype of the specular network's matrix products: float32; bfloat16 (float32 weights and "
        "outputs, bfloat16 products, forward and backward); auto: bfloat16 on a CPU with native bfloat16 products "
        "(AVX512-BF16), float32 elsewhere (a GPU included). On such a CPU bfloat16 took 0.88-0.95x float32's "
        "training time for the same accuracy (docs/performance.md); float32 gives the same numbers on every CPU. "
        "A run's summary.json names the one used (specular_products)"
    )
    near_reflection_planes: int = setting(
        2, help="with near reflections (effects.near_reflection), the most mirror planes rendered per view (those "
        "whose rectangles the view's shaded pixels hit most): each costs one more rasterization of the scene",
        minimum=1,
    )
    near_reflection_on_surface: bool = setting(
        True, help="with near reflections, a pixel reflects in the pane its ray meets first only where its surface "
        "lies on that pane (surface depth within the pane's thickness plus 5% of the distance): not where the ray "
        "passes a pane's rectangle beside the glass and meets something behind it, nor where an object stands in "
        "front of the pane (docs/fidelity.md, finding 24)"
    )
    near_reflection_trains_surfels: bool = setting(
        False, help="with near reflections, the mirrored render passes gradients to the surfels it reflects (their "
        "position, shape, occupancy, opacity and colour); off: it reads them without training them, so they learn "
        "from the views that see them directly only, and the reflection's errors (the plane, the reflectance) stay "
        "out of them, and the mirrored pass needs no backward (docs/fidelity.md, finding 24)"
    )
    near_reflection_bend: bool = setting(
        True, help="with near reflections, curved glass reflects about its own bent normal: each mirror plane carries "
        "the quadric height of the glass over it (fitted with the plane), and a pixel on bent glass reads the "
        "plane's mirrored render where its reflected ray lands instead of at itself; off: every pane reflects as "
        "its flat plane. Costs a bilinear lookup per plane, no extra rasterization (docs/fidelity.md, finding 31)"
    )
    near_reflection_weight: bool = setting(
        False, help="with near reflections, a sixth output w of the specular network weighs them per pixel: "
        "C_spec = reflectance (w C_near + (1 - w A_near) L) instead of w = 1"
    )
    occupancy_init: float = setting(0.1, help="initial surfel occupancy", minimum=0.0, maximum=1.0)
    opacity_init: float = setting(0.5, help="initial optical opacity", minimum=0.0, maximum=1.0)
    transmissivity_init: float = setting(0.5, help="initial transmissivity tau", minimum=0.0, maximum=1.0)
    roughness_init: float = setting(0.1, help="initial roughness", minimum=0.0, maximum=1.0)
    reflectance_init: float = setting(
        0.25, help="initial reflectance. The lower it is, the dimmer C_spec starts, and the more of the light that "
        "looks the same from every view (a haze, a tint) C_trans and C_scatter learn instead of C_spec "
        "(docs/fidelity.md, finding 14)", minimum=0.0, maximum=1.0
    )
    shade_alpha_threshold: float = setting(
        0.05, help="deferred shading only where the surface alpha exceeds this", minimum=0.0, maximum=1.0
    )
    shade_coverage: bool = setting(
        True, help="weigh a pixel's deferred-shaded colour by how much of the pixel the surface covers (the "
        "surface pass's alpha) as well as by its region-of-interest membership, the rest of the pixel showing the "
        "volume colour: at a silhouette, where the surface covers part of a pixel, what lies behind it keeps its "
        "share. Off: the shaded colour (from G-buffers normalised by the alpha) fills the whole pixel, as if the "
        "surface covered it (docs/fidelity.md, finding 36)"
    )
    background: Literal["learned", "black", "white", "random"] = setting(
        "learned", help="radiance where the volume transmittance is left (rtsplat/model/background.py), the same "
        "for every method: learned (a direction-indexed RGB map), black, white, or random (a random colour per "
        "training step, black when evaluating and rendering; for views whose empty pixels carry no colour)"
    )
    background_height: int = setting(256, help="learned background map height (finest level)", minimum=2)
    background_width: int = setting(512, help="learned background map width (finest level)", minimum=2)
    background_levels: int = setting(5, help="mip levels of the learned background map", minimum=1)
