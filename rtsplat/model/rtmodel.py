"""The RT-Splatting model and its hybrid deferred/forward render (paper section 3.2).

    C = C_spec + beta * (tau * C_trans + (1 - tau) * C_scatter)   (:mod:`rtsplat.model.composite`)

* ``C_trans``: volume colour of the forward pass (SH colours, weights occupancy x opacity) plus the
  background ``B(d)`` where the volume transmittance is left (:mod:`rtsplat.model.background`);
* G-buffers from the surface pass (weights occupancy): normal, roughness, material feature,
  reflectance, tau, C_scatter, region-of-interest membership and the blended opacity;
* ``C_spec``, ``beta``: specular network fed with the environment feature at the reflected
  direction, and by default (beyond the paper) with ``|cos|`` of the angle of incidence and the learned
  background's radiance at the reflected direction (no gradient into the background through it).
  Shading happens only where the surface alpha exceeds 0.05; outside the spherical region of interest
  a pixel shows plain volume radiance (blended by ROI membership), and by default (beyond the paper,
  ``shade_coverage``) so does the part of a pixel that the surface does not cover (a silhouette).

Which branches exist is decided once per scene (:class:`ActiveEffects`): without transmission
there is one opacity (opacity = 1, so both weight sets coincide) and no tau / C_scatter; without
specular there is no environment map and no specular network (plain 2DGS radiance). With near
reflections (planar glass, :mod:`rtsplat.model.mirror`) the specular light of a pixel on a pane is the
model's own surfels rendered through the pane's mirror image, over the environment lookup, weighed by
how see-through the surface is (1 - its blended optical opacity): opaque parts coplanar with a pane
(a car's body under its window) keep the environment lookup alone.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from rtsplat.camera import PIXEL_CENTER_OFFSET, Camera, pixel_rays
from rtsplat.model.background import BackgroundMap
from rtsplat.model.composite import (
    reflection_layer,
    region_blend,
    shaded_color,
    subsurface_color,
    transmission_layer,
)
from rtsplat.model.envmap import EnvironmentMap
from rtsplat.model.gating import gate_factor, gate_gradient
from rtsplat.model.gbuffer import surface_values
from rtsplat.model.mirror import (
    PLANE_COLUMNS,
    bent_lookup,
    empty_planes,
    is_bent,
    mirror_points,
    mirror_quats,
    plane_assignment,
    plane_parts,
    sample_pixels,
    signed_distance,
    with_bend,
)
from rtsplat.model.settings import SEE_THROUGH_OPACITY, Ablations, Gating, ModelSettings
from rtsplat.model.sh import eval_sh_parts
from rtsplat.model.specular import SpecularNetwork
from rtsplat.model.specular_inputs import specular_inputs
from rtsplat.model.surfels import SurfelParameters
from rtsplat.raster import RasterOutput, RasterSettings, Surfels, rasterize

STAGES = ("volume", "subsurface", "full")

# surface G-buffer channels blended with the occupancy weights: name -> width, in the order of the rasterizer's
# feature rows. A render rasterizes only the channels its model's effects and its stage read (RTModel.gbuffer_channels).
GBUFFER_WIDTHS = {"scatter": 3, "tau": 1, "roughness": 1, "material": 4, "reflectance": 1, "roi": 1, "opacity": 1}
# the G-buffer channels the specular network's inputs are made of (RTModel._specular_rows)
SPECULAR_INPUT_CHANNELS = ("roughness", "material", "reflectance")
# the surfel parameter behind each G-buffer channel (roi is the surfel's place, which has no gradient through it)
GBUFFER_PARAMETERS = {"scatter": "scatter_logit", "tau": "transmissivity_logit", "roughness": "roughness_logit",
                      "material": "material_raw", "reflectance": "reflectance_logit", "opacity": "opacity_logit"}


def gbuffer_layout(channels: tuple[str, ...]) -> dict[str, slice]:
    """Where each of ``channels`` (names of :data:`GBUFFER_WIDTHS`, in its order) lies in the feature rows."""
    layout, start = {}, 0
    for name in channels:
        layout[name] = slice(start, start + GBUFFER_WIDTHS[name])
        start += GBUFFER_WIDTHS[name]
    return layout


@dataclass(frozen=True)
class ActiveEffects:
    transmission: bool = True  # occupancy/opacity factorization, tau and C_scatter
    specular: bool = True  # environment map + specular network
    near_reflection: bool = False  # planar glass reflects the model's own surfels (mirror planes)

    def to_dict(self) -> dict:
        return asdict(self)


@dataclass
class RenderResult:
    color: Tensor  # [H,W,3] final colour
    raster: RasterOutput  # its per-surfel tensors are over the surfels of ``surfel_index`` when culled
    layers: dict[str, Tensor] = field(default_factory=dict)  # [H,W,C] decomposition and G-buffers
    surfel_index: Tensor | None = None  # [n] the surfels rasterized (render with frustum_cull); None: all
    gbuffer: dict[str, Tensor] = field(default_factory=dict)  # [H,W,C] blended channels rasterized (not normalised)


class RTModel(nn.Module):
    def __init__(
        self, surfels: SurfelParameters, *, effects: ActiveEffects, ablations: Ablations | None = None,
        settings: ModelSettings | None = None, roi_center=(0.0, 0.0, 0.0), roi_radius: float = 1e9,
    ):
        super().__init__()
        self.surfels = surfels
        self.effects = effects
        self.ablations = ablations or Ablations()
        self.settings = settings or ModelSettings()
        s = self.settings
        self.env = EnvironmentMap(s.env_channels, s.env_height, s.env_width, s.env_levels) if effects.specular else None
        self.register_buffer("roi_center", torch.as_tensor(roi_center, dtype=torch.float32).reshape(3))
        self.register_buffer("roi_radius", torch.as_tensor(float(roi_radius), dtype=torch.float32))
        self.register_buffer("mirror_planes", empty_planes())
        self.background_map = (BackgroundMap(s.background_height, s.background_width, s.background_levels)
                               if s.background == "learned" else None)
        self.specular_net = (SpecularNetwork(s.env_channels + self._extra_specular_channels(), 4, s.mlp_width,
                                             s.specular_precision, mirror=self.uses_mirror,
                                             near_weight=effects.near_reflection and s.near_reflection_weight,
                                             attenuation=s.attenuation_from)
                             if effects.specular else None)

    def _extra_specular_channels(self) -> int:
        """Channels the specular network gets beside the environment feature: |cos| of the angle of
        incidence (``specular_view_angle``) and the background at the reflected direction
        (``specular_background``, with a learned background)."""
        s = self.settings
        return int(s.specular_view_angle) + 3 * int(s.specular_background and self.background_map is not None)

    @property
    def uses_mirror(self) -> bool:
        """Whether C_spec blends in the learned background at the reflected direction (``specular_mirror``)."""
        return self.settings.specular_mirror and self.background_map is not None

    def specular_products(self) -> str | None:
        """The dtype the specular network's matrix products run in on the model's device (``float32`` or
        ``bfloat16``: ``specular_precision`` resolved), or None without the network."""
        if self.specular_net is None:
            return None
        return "bfloat16" if self.specular_net.uses_bfloat16(self.roi_center.device) else "float32"

    def set_mirror_planes(self, planes: Tensor) -> None:
        """The planes of the glass (:func:`rtsplat.model.mirror.fit_planes` rows) that near reflections use."""
        planes = planes.detach().to(device=self.roi_center.device, dtype=torch.float32)
        self.mirror_planes = with_bend(planes.reshape(-1, planes.shape[-1] if planes.numel() else PLANE_COLUMNS)
                                       ).contiguous()

    @property
    def uses_near_reflection(self) -> bool:
        return self.effects.specular and self.effects.near_reflection and self.mirror_planes.shape[0] > 0

    @property
    def uses_opacity(self) -> bool:
        """False when one opacity does both jobs (no transmission, or the occupancy ablation)."""
        return self.effects.transmission and self.ablations.occupancy

    @property
    def uses_scatter(self) -> bool:
        return self.effects.transmission and self.ablations.scattering

    # -- rasterizer inputs -------------------------------------------------------------------
    def gbuffer_channels(self, stage: str = "full") -> tuple[str, ...]:
        """The G-buffer channels a render of ``stage`` reads, in :data:`GBUFFER_WIDTHS`' order: the blended opacity
        where opacity is a parameter of its own (the mask loss; how see-through a surface is), and from the
        subsurface stage on the region of interest with transmission or specular and the subsurface terms with
        scattering; in the full stage the specular network's inputs with specular. A model without transmission
        and specular (2DGS) rasterizes none. The default, the full stage, is every channel the model has."""
        wanted = {"opacity"} if self.uses_opacity else set()
        if (self.effects.transmission or self.effects.specular) and stage != "volume":
            wanted.add("roi")
            if self.uses_scatter:
                wanted |= {"scatter", "tau"}
            if self.effects.specular and stage == "full":
                wanted |= set(SPECULAR_INPUT_CHANNELS)
        return tuple(name for name in GBUFFER_WIDTHS if name in wanted)

    def unread_channel_parameters(self, stage: str) -> list[nn.Parameter]:
        """The surfel parameters behind the channels the model has (:meth:`gbuffer_channels`) that a render of
        ``stage`` does not rasterize. Their gradient in that stage is zero, and the trainer hands Adam zeros
        for them, so that their optimizer state steps from the first iteration on as when every channel was
        rasterized in every stage: Adam leaves a parameter whose gradient has always been zero where it is, but
        its step count (the bias correction) shapes the first steps once the channel is read. Rasterizing the
        channels themselves in the stages that do not read them cost rtsplat's volume stage about 10% of its
        time (docs/performance.md, "The G-buffer channels by stage, with Adam's steps kept")."""
        unread = set(self.gbuffer_channels()) - set(self.gbuffer_channels(stage))
        return [getattr(self.surfels, GBUFFER_PARAMETERS[name]) for name in GBUFFER_WIDTHS
                if name in unread and name in GBUFFER_PARAMETERS]

    def rasterizer_surfels(self, camera: Camera, sh_degree: int | None = None, index: Tensor | None = None,
                           channels: tuple[str, ...] | None = None) -> Surfels:
        """The rasterizer's inputs for ``camera``: every surfel, or those of ``index`` [n] (in its order), with
        the G-buffer ``channels`` (names of :data:`GBUFFER_WIDTHS` in its order; default: the model's own,
        :meth:`gbuffer_channels`) as features."""
        channels = self.gbuffer_channels() if channels is None else channels
        p = self.surfels
        take = (lambda t: t) if index is None else (lambda t: t.index_select(0, index))  # noqa: E731
        means, sh_dc, sh_rest = take(p.means), take(p.sh_dc), take(p.sh_rest)
        directions = F.normalize(means - camera.center, dim=-1)
        colors = eval_sh_parts(sh_dc, sh_rest, directions, p.sh_degree if sh_degree is None else sh_degree)
        occupancy = take(p.occupancy)
        opacity = take(p.opacity) if self.uses_opacity else torch.ones_like(occupancy)
        view_independent = self.effects.specular and self.settings.view_independent_roi
        inside = (((means - self.roi_center).norm(dim=-1) <= self.roi_radius).to(means.dtype)
                  if view_independent or "roi" in channels else None)
        if view_independent:
            colors = torch.where(inside[:, None] > 0, eval_sh_parts(sh_dc, sh_rest, directions, 0), colors)
        columns = {
            "scatter": lambda: take(p.scatter), "tau": lambda: take(p.transmissivity)[:, None],
            "roughness": lambda: take(p.roughness)[:, None], "material": lambda: take(p.material),
            "reflectance": lambda: take(p.reflectance)[:, None], "roi": lambda: inside[:, None],
            "opacity": lambda: opacity[:, None],
        }
        features = (torch.cat([columns[name]() for name in channels], 1) if channels
                    else means.new_zeros(means.shape[0], 0))
        return Surfels(means, take(p.quats), take(p.scales), occupancy, opacity, features, colors)

    def in_view(self, camera: Camera, settings: RasterSettings | None = None) -> Tensor:
        """[N] bool, True for every surfel the rasterizer may draw in ``camera``'s image (and some it
        will not): a surfel is left out only when its centre is not beyond the near plane (the rasterizer
        skips those) or when its bounding sphere (radius ``extent_sigma`` times its larger scale, which
        holds its cut-off ellipse) lies in front of the camera and wholly outside one side of the image
        widened by the low-pass radius and a pixel. A camera with skewed pixels gets the near-plane
        test alone."""
        settings = settings or RasterSettings()
        p = self.surfels
        with torch.no_grad():
            R, t, K = (x.detach().double() for x in (camera.rotation, camera.translation, camera.K))
            X, Y, Z = (p.means.detach().double() @ R.T + t).unbind(-1)
            keep = Z > settings.near * (1 - 1e-6) - 1e-9
            if float(K[0, 1]) != 0.0:
                return keep
            radius = settings.extent_sigma * p.scales.detach().double().amax(-1) * (1 + 1e-6) + 1e-9
            fx, fy, cx, cy = float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2])
            margin = settings.lowpass_radius + 1.0
            ahead = Z - radius > 0  # the whole sphere in front of the camera: its image is bounded
            for f, coord, c, low, high in ((fx, X, cx, -margin, camera.width + margin),
                                           (fy, Y, cy, -margin, camera.height + margin)):
                # signed distances to the planes through the camera centre at pixel coordinate low and high
                past_low = (f * coord + (c - low) * Z) / math.hypot(f, c - low) < -radius
                past_high = (-f * coord + (high - c) * Z) / math.hypot(f, high - c) < -radius
                keep &= ~(ahead & (past_low | past_high))
        return keep

    # -- the hybrid render --------------------------------------------------------------------
    def render(
        self, camera: Camera, *, stage: str = "full", gating: Gating | None = None,
        raster_settings: RasterSettings | None = None, backend: str = "auto", sh_degree: int | None = None,
        background: Tensor | None = None, frustum_cull: bool = False, mirror_planes: Tensor | None = None,
        specular_gradient_share: float = 1.0, generator: torch.Generator | None = None,
        specular_weight: float = 1.0, specular_downsample: int = 1,
    ) -> RenderResult:
        """``background``: an RGB colour [3] that replaces the model's background for this render (the
        trainer's random background). ``frustum_cull``: rasterize only the surfels of :meth:`in_view`
        (the same image, less per-surfel work; ``result.surfel_index`` says which surfels the per-surfel
        outputs of ``result.raster`` are). ``mirror_planes``: plane rows [K,12] that replace the model's
        mirror planes in this render (as many as it has), through which gradients reach them (the trainer's
        plane refinement). ``specular_gradient_share`` < 1 (with autograd on): the specular network's gradient
        is sampled, see :meth:`_specular`; ``generator`` draws the sample. ``specular_weight`` w in [0, 1]: the
        full stage's C_spec scaled by w and beta by ``1 - w (1 - beta)``, so that w = 0 renders the subsurface
        stage's image and w = 1 the full model's (the trainer's fade-in, ``schedule.specular_fade``).
        ``specular_downsample`` f > 1: the specular network shades f x f blocks of pixels, one sample each, and
        every pixel reads C_spec and beta upsampled from them (:meth:`_specular_downsampled`; the trainer's
        ``schedule.specular_coarse_share``): about 1/f^2 of the network's and the environment lookup's work."""
        if stage not in STAGES:
            raise ValueError(f"stage must be one of {STAGES}, got {stage!r}")
        if specular_downsample < 1:
            raise ValueError(f"specular_downsample must be at least 1, got {specular_downsample}")
        if not 0.0 <= specular_weight <= 1.0:
            raise ValueError(f"specular_weight must be in [0, 1], got {specular_weight}")
        index = torch.nonzero(self.in_view(camera, raster_settings)).flatten() if frustum_cull else None
        channels = self.gbuffer_channels(stage)
        out = rasterize(self.rasterizer_surfels(camera, sh_degree, index, channels), camera, raster_settings,
                        backend=backend)
        rays = image_ray_directions(camera)  # [H,W,3], shared by the background and the specular pass
        far = self.background_radiance(camera, rays) if background is None else background.to(out.color)
        c_trans = out.color + (1.0 - out.volume_alpha) * far
        alpha = out.alpha
        alpha_safe = alpha.clamp_min(1e-6)
        layout = gbuffer_layout(channels)
        g = {name: out.features[..., sl] for name, sl in layout.items()}
        normal = F.normalize(out.normal, dim=-1)
        layers = {
            "trans": c_trans, "normal": normal, "depth": out.depth, "alpha": alpha,
            "volume_alpha": out.volume_alpha, "blended_opacity": g.get("opacity", alpha),  # opacity 1: the alpha
        }
        if stage == "volume" or not (self.effects.transmission or self.effects.specular):
            return RenderResult(c_trans, out, layers, index, g)

        shade = alpha > self.settings.shade_alpha_threshold  # [H,W,1]
        # the values of the surface a pixel shows: its region membership, optical opacity and subsurface terms
        names = ("roi",) + ("opacity",) * self.uses_opacity + ("tau", "scatter") * self.uses_scatter
        surface = surface_values(out.features, alpha_safe, layout, names,
                                 clamped=frozenset({"roi", "tau", "scatter"}))
        roi = surface["roi"]
        if self.settings.shade_coverage:  # the part of the pixel the surface does not cover shows C_trans
            roi = roi * alpha.clamp(0, 1)
        surface_opacity = surface["opacity"] if self.uses_opacity else torch.ones_like(alpha)
        if self.settings.specular_surfaces == "see_through" and self.uses_opacity:
            roi = roi * see_through_weight(surface_opacity)
        specular_on = stage == "full" and self.effects.specular
        if specular_on:
            # a pixel with no region-of-interest weight shows C_trans alone (region_blend and the layers
            # weigh C_spec and beta by roi), so the network runs only where roi > 0
            wanted = shade & (roi > 0)
            near = None
            if self.uses_near_reflection:
                near_color, near_alpha = self.near_reflection(camera, wanted[..., 0], raster_settings, backend,
                                                              surface_depth=out.depth[..., 0].detach(),
                                                              planes=mirror_planes)
                if self.uses_opacity:  # a mirror of the glass: weighed by how see-through the surface is
                    clear = (1.0 - surface_opacity).clamp(0, 1)
                    near_color, near_alpha = clear * near_color, clear * near_alpha
                near = (near_color, near_alpha)
                layers.update(near=near_color, near_alpha=near_alpha)
            if specular_downsample > 1:
                spec, beta = self._specular_downsampled(camera, out.normal, g, alpha, wanted, rays, near,
                                                        specular_downsample, specular_gradient_share, generator)
            else:
                spec, beta = self._specular(camera, normal, g, alpha_safe, wanted, near=near, rays=rays,
                                            gradient_share=specular_gradient_share, generator=generator)
            if not self.ablations.attenuation:
                beta = torch.ones_like(beta)
            if specular_weight < 1.0:
                spec, beta = spec * specular_weight, 1.0 - specular_weight * (1.0 - beta)
            layers.update(spec=spec, beta=beta)
            if self.ablations.gating and gating is not None and torch.is_grad_enabled():
                gate = gate_factor(spec, alpha, gating.k, gating.mode)
                c_trans_in = gate_gradient(c_trans, gate)
                layers["gate"] = gate
            else:
                c_trans_in = c_trans
        else:
            spec, beta, c_trans_in = torch.zeros_like(c_trans), torch.ones_like(alpha), c_trans
        if self.uses_scatter:
            tau, scatter = surface["tau"], surface["scatter"]
            sub = subsurface_color(c_trans_in, tau, scatter)
            direct = tau * c_trans
            layers.update(tau=tau, scatter=scatter)
        else:
            sub = c_trans_in
            direct = sub
        color = region_blend(shaded_color(spec, beta, sub), c_trans, roi, shade)
        layers.update(roi=roi, sub=sub, shade=shade.to(color.dtype))
        layers["transmission"] = transmission_layer(beta, direct, c_trans, roi, shade)
        layers["reflection"] = reflection_layer(spec, roi, shade)
        return RenderResult(color, out, layers, index, g)

    def background_radiance(self, camera: Camera, rays: Tensor | None = None) -> Tensor:
        """``B(d)`` for every pixel ray [H,W,3] (learned), or a constant colour [3] (black, white, random).
        ``rays``: the camera's :func:`image_ray_directions`, when the caller has them."""
        if self.background_map is not None:
            return self.background_map(image_ray_directions(camera) if rays is None else rays)
        value = 1.0 if self.settings.background == "white" else 0.0
        return torch.full((3,), value, dtype=self.roi_center.dtype, device=self.roi_center.device)

    def near_reflection(self, camera: Camera, wanted: Tensor, raster_settings: RasterSettings | None,
                        backend: str, surface_depth: Tensor | None = None,
                        planes: Tensor | None = None) -> tuple[Tensor, Tensor]:
        """C_near [H,W,3] (premultiplied) and its coverage A_near [H,W,1]: for the ``wanted`` pixels [H,W]
        whose ray hits a mirror plane, the volume colour of the surfels on the camera's side of the
        first plane hit, reflected in it (:mod:`rtsplat.model.mirror`); zero elsewhere. At most
        ``near_reflection_planes`` planes are rendered per view, those that cover the most pixels. The
        reflected surfels show their view-independent colour (SH degree 0). ``planes``: rows [K,12] in place
        of the model's mirror planes; the mirrored surfels' positions and rotations carry their gradient
        (which pixel meets which plane, and which surfels are mirrored, are discrete choices, without it)."""
        H, W = wanted.shape
        p = self.surfels
        planes = self.mirror_planes if planes is None else with_bend(planes)
        if planes.shape != self.mirror_planes.shape:
            raise ValueError(f"mirror_planes must be {tuple(self.mirror_planes.shape)} (the model's), "
                             f"got {tuple(planes.shape)}")
        directions = image_ray_directions(camera)
        index, distance = plane_assignment(camera, planes.detach(), directions)
        normals, centres, _, _, _, thickness = plane_parts(planes.to(p.means.dtype))
        thickness = thickness.detach()
        if self.settings.near_reflection_on_surface and surface_depth is not None:
            wanted = wanted & on_plane_surface(index, distance, directions, camera, surface_depth, thickness)
        index = torch.where(wanted, index, torch.full_like(index, -1))
        K = self.mirror_planes.shape[0]
        counts = torch.bincount((index + 1).flatten(), minlength=K + 1)[1:].tolist()
        order = sorted(range(K), key=lambda k: -counts[k])[: self.settings.near_reflection_planes]
        color = torch.zeros(H, W, 3, dtype=p.means.dtype, device=p.means.device)
        alpha = torch.zeros(H, W, 1, dtype=p.means.dtype, device=p.means.device)
        center = camera.center.to(p.means.dtype)
        bent = (is_bent(planes) & self.settings.near_reflection_bend).tolist()
        # without a gradient to pass (surfels only read, planes fixed) the mirrored passes build no autograd
        # graph: the rasterizer would otherwise track its screen-space probe and run a backward for nothing
        needs_grad = self.settings.near_reflection_trains_surfels or planes.requires_grad
        with torch.set_grad_enabled(torch.is_grad_enabled() and needs_grad):
            for k in order:
                if counts[k] == 0:
                    break
                n, c = normals[k], centres[k]
                camera_side = signed_distance(center, n, c).detach()  # which side: no gradient
                if float(camera_side.abs()) <= float(thickness[k]):
                    continue  # the camera is inside the pane's slab: no side to mirror
                side = signed_distance(p.means.detach(), n.detach(), c.detach()) * torch.sign(camera_side)
                keep = torch.nonzero(side > thickness[k], as_tuple=False).flatten()
                if keep.numel() == 0:
                    continue
                means = p.means[keep]
                # the view-independent (degree 0) colour, which no direction changes: a reflection sees the
                # surfels from directions that no view may have seen them from, where higher degrees extrapolate
                colors = eval_sh_parts(p.sh_dc[keep], p.sh_rest[keep], F.normalize(means - center, dim=-1), 0)
                quats, scales = p.quats[keep], p.scales[keep]
                occupancy = p.occupancy[keep]
                opacity = p.opacity[keep] if self.uses_opacity else torch.ones_like(occupancy)
                if not self.settings.near_reflection_trains_surfels:  # the reflection reads the surfels only
                    means, quats, scales, occupancy, opacity, colors = (
                        t.detach() for t in (means, quats, scales, occupancy, opacity, colors))
                mirrored = Surfels(mirror_points(means, n, c), mirror_quats(quats, n), scales, occupancy, opacity,
                                   means.new_zeros(keep.numel(), 0), colors)
                out = rasterize(mirrored, camera, raster_settings, backend=backend)
                plane_color, plane_alpha = out.color, out.volume_alpha
                if bent[k]:  # curved glass: each pixel reads the mirrored render where its bent reflection lands
                    plane_distance = torch.where(index == k, distance, torch.full_like(distance, float("inf")))
                    xy, valid = bent_lookup(camera, directions, planes[k].detach(), plane_distance,
                                            mirrored_distance(out, directions, camera))
                    plane_color = sample_pixels(out.color, xy, valid)
                    plane_alpha = sample_pixels(out.volume_alpha, xy, valid)
                on_plane = (index == k)[..., None]
                color = torch.where(on_plane, plane_color, color)
                alpha = torch.where(on_plane, plane_alpha, alpha)
        return color, alpha

    def _specular_downsampled(self, camera: Camera, normal_sum: Tensor, g: dict, alpha: Tensor, wanted: Tensor,
                              rays: Tensor, near: tuple[Tensor, Tensor] | None, factor: int, gradient_share: float,
                              generator: torch.Generator | None) -> tuple[Tensor, Tensor]:
        """C_spec [H,W,3] and beta [H,W,1] at the ``wanted`` pixels [H,W,1] (0 and 1 elsewhere), shaded once per
        ``factor`` x ``factor`` block: the network's inputs are the block's means (:func:`block_mean` of the
        blended, alpha-weighted G-buffer channels and normal, so a block reads its covered pixels' surface; of the
        unit pixel rays; of the near reflection), a block is shaded where any of its pixels is wanted, and every
        pixel reads the bilinear interpolation of the shaded blocks around it (:func:`upsampled_from_blocks`).
        ``normal_sum``: the rasterizer's blended normal, before normalisation. The gradient reaches every pixel of
        a block through the means, and ``gradient_share`` samples the blocks as :meth:`_specular` samples pixels."""
        H, W = alpha.shape[:2]
        # the images averaged in two passes, one over those with a gradient and one over those without: the
        # channels of each side by side, so that each pass is one pooling (a mean is taken channel by channel,
        # so the same values as one pooling per image)
        tracked = [alpha, normal_sum, *(g[name] for name in SPECULAR_INPUT_CHANNELS), *(near or ())]
        coarse_alpha, normal, *coarse_channels = block_mean(torch.cat(tracked, -1), factor).split(
            [t.shape[-1] for t in tracked], -1)
        coarse_g = dict(zip(SPECULAR_INPUT_CHANNELS, coarse_channels, strict=False))
        coarse_near = None if near is None else tuple(coarse_channels[len(SPECULAR_INPUT_CHANNELS):])
        normal = F.normalize(normal.contiguous(), dim=-1)  # contiguous: a norm over a strided last dim is slower
        with torch.no_grad():
            coarse_rays, shaded = block_mean(torch.cat([rays.to(alpha.dtype), wanted.to(alpha.dtype)], -1),
                                             factor).split([3, 1], -1)
        coarse_rays = F.normalize(coarse_rays.contiguous(), dim=-1)
        shaded = shaded > 0
        spec, beta = self._specular(camera, normal, coarse_g, coarse_alpha.clamp_min(1e-6), shaded,
                                    near=coarse_near, rays=coarse_rays, gradient_share=gradient_share,
                                    generator=generator)
        weight = shaded.to(spec.dtype)
        spec, beta = upsampled_from_blocks(torch.cat([spec, beta], -1), weight, factor, (H, W)).split([3, 1], -1)
        return torch.where(wanted, spec, 0.0), torch.where(wanted, beta, 1.0)

    def _specular(self, camera: Camera, normal: Tensor, g: dict, alpha_safe: Tensor, shade: Tensor,
                  every_pixel: bool | None = None, near: tuple[Tensor, Tensor] | None = None,
                  rays: Tensor | None = None, gradient_share: float = 1.0,
                  generator: torch.Generator | None = None):
        """C_spec and beta where ``shade`` (the render passes the shaded pixels with region-of-interest
        weight); 0 and 1 elsewhere (``rays``: the camera's :func:`image_ray_directions`, when known). On the
        CPU only those pixels are evaluated; on other devices (``every_pixel``, default: not on the CPU) every
        pixel is and the others are masked out, because gathering them would wait for the device to count
        them. Both give the same values and gradients.

        ``gradient_share`` < 1 with autograd on samples the gradient: each shaded pixel is tracked with that
        probability (drawn from ``generator``), and only the tracked ones pass a gradient, scaled by
        ``1 / gradient_share`` so that its expected value is the full gradient. Every pixel gets the same
        value either way. On the CPU the untracked pixels are evaluated without autograd, which saves the
        backward of the network, the environment lookup and the G-buffer reads for them, and both sets of
        pixels read one texel table of the environment map (one mip pyramid per render)."""
        H, W = normal.shape[:2]
        flat = shade.reshape(-1)
        every_pixel = normal.device.type != "cpu" if every_pixel is None else every_pixel
        idx = None if every_pixel else torch.nonzero(flat, as_tuple=False).flatten()
        spec = torch.zeros(H * W, 3, dtype=normal.dtype, device=normal.device)
        beta = torch.ones(H * W, 1, dtype=normal.dtype, device=normal.device)
        if idx is not None and idx.numel() == 0:
            return spec.reshape(H, W, 3), beta.reshape(H, W, 1)
        if not 0.0 < gradient_share <= 1.0:
            raise ValueError(f"gradient_share must be in (0, 1], got {gradient_share}")
        sampled = gradient_share < 1.0 and torch.is_grad_enabled()

        def evaluate(rows: Tensor | None, env_table: Tensor | None = None) -> tuple[Tensor, Tensor]:
            return self._specular_rows(camera, normal, g, alpha_safe, rows, near, rays, env_table)

        if idx is None:
            s, b = evaluate(None)
            if sampled:
                tracked = torch.rand(H * W, 1, generator=generator).to(normal.device) < gradient_share
                weight = tracked.to(normal.dtype) / gradient_share
                s, b = gradient_scaled(s, weight), gradient_scaled(b, weight)
            spec = torch.where(flat[:, None], s, spec)
            beta = torch.where(flat[:, None], b, beta)
        elif sampled:
            tracked = torch.rand(idx.numel(), generator=generator) < gradient_share
            table = self.env.texel_table()[0]
            for rows, differentiated in ((idx[tracked], True), (idx[~tracked], False)):
                if rows.numel() == 0:
                    continue
                with torch.set_grad_enabled(differentiated):
                    s, b = evaluate(rows, table if differentiated else table.detach())
                if differentiated:
                    s, b = gradient_scaled(s, 1.0 / gradient_share), gradient_scaled(b, 1.0 / gradient_share)
                spec, beta = spec.index_copy(0, rows, s), beta.index_copy(0, rows, b)
        else:
            s, b = evaluate(idx)
            spec, beta = spec.index_copy(0, idx, s), beta.index_copy(0, idx, b)
        return spec.reshape(H, W, 3), beta.reshape(H, W, 1)

    def _specular_rows(self, camera: Camera, normal: Tensor, g: dict, alpha_safe: Tensor, idx: Tensor | None,
                       near: tuple[Tensor, Tensor] | None, rays: Tensor | None,
                       env_table: Tensor | None = None) -> tuple[Tensor, Tensor]:
        """The specular network's C_spec [N,3] and beta [N,1] at the pixels ``idx`` of the flattened image
        (None: every pixel), from the G-buffer ``g`` and the blended ``normal``; ``env_table``: the
        environment map's texel table, when the caller shares one (:meth:`EnvironmentMap.forward`)."""
        reflected, cos_incidence, rough, material, reflectance = specular_inputs(
            image_ray_directions(camera) if rays is None else rays, normal, g["roughness"], g["material"],
            g["reflectance"], alpha_safe, idx)
        if self.settings.specular_fresnel:
            reflectance = schlick_fresnel(reflectance, cos_incidence)
        env = self.env(reflected, rough, env_table)
        reflected_background = None
        if self.background_map is not None and (self.settings.specular_background or self.uses_mirror):
            with torch.no_grad():  # B learns only from the pixels that see it
                reflected_background = self.background_map(reflected).to(env.dtype)
        extra = []
        if self.settings.specular_view_angle:
            extra.append(cos_incidence)
        if self.settings.specular_background and reflected_background is not None:
            extra.append(reflected_background)
        if extra:
            env = torch.cat([env, *extra], -1)
        rows = (lambda t: t) if idx is None else (lambda t: t[idx])  # noqa: E731
        near_rows = None if near is None else (rows(near[0].reshape(-1, 3)), rows(near[1].reshape(-1, 1)))
        s, b = self.specular_net(env, material, reflectance, reflected_background if self.uses_mirror else None,
                                 near=near_rows, cos_incidence=cos_incidence)
        return s, b


def block_mean(t: Tensor, factor: int) -> Tensor:
    """``t`` [H,W,C] -> [ceil(H / factor), ceil(W / factor), C] (contiguous): the mean over each ``factor`` x
    ``factor`` block of pixels; a block cut by the right or bottom edge averages the pixels it holds."""
    # channel-major input: each channel is pooled on its own, whatever the channels beside it
    return F.avg_pool2d(t.permute(2, 0, 1).contiguous()[None], factor, ceil_mode=True)[0].permute(1, 2, 0).contiguous()


def upsampled_from_blocks(values: Tensor, weight: Tensor, factor: int, size: tuple[int, int]) -> Tensor:
    """Per-block ``values`` [h,w,C] (each at its block's centre, :func:`block_mean`'s blocks) interpolated
    bilinearly to the pixels [H,W,C] of ``size``, each block weighed by ``weight`` [h,w,1] (0 or 1): a pixel
    reads the weighted mean of the nearest blocks, so blocks of weight 0 neither dim nor tint their
    neighbours. A pixel whose four nearest blocks all weigh 0 gets 0. The pixels of a block of weight 1
    always read it with a weight of at least 9/16."""
    H, W = size
    h, w = weight.shape[:2]

    def spread(t: Tensor) -> Tensor:
        grid = F.interpolate(t.permute(2, 0, 1)[None], size=(h * factor, w * factor), mode="bilinear",
                             align_corners=False)
        return grid[0, :, :H, :W].permute(1, 2, 0)

    total = spread(weight)
    return spread(values * weight) / total.clamp_min(1e-6)


def gradient_scaled(t: Tensor, weight: Tensor | float) -> Tensor:
    """``t`` unchanged in value, its gradient multiplied by ``weight`` (a number or a tensor that broadcasts)."""
    return t.detach() + (t - t.detach()) * weight


MIRRORED_MIN_ALPHA = 0.05  # a mirrored render thinner than this shows nothing at a pixel (no distance)


def mirrored_distance(out, directions: Tensor, camera: Camera) -> Tensor:
    """Distance [H,W] along each pixel ray to what a mirrored render ``out`` shows there (its volume depth
    turned from camera z to distance along the ray); inf where it shows less than :data:`MIRRORED_MIN_ALPHA`."""
    forward = camera.world_to_camera[2, :3].to(directions.dtype)
    along = (directions * forward).sum(-1).clamp_min(1e-6)
    distance = out.volume_depth[..., 0].detach() / along
    shown = (out.volume_alpha[..., 0].detach() >= MIRRORED_MIN_ALPHA) & torch.isfinite(distance)
    return torch.where(shown, distance, torch.full_like(distance, float("inf")))


ON_PLANE_TOLERANCE = 0.05  # relative to the distance: how far a pixel's surface may lie from the pane it is on


def on_plane_surface(index: Tensor, distance: Tensor, directions: Tensor, camera: Camera, surface_depth: Tensor,
                     thickness: Tensor) -> Tensor:
    """[H,W] bool: the pixels whose surface depth (z, [H,W]) lies on the plane their ray meets first (``index``,
    ``distance`` along the ray from :func:`rtsplat.model.mirror.plane_assignment`), within that plane's
    ``thickness`` ([K]) plus :data:`ON_PLANE_TOLERANCE` of its depth; False where the ray meets no plane."""
    hit = index >= 0
    forward = camera.world_to_camera[2, :3].to(directions.dtype)
    plane_depth = torch.where(hit, distance, torch.zeros_like(distance)) * (directions * forward).sum(-1)
    tolerance = thickness.to(directions.dtype)[index.clamp_min(0)] + ON_PLANE_TOLERANCE * plane_depth.abs()
    return hit & ((surface_depth.to(directions.dtype) - plane_depth).abs() <= tolerance)


def see_through_weight(opacity: Tensor) -> Tensor:
    """How much a pixel's surface counts as see-through for ``specular_surfaces="see_through"``, from its
    blended optical opacity [H,W,1]: 1 up to ``SEE_THROUGH_OPACITY[0]``, 0 from ``SEE_THROUGH_OPACITY[1]``,
    linear between; without gradient (the opacity learns from the images and the masks, not from where the
    network shades)."""
    low, high = SEE_THROUGH_OPACITY
    return ((high - opacity.detach()) / (high - low)).clamp(0, 1)


def schlick_fresnel(normal_reflectance: Tensor, cos_incidence: Tensor) -> Tensor:
    """Schlick's approximation of a dielectric's reflectance: F0 at normal incidence (``cos_incidence``
    1), rising to 1 at grazing incidence (0)."""
    return normal_reflectance + (1.0 - normal_reflectance) * (1.0 - cos_incidence) ** 5


def image_ray_directions(camera: Camera) -> Tensor:
    """Unit world-space directions [H,W,3] from the camera centre through each pixel centre
    (:func:`rtsplat.camera.pixel_rays` on the image's pixel grid)."""
    dtype, device = camera.K.dtype, camera.K.device
    ys = torch.arange(camera.height, dtype=dtype, device=device) + PIXEL_CENTER_OFFSET
    xs = torch.arange(camera.width, dtype=dtype, device=device) + PIXEL_CENTER_OFFSET
    yy, xx = torch.meshgrid(ys, xs, indexing="ij")
    return pixel_rays(camera, xx, yy)[1]
