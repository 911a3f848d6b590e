"""The trainer, kept small: data, model, losses, density control, the divergence watch, the mirror-plane
fit, evaluation, checkpoints and resuming each live in their own module; this file sequences a training
step and holds the state a checkpoint resumes (the model, the optimizer, the clock and the time spent).
What a run folder holds and when it is written (the train log, checkpoints on the schedule, the summary)
is :mod:`rtsplat.train.run`'s; :meth:`Trainer.train` runs it."""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from rtsplat.camera import Camera
from rtsplat.devices import resolve_device
from rtsplat.errors import PipelineError
from rtsplat.io.train_log import LOG_NAME
from rtsplat.model.appearance import apply_appearance
from rtsplat.model.checkpoint import Checkpoint, read_checkpoint, write_checkpoint
from rtsplat.model.rtmodel import RenderResult, RTModel
from rtsplat.model.specular import cpu_has_amx_tiles
from rtsplat.model.surfels import (
    PARAMETERS,
    SurfelParameters,
    concat_surfels,
    init_from_points,
)
from rtsplat.quality import masked_mean, psnr
from rtsplat.quality.lpips import load_lpips
from rtsplat.scene import PreparedScene
from rtsplat.train import losses
from rtsplat.train.appearance import (
    APPEARANCE_SPREAD,
    PROJECTED_SPREAD,
    AppearanceCorrections,
    AppearanceDecision,
    ExposureSpread,
    decide_appearance,
    exposure_spread,
    scene_log_gains,
    view_log_gains,
)
from rtsplat.train.cameras import PoseCorrections
from rtsplat.train.clock import ScheduleClock
from rtsplat.train.data import ViewSet, load_views, scene_extent
from rtsplat.train.density import DensityControl, DensityEvents
from rtsplat.train.divergence import DivergenceWatch, diverged_error
from rtsplat.train.effects import decide_effects
from rtsplat.train.evaluation import TestViews, rows_by_name, views_psnr
from rtsplat.train.glass_planes import fit_near_planes
from rtsplat.train.initial import density_start, initial_surfels, plan_starting_surfels, starting_cap
from rtsplat.train.optim import append_rows, build_optimizer, load_optimizer_state, position_lr
from rtsplat.train.planes import PlaneRefinement
from rtsplat.train.resume import check_resumable
from rtsplat.train.run import TrainingRun, write_effects
from rtsplat.train_config import TrainConfig
from rtsplat.usage import Usage, UsageClock, compute_threads

MIN_COARSE_SIDE = 8  # progressive resolution: the coarsest training views keep at least this many pixels a side


@dataclass
class StepResult:
    """One iteration's numbers, as 0-d tensors on the training device: reading them (``float``)
    waits for the device, so the loop reads them only on logging steps."""

    iteration: int
    positions: tuple[int, int]  # the plan's position before and at this step (rtsplat.train.clock)
    loss: Tensor
    psnr: Tensor
    terms: dict[str, Tensor]
    stage: str
    density: dict[str, int | str]

    def numbers(self) -> dict[str, float]:
        """loss, psnr and ``loss_<term>`` as floats (one transfer from the device)."""
        names = ["loss", "psnr", *(f"loss_{k}" for k in self.terms)]
        values = torch.stack([self.loss, self.psnr, *self.terms.values()]).tolist()
        return dict(zip(names, values, strict=True))


def stage_at(iteration: int, cfg: TrainConfig) -> str:
    s = cfg.schedule
    if iteration <= s.volume_until:
        return "volume"
    if iteration <= s.specular_from:
        return "subsurface"
    return "full"


class Trainer:
    def __init__(
        self, scene: PreparedScene, cfg: TrainConfig, out_dir: str | Path, *, log: Callable[[str], None] = print,
        progress: bool = True, checkpoint_dir: str | Path | None = None,
    ):
        self.cfg = cfg.validate()
        self.scene = scene
        # the prepared scene this run trains on, recorded in its checkpoints (None: a scene without a folder)
        self.data = scene.data_record() if scene.root is not None else None
        self.out = Path(out_dir)
        self.checkpoint_dir = Path(checkpoint_dir) if checkpoint_dir is not None else self.out / "checkpoints"
        self.log = log
        self.progress = progress
        # set (to a signal number) from outside, e.g. a signal handler: the loop writes the checkpoint at the
        # end of the current iteration and raises run.TrainingStopped (rtsplat train: SIGTERM, SIGUSR1)
        self.stop_signal: int | None = None
        self.device = resolve_device(cfg.device, key="train.device")
        torch.manual_seed(cfg.seed)
        self.rng = torch.Generator().manual_seed(cfg.seed)
        # the share of the shaded pixels through which the specular network's gradient flows in training renders
        self.specular_gradient_share = cfg.schedule.resolved_specular_gradient_share(
            self.device.type == "cpu" and not cpu_has_amx_tiles())
        self.train_views = load_views(scene, "train", self.device, cfg.train_downsample)
        # the progressive resolution's coarser copies of the training views, by factor (1: train_views)
        self.train_levels = {factor: self._coarse_views(factor) for factor in cfg.schedule.downsample_levels()}
        self.test_views = load_views(scene, "test", self.device)
        self.extent = scene_extent(self.train_views.cameras)
        roi = getattr(scene, "roi", None)
        roi_source = roi.source if roi is not None and float(roi.radius) > 0 else None
        self.effects, self.effect_reasons = decide_effects(
            cfg.effects, self.train_views.transparent_fraction, roi_source
        )
        self.near_fit: dict | None = None  # the mirror-plane fit (fit_mirror_planes), once it ran
        self.plane_refinement: PlaneRefinement | None = None  # the planes learnt from the images, once fitted
        self.points = _scene_points(scene)  # the SfM points [N,3] and their colours [N,3] in [0, 1]
        train_pixels = sum(int(image.shape[0]) * int(image.shape[1]) for image in self.train_views.images)
        self.starting = plan_starting_surfels(self.points[0].shape[0], cfg.densify.initial_copies,
                                              starting_cap(cfg.densify, train_pixels))
        self.density_start = density_start(cfg.schedule, cfg.densify, self.starting,
                                           train_pixels / max(len(self.train_views), 1))
        self.exposure, self.appearance_decision = self._decide_appearance()
        self.effect_reasons["appearance"] = self.appearance_decision.reason
        self.appearance = (AppearanceCorrections(len(self.train_views), cfg.appearance.lr, self.device)
                           if self.appearance_decision.on else None)
        surfels, n_see_through = self._init_surfels()
        self.model = self.new_model(surfels)
        self.optimizer = build_optimizer(self.model, self.model.surfels, cfg.lr, self.extent)
        self.density = DensityControl(cfg.densify,
                                      replace(cfg.schedule, densify_from=self.density_start.densify_from), self.extent,
                                      spared_early=torch.arange(len(surfels), device=self.device)
                                      >= len(surfels) - n_see_through)
        c = cfg.cameras
        self.poses = PoseCorrections(len(self.train_views), self.extent, c.lr_rotation, c.lr_translation,
                                     self.device) if c.refine else None
        # the test views' pose and appearance corrections, fitted with the model fixed (not in self.elapsed)
        self.test = TestViews(self.test_views, self.device, poses=self.poses is not None,
                              appearance=self.appearance is not None)
        self.frozen = torch.zeros(len(self.model.surfels), dtype=torch.bool, device=self.device)
        self.any_frozen = False  # kept on the host: the step tests it without reading the device
        self.iteration = 0
        self.clock = ScheduleClock(cfg.schedule.iterations, cfg.schedule.seconds)
        self.elapsed = 0.0  # wall seconds of the training steps
        self.cpu_elapsed: float | None = 0.0  # CPU seconds of the same steps (None: resumed from a run without)
        self.usage_before: Usage | None = Usage(threads=compute_threads())  # the resumed parts' run usage
        self.run_clock = UsageClock()  # this part's, restarted when train() starts
        self.order: list[int] = []
        self.watch = DivergenceWatch(self.device)
        # the iteration of the checkpoint at checkpoint_path this run wrote or resumed from
        self.checkpoint_iteration: int | None = None
        self.perceptual, why = load_lpips(cfg.losses.lpips_weights, self.device)
        self.perceptual_note = why
        # what trained each part of the run (rtsplat.provenance), one more each time a resume runs other code
        self.provenance: list[dict] = []

    # -- construction ------------------------------------------------------------------------
    def _decide_appearance(self) -> tuple[ExposureSpread, AppearanceDecision]:
        """The spread of the training photos' exposures, measured by prepare from the SfM observations (else
        from the points projected into the photos), and whether per-view appearance is learnt."""
        views, scene = self.train_views, self.scene
        gains, source, threshold = (scene_log_gains(scene.exposure or {}, views.names, scene.exposure_points,
                                                    scene.exposure_error),
                                    "SfM observations", APPEARANCE_SPREAD)
        if gains is None:  # a scene prepared without the measurement
            gains = view_log_gains(views.cameras, views.images, views.masks, self.points[0].to(self.device),
                                   self.points[1].to(self.device))
            source, threshold = "the points projected", PROJECTED_SPREAD
        exposure = exposure_spread(gains)
        return exposure, decide_appearance(self.cfg.effects.appearance, exposure, source, threshold)

    def _init_surfels(self) -> tuple[SurfelParameters, int]:
        """The starting surfels: those from the SfM points, then the see-through surface's seeds (their
        number is the second value)."""
        m = self.cfg.model
        surfels = initial_surfels(
            *self.points, self.starting, self.rng,
            point_normals=self.cfg.densify.initial_orientation == "point_normals", sh_degree=m.sh_degree,
            occupancy=m.occupancy_init, opacity=m.opacity_init, transmissivity=m.transmissivity_init,
            roughness=m.roughness_init, reflectance=m.reflectance_init,
        )
        surface = self.scene.load_transparent_surface() if self.cfg.seed_transparent_surface else None
        if surface is None or not self.effects.transmission or len(surface[0]) < 4:
            return surfels, 0
        seeds = self._transparent_surface_surfels(*surface)
        return concat_surfels([surfels, seeds]), len(seeds)

    def fit_mirror_planes(self) -> dict:
        """Fit the glass's mirror planes to the model's own see-through surface, switch the near reflections on
        where it is planar (:func:`rtsplat.train.glass_planes.fit_near_planes`) and learn the planes from here
        on; returns the fit's record (``near_fit``)."""
        planes, record = fit_near_planes(self.model, self.train_views, self.scene, self.cfg, self.rng)
        self.near_fit = {"iteration": self.iteration, **record}
        self.model.set_mirror_planes(planes)
        self._start_plane_refinement()
        self.log(f"near reflection at iteration {self.iteration}: {'on' if record['on'] else 'off'} "
                 f"({record['reason']}; fitted in {record['seconds']:.1f} s)")
        write_effects(self)
        return self.near_fit

    def _start_plane_refinement(self) -> None:
        """Learn the mirror planes from the images from here on (:mod:`rtsplat.train.planes`) when near
        reflections are on and a plane learning rate is set."""
        lr = self.cfg.lr
        self.plane_refinement = None
        if self.model.uses_near_reflection and (lr.mirror_plane_rotation > 0 or lr.mirror_plane_shift > 0):
            self.plane_refinement = PlaneRefinement(self.model.mirror_planes, self.extent, lr.mirror_plane_rotation,
                                                    lr.mirror_plane_shift)

    def _transparent_surface_surfels(self, xyz: np.ndarray, normal: np.ndarray) -> SurfelParameters:
        """Surfels where the see-through surface is (prepare's points on the masks' visual hull), which
        SfM points miss: oriented along the hull's normals and clear (low opacity, high transmissivity,
        no colour of their own), so that they start as glass that reflects and lets the scene through."""
        m = self.cfg.model
        xyz_t = torch.as_tensor(xyz, dtype=torch.float32)
        seeds = init_from_points(
            xyz_t, torch.zeros_like(xyz_t), sh_degree=m.sh_degree, occupancy=m.occupancy_init, opacity=0.1,
            transmissivity=0.9, roughness=m.roughness_init, reflectance=m.reflectance_init, generator=self.rng,
            normals=torch.as_tensor(normal, dtype=torch.float32), scale_factor=self.cfg.transparent_surface_scale,
        )
        return seeds

    def new_model(self, surfels: SurfelParameters) -> RTModel:
        """A model of this run's effects and settings made of ``surfels``, on the training device."""
        roi = self.scene.roi
        return RTModel(
            surfels, effects=self.effects, ablations=self.cfg.ablations, settings=self.cfg.model,
            roi_center=roi.center, roi_radius=roi.radius,
        ).to(self.device)

    def _coarse_views(self, factor: int) -> ViewSet:
        """The training views box-filtered by ``factor`` more than the training resolution (the progressive
        resolution's levels, ``schedule.coarse_downsample``), read once when the trainer starts."""
        if factor == 1:
            return self.train_views
        smallest = min(min(int(image.shape[0]), int(image.shape[1])) for image in self.train_views.images)
        if smallest // factor < MIN_COARSE_SIDE:
            raise PipelineError(
                f"train.schedule.coarse_downsample {self.cfg.schedule.coarse_downsample} leaves training views of "
                f"{smallest // factor} pixels on their short side (fewer than {MIN_COARSE_SIDE})",
                path=self.scene.root, fix="lower train.schedule.coarse_downsample (1 trains at full size throughout)")
        return load_views(self.scene, "train", self.device, self.cfg.train_downsample * factor)

    # -- one iteration -----------------------------------------------------------------------
    def _next_view(self) -> int:
        if not self.order:
            self.order = torch.randperm(len(self.train_views), generator=self.rng).tolist()
        return self.order.pop()

    def _background_phase(self) -> bool:
        return (not self.cfg.ablations.joint_optimization
                and self.clock.position <= self.cfg.schedule.background_phase_end())

    def step(self) -> StepResult:
        cfg = self.cfg
        self.iteration += 1
        # it: the plan's iteration this step stands at (the run's iteration without a time budget)
        previous, it = self._advance()
        idx = self._next_view()
        views = self.train_levels[cfg.schedule.downsample_at(it)]
        camera, target, mask = views.cameras[idx], views.images[idx], views.masks[idx]
        refine_pose = self.poses is not None and it > cfg.cameras.refine_from
        if refine_pose:
            camera = self.poses.camera(idx, camera)
        if (self.effects.near_reflection and self.near_fit is None and stage_at(it, cfg) == "full"
                and not self._background_phase()):
            self.fit_mirror_planes()  # once, as the reflections start: the glass has its shape by then
        background_phase = self._background_phase()
        stage = "volume" if background_phase else stage_at(it, cfg)
        result = self._render_training_view(camera, stage, it)
        weight = (1.0 - mask) if (background_phase and mask is not None) else None
        color = result.color
        learn_appearance = self.appearance is not None and it > cfg.appearance.start(cfg.schedule)
        if learn_appearance:
            color = apply_appearance(color, self.appearance.correction(idx))
        terms = self._loss_terms(it, result, color, target, mask, weight, camera,
                                 idx if learn_appearance else None)
        loss = sum(terms.values())
        loss.backward()
        for parameter in self.model.unread_channel_parameters(stage):
            if parameter.grad is None:
                parameter.grad = torch.zeros_like(parameter)
        events = self._update(result, it, previous, refine_pose, learn_appearance, loss)
        with torch.no_grad():
            value = psnr(color.detach().clamp(0, 1), target)
        return StepResult(self.iteration, (previous, it), loss.detach(), value,
                          {k: v.detach() for k, v in terms.items()}, stage, events.to_dict() if events.any() else {})

    def _advance(self) -> tuple[int, int]:
        """Move the plan's clock on by one step (:meth:`ScheduleClock.advance`): the plan's iterations before
        and at this step; freeze the background as its phase ends and set the position learning rate."""
        cfg = self.cfg
        previous, it = self.clock.advance(self.elapsed)
        if not cfg.ablations.joint_optimization and previous <= cfg.schedule.background_phase_end() < it:
            self._freeze_background()
        for group in self.optimizer.param_groups:
            if group.get("name") == "means":
                group["lr"] = position_lr(it, cfg.lr, self.extent)
        return previous, it

    def _render_training_view(self, camera: Camera, stage: str, it: int) -> RenderResult:
        """The model's render of a training view at the plan's iteration ``it``: its spherical harmonics
        degree, a random background (``model.background: random``), the mirror planes being learnt, the
        specular gradient's share (``schedule.specular_gradient_share``), the specular branch's fade-in
        (``schedule.specular_fade``) and its shading resolution (``schedule.specular_coarse_share``)."""
        cfg = self.cfg
        sh_degree = min(it // cfg.schedule.sh_degree_every, cfg.model.sh_degree)
        background = torch.rand(3, generator=self.rng) if cfg.model.background == "random" else None
        planes = self.plane_refinement.planes() if self.plane_refinement is not None else None
        return self.model.render(camera, stage=stage, gating=cfg.gating, raster_settings=cfg.raster,
                                 backend=cfg.backend, sh_degree=sh_degree, background=background,
                                 mirror_planes=planes,
                                 specular_gradient_share=self.specular_gradient_share,
                                 generator=self.rng, specular_weight=cfg.schedule.specular_weight_at(it),
                                 specular_downsample=cfg.schedule.specular_downsample_at(it))

    def _loss_terms(self, it: int, result: RenderResult, color: Tensor, target: Tensor, mask: Tensor | None,
                    weight: Tensor | None, camera: Camera, appearance_view: int | None) -> dict[str, Tensor]:
        """The weighted loss terms of one training view by name, in the order they are summed: the image term
        (pixels weighted by ``weight``) and those whose weight, iteration and inputs switch them on;
        ``appearance_view``: the view whose appearance correction is learnt (its prior term), None: none is."""
        cfg, L = self.cfg, self.cfg.losses
        terms = {"image": losses.image_loss(color, target, cfg.losses.ssim_weight, weight)}
        if appearance_view is not None and cfg.appearance.prior_weight > 0:
            terms["appearance"] = cfg.appearance.prior_weight * self.appearance.prior(appearance_view)
        if L.normal_weight > 0 and it > L.normal_from:
            depth = result.raster.depth_median if L.normal_depth == "median" else result.raster.depth
            terms["normal"] = L.normal_weight * losses.normal_consistency(
                result.layers["normal"], depth, result.layers["alpha"], camera)
        if cfg.ablations.mask_loss and mask is not None and self.model.uses_opacity:
            if L.mask_weight > 0:
                surface_alpha = result.layers["alpha"] if L.mask_opaque_target == "surface" else None
                terms["mask"] = L.mask_weight * losses.transparent_mask_loss(
                    result.layers["blended_opacity"], mask, surface_alpha)
            if L.mask_coverage_weight > 0:
                terms["mask_coverage"] = L.mask_coverage_weight * losses.mask_coverage_loss(
                    result.layers["alpha"], mask)
        if L.shading_smoothness_weight > 0 and mask is not None and "spec" in result.layers:
            g = result.gbuffer
            shading = torch.cat([g["reflectance"], g["roughness"], g["material"]], -1)
            terms["shading_smoothness"] = L.shading_smoothness_weight * losses.shading_smoothness(
                shading, result.raster.alpha, mask)
        if L.distortion_weight > 0:
            terms["distortion"] = L.distortion_weight * result.raster.distortion.mean()
        if self.perceptual is not None and L.perceptual_weight > 0 and it >= L.perceptual_from:
            terms["perceptual"] = L.perceptual_weight * self.perceptual(color, target)
        if L.transmissivity_bce_weight > 0 and "tau" in result.layers and mask is not None:
            terms["tau"] = L.transmissivity_bce_weight * masked_mean(
                -torch.log((1 - result.layers["tau"]).clamp_min(1e-6)), 1 - mask)
        if L.reflection_weight > 0 and "spec" in result.layers:
            terms["reflection"] = L.reflection_weight * result.layers["reflection"].mean()
        if L.occupancy_decay_weight > 0:  # mean occupancy of the visible surfels (0 when none is)
            visible = result.raster.visible.to(self.model.surfels.occupancy.dtype)
            terms["occupancy_decay"] = L.occupancy_decay_weight * (
                (self.model.surfels.occupancy * visible).sum() / visible.sum().clamp_min(1))
        return terms

    def _update(self, result: RenderResult, it: int, previous: int, refine_pose: bool, learn_appearance: bool,
                loss: Tensor) -> DensityEvents:
        """After the backward pass: the optimizer steps (surfels, poses, mirror planes, appearance), density
        control, and the divergence watch's record of the step; returns the density events."""
        trainable = (~self.frozen).float()
        self.density.observe(result.raster, trainable)
        gradients = self._optimizer_step()
        if refine_pose:
            self.poses.step()
        if self.plane_refinement is not None:
            self.model.set_mirror_planes(self.plane_refinement.step())
        if learn_appearance:
            self.appearance.step()
        events, self.frozen = self.density.step(it, self.model.surfels, self.optimizer, self.rng, self.frozen,
                                                previous=previous)
        self.watch.record(self.iteration, loss, gradients, self.optimizer)
        return events

    def _optimizer_step(self) -> Tensor:
        """Adam on the unfrozen rows; returns the gradients' group sums for the divergence watch."""
        frozen = self.frozen
        saved = {}
        if self.any_frozen:
            for name in PARAMETERS:
                p = getattr(self.model.surfels, name)
                if p.grad is not None:
                    p.grad[frozen] = 0
                saved[name] = p.detach()[frozen].clone()
        gradients = self.watch.gradients(self.optimizer)
        self.optimizer.step()
        self.optimizer.zero_grad(set_to_none=True)
        if saved:
            with torch.no_grad():
                for name, value in saved.items():
                    getattr(self.model.surfels, name)[frozen] = value
        return gradients

    def _freeze_background(self) -> None:
        """joint_optimization off: freeze what was learnt on the background pixels and start fresh
        surfels (from the SfM points) for the see-through surfaces."""
        fresh, _ = self._init_surfels()
        n_old = len(self.model.surfels)
        append_rows(self.optimizer, self.model.surfels,
                    {k: v.detach().to(self.device) for k, v in fresh.tensors().items()})
        self.frozen = torch.cat([torch.ones(n_old, dtype=torch.bool, device=self.device),
                                 torch.zeros(len(fresh), dtype=torch.bool, device=self.device)])
        self.any_frozen = n_old > 0
        self.log(f"joint_optimization off: froze {n_old} background surfels, added {len(fresh)} new ones")

    # -- evaluation --------------------------------------------------------------------------
    def _evaluation_color(self, camera: Camera) -> Tensor:
        """The model's colour at ``camera`` in the stage the plan stands at (no random background)."""
        return self.model.render(camera, stage=stage_at(max(self.clock.position, 1), self.cfg),
                                 raster_settings=self.cfg.raster, backend=self.cfg.backend).color

    def fit_test_cameras(self, steps: int) -> None:
        """Fit the test views' corrections to their photos with the model fixed (:meth:`TestViews.fit`): the
        poses only with pose refinement (``cameras.refine``), the appearance only where it is learnt."""
        self.test.fit(self._evaluation_color, steps, self.extent, self.cfg.cameras.test_fit_lr,
                      self.cfg.appearance.test_prior)

    @torch.no_grad()
    def evaluate(self, views: ViewSet | None = None) -> dict[str, float]:
        """Test PSNR (entire image, transparent region) of ``views`` at their cameras (default: the test views
        with their fitted corrections; :func:`rtsplat.train.evaluation.views_psnr`)."""
        if views is None:
            return self.test.psnr(self._evaluation_color)
        return views_psnr(self._evaluation_color, views.cameras, views, None)

    def camera_corrections(self) -> dict[str, list[float]]:
        """Every view's pose correction by name (rotation vector in radians, translation), for
        :meth:`rtsplat.camera.Camera.corrected`; empty without pose refinement."""
        if self.poses is None:
            return {}
        return {**rows_by_name(self.train_views.names, self.poses.values()),
                **rows_by_name(self.test_views.names, self.test.poses)}

    def appearance_corrections(self) -> dict[str, list[float]]:
        """Every view's appearance correction by name (log gain, offset per channel), for
        :func:`rtsplat.model.appearance.apply_appearance`; empty where appearance is not learnt."""
        if self.appearance is None:
            return {}
        return {**rows_by_name(self.train_views.names, self.appearance.detached()),
                **rows_by_name(self.test_views.names, self.test.appearance)}

    def appearance_summary(self) -> dict:
        """Whether appearance is learnt, why, how confident that decision is, what it rested on (the spread, the
        views with a gain, the median observations per view, the spread the gains' noise alone gives), and the
        mean absolute log gain and offset of the views."""
        out = {"on": self.appearance is not None, "spread": self.exposure.spread,
               "reason": self.effect_reasons["appearance"], "confidence": self.appearance_decision.confidence,
               "views_measured": self.exposure.views, "observations_per_view": self.exposure.observations,
               "noise": self.exposure.noise}
        if self.appearance is not None:
            for split, values in (("train", self.appearance.detached()), ("test", self.test.appearance)):
                if len(values):
                    out[f"{split}_mean_abs_log_gain"] = float(values[:, :3].abs().mean())
                    out[f"{split}_mean_abs_offset"] = float(values[:, 3:].abs().mean())
        return out

    def correction_sizes(self) -> dict[str, float]:
        """Mean rotation (degrees) and translation (scene units) of the training and test views'
        corrections, for the run summary."""
        if self.poses is None:
            return {}
        out = {"test_fit_seconds": round(self.test.seconds, 3)}
        for split, values in (("train", self.poses.values()), ("test", self.test.poses)):
            if len(values):
                out[f"{split}_pose_correction_deg"] = math.degrees(float(values[:, :3].norm(dim=1).mean()))
                out[f"{split}_pose_correction_translation"] = float(values[:, 3:].norm(dim=1).mean())
        return out

    # -- checkpoints ---------------------------------------------------------------------------
    @property
    def checkpoint_path(self) -> Path:
        return self.checkpoint_dir / "last.pt"

    @property
    def kept_log_path(self) -> Path | None:
        """A checkpoint folder outside the run folder keeps a copy of the train log, taken with each
        checkpoint: a resume into a run folder that was deleted restores the log from it."""
        return None if self.checkpoint_dir == self.out / "checkpoints" else self.checkpoint_dir / LOG_NAME

    def training_state(self) -> dict:
        """What resumes the run besides the model: iteration, config, optimizer, density, RNGs."""
        return {
            "iteration": self.iteration,
            "position": self.clock.position,
            "elapsed": self.elapsed,
            "cpu_elapsed": self.cpu_elapsed,
            "run_usage": None if (usage := self.run_usage()) is None else usage.to_dict(),
            "config": self.cfg.to_dict(),
            "data": self.data,
            "optimizer": self.optimizer.state_dict(),
            "density": self.density.state_dict(),
            "frozen": self.frozen,
            "order": list(self.order),
            "poses": None if self.poses is None else self.poses.state_dict(),
            "camera_corrections": self.camera_corrections(),
            "appearance": None if self.appearance is None else self.appearance.state_dict(),
            "appearance_corrections": self.appearance_corrections(),
            "near_fit": self.near_fit,
            "provenance": self.provenance,
            "plane_refinement": None if self.plane_refinement is None else self.plane_refinement.state_dict(),
            "rng": self.rng.get_state(),
            "torch_rng": torch.get_rng_state(),
        }

    def save_checkpoint(self, path: Path | None = None) -> Path:
        """Write the state (``checkpoints/last.pt`` by default); a diverged state is never written."""
        self.stop_if_diverged()
        path = path or self.checkpoint_path
        written = write_checkpoint(path, self.model, self.cfg.raster, self.training_state())
        if path == self.checkpoint_path:
            self.checkpoint_iteration = self.iteration
        return written

    def stop_if_diverged(self) -> None:
        """Raise :class:`~rtsplat.train.divergence.TrainingDiverged` if a loss, gradient or parameter
        went non-finite so far."""
        divergence = self.watch.check()
        if divergence is not None:
            raise diverged_error(divergence, self.iteration, self.checkpoint_path, self.checkpoint_iteration)

    def load_checkpoint(self, path: Path, new_config: bool = False) -> None:
        """Resume from ``path``. A checkpoint written training on another prepared scene (another
        :meth:`~rtsplat.scene.PreparedScene.data_record` fingerprint) is an error naming both. A config
        that differs from the checkpoint's (beyond
        :data:`rtsplat.train_config.RESUME_MAY_CHANGE`) is an error naming the keys, unless
        ``new_config`` (``--resume-with-new-config``), which logs them and trains on with this config."""
        checkpoint = read_checkpoint(path, self.device)
        changed = check_resumable(checkpoint, path, self.data, self.effects, self.cfg, new_config)
        if changed:
            self.log("resuming with a changed config: " + "; ".join(changed))
        self._restore_model(checkpoint)
        self._restore_progress(checkpoint.training)

    def _restore_model(self, checkpoint: Checkpoint) -> None:
        """The model and what trains it, from a checkpoint: optimizer, density control, frozen rows, the pose,
        appearance and mirror-plane corrections, the plane fit, and what trained each part of the run."""
        state = checkpoint.training
        self.model = checkpoint.build_model(self.device, ablations=self.cfg.ablations, settings=self.cfg.model)
        self.optimizer = build_optimizer(self.model, self.model.surfels, self.cfg.lr, self.extent)
        load_optimizer_state(self.optimizer, state["optimizer"])
        self.density.load_state_dict(state["density"])
        self.frozen = state["frozen"].to(self.device)
        if self.poses is not None and state.get("poses") is not None:
            self.poses.load_state_dict(state["poses"])
        if self.appearance is not None and state.get("appearance") is not None:
            self.appearance.load_state_dict(state["appearance"])
        self.test.restore(state.get("camera_corrections", {}), state.get("appearance_corrections", {}))
        self.any_frozen = bool(self.frozen.any())
        self.near_fit = state.get("near_fit")
        self.provenance = list(state.get("provenance") or [])
        self._start_plane_refinement()
        if self.plane_refinement is not None and state.get("plane_refinement") is not None:
            self.plane_refinement.load_state_dict(state["plane_refinement"])

    def _restore_progress(self, state: dict) -> None:
        """Where the run stood at the checkpoint: the view order, the random generators, the iteration and the
        plan's position, and the time spent."""
        self.order = list(state["order"])
        # generator states are CPU byte tensors (the checkpoint was read onto self.device)
        self.rng.set_state(state["rng"].cpu())
        torch.set_rng_state(state["torch_rng"].cpu())
        self.iteration = int(state["iteration"])
        self.clock.position = int(state.get("position", self.iteration))
        self.elapsed = float(state["elapsed"])
        self.cpu_elapsed = None if state.get("cpu_elapsed") is None else float(state["cpu_elapsed"])
        self.usage_before = None if state.get("run_usage") is None else Usage.from_dict(state["run_usage"])
        self.checkpoint_iteration = self.iteration

    # -- the run -------------------------------------------------------------------------------
    def train(self, resume: bool = True, new_config: bool = False) -> dict:
        """Train into the run folder (:class:`rtsplat.train.run.TrainingRun`) and return the summary."""
        return TrainingRun(self).train(resume, new_config)

    def run_usage(self) -> Usage | None:
        """Wall and CPU seconds, threads and the other processes' CPU time of the whole run so far (this
        part since :meth:`train` started, plus the parts it resumed from); None when a resumed part
        did not record it."""
        return None if self.usage_before is None else self.usage_before + self.run_clock.read()


def _scene_points(scene: PreparedScene) -> tuple[Tensor, Tensor]:
    """The prepared scene's SfM points [N,3] and their colours [N,3] in [0, 1]; an error when there are none."""
    xyz, rgb = scene.load_points()
    points = (torch.as_tensor(np.asarray(xyz), dtype=torch.float32),
              torch.as_tensor(np.asarray(rgb), dtype=torch.float32) / 255.0)
    if points[0].shape[0] == 0:
        raise PipelineError("the point cloud is empty; cannot initialise surfels", path=scene.points_path,
                            fix="rerun `rtsplat prepare` on a scene whose SfM produced points")
    return points
