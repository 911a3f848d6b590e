"""Configuration of the RT-Splatting trainer: one dataclass tree, the ``train:`` tree of a config.
It is plain settings (no training code), so the pipeline config and the stages can read it without
importing the trainer.

The model's own settings (:class:`ModelSettings`, :class:`Ablations`, :class:`Gating`) live in
:mod:`rtsplat.model.settings` and the rasterizer's in :class:`rtsplat.raster.RasterSettings`; this
tree holds them as sections next to the training-only ones. Fields are made with
:func:`rtsplat.schema.setting` (help text and schema keywords), so the tree is checked by the same
machinery as the pipeline config and is part of its generated JSON schema (``train.options``).
:class:`Effects` decides which branches run (``auto`` decides from the prepared scene).
Defaults follow METHOD.md sections 1-6 except the iteration counts, which are sized for a CPU, and the
mask loss's target outside the mask (`Losses.mask_opaque_target`), which is made for a learned background.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any, Literal

from rtsplat import schema
from rtsplat.devices import DEVICE_PATTERN
from rtsplat.errors import ConfigError
from rtsplat.model.settings import Ablations, Gating, ModelSettings
from rtsplat.raster import RasterSettings, check_backend_name
from rtsplat.schema import setting

__all__ = ["Ablations", "AppearanceSettings", "CameraRefinement", "Densification", "Effects", "Gating",
           "ITERATION_COUNTS", "LearningRates",
           "Losses", "ModelSettings", "RESUME_MAY_CHANGE", "Schedule", "TrainConfig", "resume_differences",
           "scale_budget"]


@dataclass
class Effects:
    """Which branches run. ``auto``: transmission iff the training masks have transparent pixels;
    specular iff the scene has a region of interest (reflections requested)."""

    transmission: Literal["auto", "on", "off"] = setting(
        "auto", help="occupancy/opacity factorization, tau and C_scatter; auto: on iff the training masks "
        "mark transparent pixels"
    )
    specular: Literal["auto", "on", "off"] = setting(
        "auto", help="environment map and specular network; auto: on iff the scene has transparent pixels or "
        "a region of interest given in the config"
    )
    near_reflection: Literal["auto", "on", "off"] = setting(
        "off", help="reflections of the scene's own surfels in the glass (mirror planes fitted, as the "
        "reflections start, to the surface depth of the see-through pixels, bent with curved glass; one more "
        "rasterization per plane in view); auto: on iff transmission and specular are on, see-through planes "
        "explain enough of that surface and their mirrored render covers enough of it. Off by default: on the "
        "glass family it cost flat glass time and accuracy and helped two of three curved scenes "
        "(docs/fidelity.md, finding 34)"
    )
    appearance: Literal["auto", "on", "off"] = setting(
        "auto", help="a per-view exposure and white-balance correction (log gain and offset per channel) learnt "
        "for each training view and fitted for each test view; auto: on iff the photos' colours of the SfM points "
        "spread by exposure (rtsplat.train.appearance)"
    )


# the specular gradient's share of a time-budgeted training on the CPU when schedule.specular_gradient_share is null
BUDGETED_SPECULAR_GRADIENT_SHARE = 0.25
# the share of the plan over which the full model's specular branch fades in (Schedule.specular_fade)
SPECULAR_FADE = 0.0667
# the share of the full stage whose training renders shade at half resolution (Schedule.specular_coarse_share)
SPECULAR_COARSE_SHARE = 0.5
# the factor of those renders' shading resolution (RTModel.render's specular_downsample)
SPECULAR_COARSE_FACTOR = 2


@dataclass
class Schedule:
    """Iteration counts of the training schedule."""

    iterations: int = setting(3000, help="training iterations (with seconds: the length of the plan the other "
                              "counts place their events in)", minimum=1)
    seconds: float | None = setting(
        None, help="a time budget: train for this many wall seconds of training steps (evaluations, test-view fits "
        "and checkpoints not counted), each step placed in the plan of `iterations` iterations by the share of the "
        "budget spent, so that every stage, density step and resolution step takes its share of the time "
        "(rtsplat/train/clock.py; not bit-reproducible); null: train for `iterations` iterations",
        exclusiveMinimum=0.0
    )
    volume_until: int = setting(300, help="stage 1 (volume colour only) up to this iteration", minimum=0)
    specular_from: int = setting(
        600, help="stage 3 (full model) after this iteration; stage 2 (no specular) in between", minimum=0
    )
    separate_background_until: int | None = setting(
        None, help="ablations.joint_optimization off: the background-only phase lasts up to this iteration; null: "
        "half the run, so that the phase follows the run's length", minimum=0
    )
    densify_from: int = setting(500, help="densification starts after this iteration", minimum=0)
    dense_start_densify_from: int | None = setting(
        None, help="with a dense start (at least densify.dense_start_per_pixel surfels started from the SfM points "
        "per pixel of a training view), densification starts after this iteration instead of densify_from: its "
        "first step prunes most of a dense start (55-88% on the tuning scenes' ground-truth clouds), and the "
        "surfels it prunes stop costing time earlier. At 124 instead of the demo's 188 on the ten tuning scenes "
        "(8-13 surfels per pixel): 0.90x rtsplat's and 0.88x 2dgs's training CPU seconds, median +0.03 / +0.06 "
        "and -0.11 / -0.07 dB; on sparse SfM starts (1.1-1.9 per pixel) it saved nothing and cost 2dgs 3-6% "
        "(docs/fidelity.md, finding 53). null: densify_from whatever the start", minimum=0
    )
    densify_until: int | None = setting(
        None, help="density control and resets stop at this iteration (exclusive); null: half the run, the 2DGS "
        "ratio (15000 of 30000), so that the second half refines a fixed set of surfels", minimum=0
    )
    densify_every: int = setting(100, help="densify every N iterations", minimum=1)
    reset_every: int = setting(1500, help="alternating occupancy / opacity resets every N iterations (0: never)",
                               minimum=0)
    sh_degree_every: int = setting(
        1000, help="the volume colour's SH degree grows by one every N iterations (up to model.sh_degree)", minimum=1
    )
    coarse_downsample: int = setting(
        1, help="progressive resolution: the training views start box-filtered by this factor (a power of two, "
        "cameras scaled to match), which halves at evenly spaced iterations up to full_resolution_from; from "
        "there on they are at the training resolution (train_downsample). Every per-pixel cost (rasterizer, "
        "specular network, SSIM) shrinks early in the run; 1: the training resolution throughout", minimum=1
    )
    full_resolution_from: int = setting(
        0, help="progressive resolution: the training views are at the training resolution from this iteration on",
        minimum=0
    )
    specular_fade: float = setting(
        SPECULAR_FADE, help="the full model's specular branch fades in over this share of the plan's iterations after "
        "specular_from: C_spec is scaled by w and beta by 1 - w (1 - beta), w rising linearly from 0 to 1, so that the "
        "first full-model renders are the stage before's image and the untrained network does not knock the image "
        "off its fit (on the tuning scenes the training PSNR fell by 2-9 dB at an abrupt switch and took 20-50 "
        "iterations to recover; docs/fidelity.md, finding 47); the network learns at its full rate all along (Adam's "
        "steps do not shrink with w). 0: the branch switches on at once", minimum=0.0, maximum=1.0
    )
    specular_coarse_share: float = setting(
        SPECULAR_COARSE_SHARE, help="the first share of the full stage's iterations (from specular_from to the plan's "
        f"end) in which a training render runs the specular network at 1/{SPECULAR_COARSE_FACTOR} of the resolution: "
        f"on the G-buffer averaged over {SPECULAR_COARSE_FACTOR}x{SPECULAR_COARSE_FACTOR} blocks, C_spec and beta "
        "upsampled bilinearly (rtsplat.model.rtmodel.RTModel.render, specular_downsample). The network, the "
        "environment lookup and their backward then cost about a quarter: on five tuning scenes, two seeds, runs at "
        "the demo's settings took 0.84-1.01x the training CPU seconds (median 0.94x) for the same test PSNR to "
        "within the seed noise (docs/performance.md, \"The specular network at half resolution in the first half "
        "of the full stage\"). The later training renders, the evaluations and rtsplat render shade every pixel. "
        "0: every pixel throughout",
        minimum=0.0, maximum=1.0
    )
    specular_gradient_share: float | None = setting(
        None, help="the share of the shaded pixels of a training render through which the specular network's "
        "gradient flows, drawn afresh each iteration; the others get the same colour without autograd, and the "
        "sampled pixels' gradient is scaled by 1/share, so that its expected value is the full gradient. The "
        "rendered images and the loss are unchanged. On a CPU without AMX (an AMD EPYC) this saves the backward of "
        "the network and of the environment lookup for the others: an iteration of the family's car-0 took 0.85x "
        "the time at 0.25, "
        "which a time budget turns into more iterations (ahead by 0.21 dB median in the transparent region on "
        "the tuning scenes, two seeds), while at a fixed iteration count the noisier gradient lost about 0.2 dB "
        "(docs/benchmarks.md). On a GPU every pixel is evaluated with autograd and the others' gradient is masked, "
        "which saves nothing. On a CPU with AMX tiles the network's bfloat16 products are cheap and the sampled "
        "render cost more than it saved (a time-budgeted run made about 10% fewer iterations at 0.25, and every "
        "pixel gained 0.19 / 0.14 dB at equal time on the seed-0 tuning scenes; docs/benchmarks.md, \"The specular "
        "gradient's share on a CPU with AMX\"). null: 0.25 for a training on a CPU without AMX tiles with a time "
        "budget (seconds), else 1 (every pixel, the exact gradient)", exclusiveMinimum=0.0, maximum=1.0
    )
    log_every: int = setting(10, help="a train_log.jsonl line every N iterations (a logging rate, not scaled by "
                             "budget)", minimum=1)
    checkpoint_every: int = setting(500, help="write checkpoints/last.pt every N iterations (0: never)", minimum=0)
    eval_every: int = setting(
        0, help="test-view PSNR (entire / transparent) every N iterations into the log, for accuracy-against-time "
        "curves; 0: only at the end. Evaluation time is not counted in the log's seconds", minimum=0
    )

    def _or_half_run(self, count: int | None) -> int:
        """An iteration count whose null means half the run."""
        return self.iterations // 2 if count is None else count

    def densify_stop(self) -> int:
        """The iteration at which density control and resets stop (exclusive)."""
        return self._or_half_run(self.densify_until)

    def background_phase_end(self) -> int:
        """The last iteration of the background-only phase (joint optimization off)."""
        return self._or_half_run(self.separate_background_until)

    def resolved_specular_gradient_share(self, sampling_saves_time: bool) -> float:
        """The specular gradient's share of every training render (:attr:`specular_gradient_share`, or its
        default: 0.25 for a training with a time budget where sampling saves time (``sampling_saves_time``: the
        trainer's device is a CPU without AMX tiles), else 1)."""
        if self.specular_gradient_share is not None:
            return self.specular_gradient_share
        return BUDGETED_SPECULAR_GRADIENT_SHARE if sampling_saves_time and self.seconds is not None else 1.0

    def specular_weight_at(self, iteration: int) -> float:
        """The specular branch's weight at the plan's ``iteration`` (:attr:`specular_fade`): 0 up to
        ``specular_from``, rising linearly to 1 over ``specular_fade`` x ``iterations`` iterations after it."""
        progress = iteration - self.specular_from
        if progress <= 0:
            return 0.0
        fade = self.specular_fade * self.iterations
        return 1.0 if progress >= fade else progress / fade

    def specular_downsample_at(self, iteration: int) -> int:
        """The specular shading's resolution factor of a training render at the plan's ``iteration``
        (:attr:`specular_coarse_share`): :data:`SPECULAR_COARSE_FACTOR` in the first share of the full stage
        (after ``specular_from``), 1 elsewhere."""
        coarse_until = self.specular_from + self.specular_coarse_share * max(self.iterations - self.specular_from, 0)
        return SPECULAR_COARSE_FACTOR if self.specular_from < iteration <= coarse_until else 1

    def downsample_at(self, iteration: int) -> int:
        """The progressive-resolution factor of ``iteration`` (1: the training resolution): the coarse
        factor halves ``log2(coarse_downsample)`` times at evenly spaced iterations of
        ``[0, full_resolution_from)``."""
        if self.coarse_downsample <= 1 or iteration >= self.full_resolution_from:
            return 1
        steps = self.coarse_downsample.bit_length() - 1  # the levels coarser than full size
        level = min(steps - 1, (max(iteration - 1, 0) * steps) // max(self.full_resolution_from - 1, 1))
        return self.coarse_downsample >> level

    def downsample_levels(self) -> list[int]:
        """Every factor :meth:`downsample_at` gives over the run, coarsest first."""
        if self.coarse_downsample <= 1 or self.full_resolution_from <= 1:
            return [1]
        return sorted({self.downsample_at(it) for it in range(1, min(self.full_resolution_from, self.iterations) + 1)}
                      | {1}, reverse=True)


@dataclass
class LearningRates:
    """Adam learning rates per parameter group."""

    position_init: float = setting(1.6e-4, help="surfel centres at the start (times the scene extent)",
                                   exclusiveMinimum=0.0)
    position_final: float = setting(1.6e-6, help="surfel centres at position_max_steps (log-linear decay)",
                                    exclusiveMinimum=0.0)
    position_max_steps: int = setting(30000, help="iterations of the position decay", minimum=1)
    sh_dc: float = setting(2e-3, help="SH DC coefficients", minimum=0.0)
    sh_rest: float | None = setting(
        None, help="SH coefficients of degree 1 and up (the view-dependent colour); null: sh_dc / 20, the 3DGS ratio",
        minimum=0.0)
    occupancy: float = setting(0.05, help="occupancy logits", minimum=0.0)
    opacity: float = setting(0.05, help="optical opacity logits", minimum=0.0)
    scaling: float = setting(2e-2, help="log scales (4x the 2DGS rate: surfels reach their size in a short run)",
                             minimum=0.0)
    rotation: float = setting(1e-3, help="rotation quaternions", minimum=0.0)
    reflectance: float = setting(5e-3, help="reflectance logits", minimum=0.0)
    roughness: float = setting(2e-3, help="roughness logits", minimum=0.0)
    transmissivity: float = setting(1e-2, help="transmissivity logits", minimum=0.0)
    scatter: float = setting(2e-3, help="scatter colours", minimum=0.0)
    material: float = setting(2e-3, help="material features", minimum=0.0)
    env_map: float = setting(2e-3, help="environment feature map", minimum=0.0)
    mlp: float = setting(5e-4, help="specular network", minimum=0.0)
    background: float = setting(1e-2, help="learned background map (model.background: learned)", minimum=0.0)
    mirror_plane_rotation: float = setting(
        0.0, help="the near reflections' mirror planes turned about their centres to fit the images (radians per "
        "Adam step; rtsplat.train.planes); 0 together with mirror_plane_shift: the planes stay as fitted",
        minimum=0.0)
    mirror_plane_shift: float = setting(
        0.0, help="the mirror planes moved along their normals to fit the images (times the scene extent per Adam "
        "step)", minimum=0.0)

    def scaled(self, factor: float) -> LearningRates:
        values = {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}
        return LearningRates(**{k: (v * factor if isinstance(v, float) else v) for k, v in values.items()})


@dataclass
class Losses:
    """Loss weights and the iterations they start at."""

    ssim_weight: float = setting(0.2, help="weight w of (1 - w) L1 + w (1 - SSIM)", minimum=0.0, maximum=1.0)
    perceptual_weight: float = setting(0.01, help="LPIPS-VGG term (needs real weights)", minimum=0.0)
    perceptual_from: int = setting(15000, help="the LPIPS term starts at this iteration", minimum=0)
    lpips_weights: str = setting("", help="path to the LPIPS-VGG weights; empty: look in the torch hub cache")
    normal_weight: float = setting(0.05, help="normal consistency (2DGS)", minimum=0.0)
    normal_from: int = setting(0, help="the normal term starts after this iteration", minimum=0)
    normal_depth: Literal["expected", "median"] = setting(
        "expected", help="the depth whose normals the surface normals are held to: expected (sum p z / sum p, "
        "2DGS's choice for unbounded scenes) or median (the surfel where the surface transmittance crosses 0.5, "
        "2DGS's choice for bounded ones). Behind glass the expected depth mixes the pane with what is seen "
        "through it; the median depth is the pane's wherever the pane holds most of the surface weight"
    )
    mask_weight: float = setting(0.01, help="transparent-mask BCE on the blended opacity", minimum=0.0)
    mask_opaque_target: Literal["surface", "one"] = setting(
        "surface", help="what the mask BCE asks of the blended opacity on pixels the mask does not mark: surface "
        "(as opaque as the surface alpha there: whatever surface the pixel has is opaque, and a pixel that sees "
        "the learned background is not asked to grow one; docs/fidelity.md, finding 11), or one (the paper: an "
        "opaque surface on every such pixel, the sky included)"
    )
    mask_coverage_weight: float = setting(
        0.01, help="BCE of the surface alpha against 1 on the pixels the transparent mask marks (mean over the "
        "image, as the mask BCE): the mask says a surface covers the pixel, so the glass grows no holes, where "
        "a pixel would show the volume colour without the glass's reflection (model.shade_coverage). The mask "
        "BCE alone can clear a see-through pixel by lowering the occupancy as well as the opacity (docs/fidelity.md, "
        "finding 36; 0: the paper's losses)", minimum=0.0
    )
    reflection_weight: float = setting(
        0.0, help="L1 of the reflection layer (roi C_spec, mean over the image): among decompositions that give "
        "the same image, prefer the one that leaves view-independent light to C_trans and C_scatter", minimum=0.0
    )
    shading_smoothness_weight: float = setting(
        0.0, help="mean absolute difference of the shading parameters (reflectance, roughness, material feature) "
        "between neighbouring pixels of the transparent mask: a pane is one material, so its reflection varies "
        "with the light it mirrors, not with a texture painted on the glass that the transmission would have to "
        "take back", minimum=0.0
    )
    distortion_weight: float = setting(0.0, help="2DGS depth distortion", minimum=0.0)
    transmissivity_bce_weight: float = setting(0.0, help="reference extra, off in the paper", minimum=0.0)
    occupancy_decay_weight: float = setting(0.0, help="reference extra, off in the paper", minimum=0.0)


@dataclass
class Densification:
    """Clone / split / prune / reset (adaptive density control)."""

    grad_threshold: float = setting(2e-4, help="densify surfels whose mean gradient reaches this",
                                    minimum=0.0)
    percent_dense: float = setting(
        0.01, help="clone if max scale <= percent_dense * extent, else split", minimum=0.0
    )
    split_mode: Literal["halves", "random"] = setting(
        "halves", help="halves: a split surfel becomes two surfels that tile it along its longer tangent axis "
        "(centres at +-0.6 x that scale, that scale x 0.6, the other kept), which changes the image far less than "
        "random (3DGS/2DGS: two surfels at N(0, scale) offsets, both scales / split_factor)"
    )
    split_factor: float = setting(1.6, help="split_mode random: the children get the parent's scales divided by "
                                  "this", exclusiveMinimum=0.0)
    clone_preserves_coverage: bool = setting(
        True, help="a clone and its original share what the original covered (occupancy 1 - sqrt(1 - occupancy), "
        "occupancy x opacity likewise), so two coincident copies cover what one did at its centre; false: both keep "
        "the original's values (3DGS), which doubles their coverage"
    )
    prune_occupancy: float = setting(0.05, help="prune surfels with occupancy below this", minimum=0.0, maximum=1.0)
    early_prune_occupancy: float = setting(
        0.0, help="before the first densification (every densify_every iterations below densify_from), prune the "
        "surfels seen so far whose occupancy is below this (at most prune_occupancy): the starting points that the "
        "images push out, which the first densification would prune anyway, stop costing time early; the see-through "
        "surface's seeds are spared. At 0.1 on the ten tuning scenes: 0.95x rtsplat's and 0.91x 2dgs's training CPU "
        "seconds for -0.05 / -0.08 and -0.09 / -0.01 dB (docs/performance.md, \"Pruning the starting surfels "
        "early\"). 0: off",
        minimum=0.0, maximum=1.0
    )
    max_screen_size: float = setting(0.0, help="prune surfels larger than this many pixels (0: off)", minimum=0.0)
    max_world_scale: float = setting(
        0.1, help="prune surfels larger than this fraction of the scene extent", minimum=0.0
    )
    reset_value: float = setting(
        0.01, help="a reset clamps occupancy (then, next time, opacity) to at most this", minimum=0.0, maximum=1.0
    )
    max_surfels: int = setting(200_000, help="no densification beyond this many surfels", minimum=1)
    initial_orientation: Literal["random", "point_normals"] = setting(
        "point_normals", help="how the surfels started at the SfM points face: point_normals: along the point "
        "cloud's local normal (the least-spread axis of each point's 16 nearest points; a point's copies share "
        "it), so that a surfel starts flat on the surface it samples (docs/fidelity.md, finding 17); or random "
        "(2DGS)"
    )
    initial_copies: int = setting(
        4, help="surfels started per SfM point: the point and copies - 1 more around it, offset by a normal "
        "deviate of half its RMS distance to its 3 nearest points (colour copied); a sparse SfM cloud otherwise "
        "leaves too few surfels for the few densifications of a short run to grow. 1: one surfel per point. Fewer "
        "copies, or a random subset of the points with one surfel each, when they exceed the cap that "
        "initial_budget_share and initial_pixels_per_surfel set (rtsplat/train/initial.py)",
        minimum=1,
    )
    initial_budget_share: float = setting(
        0.5, help="the surfels started from the SfM points are at most this share of max_surfels (the rest is "
        "left to densification)", exclusiveMinimum=0.0, maximum=1.0
    )
    initial_pixels_per_surfel: float = setting(
        1.0, help="... and at most one per this many training pixels (the training views at the training "
        "resolution, summed): more surfels than pixels have more parameters than the images have values. 0: no "
        "such cap", minimum=0.0
    )
    dense_start_per_pixel: float = setting(
        4.0, help="a start is dense when the surfels started from the SfM points number at least this many per "
        "pixel of a training view (at the training resolution, the views' mean); then "
        "schedule.dense_start_densify_from, where set, places the first density step (rtsplat/train/initial.py)",
        minimum=0.0
    )


@dataclass
class CameraRefinement:
    """Per-view pose corrections (see :mod:`rtsplat.train.cameras`): the training views' are learnt with
    the model; the test views' are fitted to their images, model fixed, before each evaluation, so that
    test PSNR measures the reconstruction rather than the error of the test views' SfM poses. The
    corrections are saved with the model and applied by ``rtsplat render``."""

    refine: bool = setting(
        True, help="learn a rotation and a translation per training view with the model; false: the prepared poses "
        "are used as they are, for training and for evaluation (no test-view fitting)"
    )
    refine_from: int = setting(100, help="the training views' corrections are learnt after this iteration",
                               minimum=0)
    lr_rotation: float = setting(1e-4, help="Adam learning rate of the training views' rotation corrections "
                                 "(radians)", minimum=0.0)
    lr_translation: float = setting(1e-4, help="Adam learning rate of their translation corrections (times the "
                                    "scene extent)", minimum=0.0)
    test_fit_steps: int = setting(
        3, help="Adam steps that fit each test view's correction before an evaluation during training, "
        "continuing from the previous evaluation's", minimum=0
    )
    final_fit_steps: int = setting(15, help="the same before the final evaluation", minimum=0)
    test_fit_lr: float = setting(1e-3, help="learning rate of the test-view fits (radians; translation: times the "
                                 "scene extent), decayed to a tenth over each fit", minimum=0.0)


@dataclass
class AppearanceSettings:
    """Per-view appearance corrections (:mod:`rtsplat.train.appearance`), when effects.appearance is on:
    learnt for the training views with the model, fitted in closed form for the test views before each
    evaluation, saved with the model and applied by ``rtsplat render``."""

    learn_from: int | None = setting(
        None, help="the training views' corrections are learnt after this iteration; null: after "
        "schedule.volume_until (the model has its first colours by then, so a view's gain does not take what the "
        "model has not learnt yet)", minimum=0
    )

    def start(self, schedule: Schedule) -> int:
        """The iteration after which the corrections are learnt."""
        return schedule.volume_until if self.learn_from is None else self.learn_from
    lr: float = setting(2e-3, help="Adam learning rate of the corrections (log gain, offset)", minimum=0.0)
    prior_weight: float = setting(
        1e-3, help="loss weight of the squared distance of the current view's correction from the identity; it "
        "keeps the model's colours at the photos' common exposure", minimum=0.0
    )
    test_prior: float = setting(
        1e-2, help="ridge weight (per pixel) of the test views' closed-form fits towards the identity", minimum=0.0
    )


@dataclass
class TrainConfig:
    """The trainer's config tree (rtsplat train)."""

    seed: int = setting(0, help="random seed", minimum=0)
    backend: str = setting("auto", help="rasterizer backend: auto (triton on a GPU, else cpu) | cpu | triton | "
                           "reference")
    device: str = setting(
        "auto", help="torch device: auto (the GPU when torch sees one, else the CPU) | cpu | cuda | cuda:N",
        pattern=DEVICE_PATTERN,
    )
    train_downsample: int = setting(
        1, help="train on the training views box-filtered by this factor (cameras scaled to match); test views, "
        "evaluation and rtsplat render stay at the prepared resolution", minimum=1
    )
    seed_transparent_surface: bool = setting(
        True, help="with transmission on and a prepared transparent_surface.npz, also start surfels on the "
        "masks' visual hull, oriented along its normals (clear: opacity 0.1, transmissivity 0.9)"
    )
    transparent_surface_scale: float = setting(
        1.0, help="the initial scale of the surfels started on the masks' visual hull, as a multiple of their "
        "points' neighbour distance (about the hull grid's step). Smaller seeds save little time and lose the "
        "glass (0.5: 0.95-1.02x the training CPU seconds, case-0 -1.15 / -1.29 dB), larger ones (1.5) changed "
        "nothing measurable (docs/performance.md, \"The glass seeds' size\")", exclusiveMinimum=0.0
    )
    ablations: Ablations = setting(help="the paper's ablation switches", factory=Ablations)
    effects: Effects = setting(help="which branches run", factory=Effects)
    gating: Gating = setting(help="specular-aware gradient gating", factory=Gating)
    schedule: Schedule = setting(help="iteration counts", factory=Schedule)
    lr: LearningRates = setting(help="learning rates", factory=LearningRates)
    losses: Losses = setting(help="loss weights", factory=Losses)
    densify: Densification = setting(help="adaptive density control", factory=Densification)
    model: ModelSettings = setting(help="model sizes and initial values", factory=ModelSettings)
    raster: RasterSettings = setting(help="rasterizer constants", factory=RasterSettings)
    cameras: CameraRefinement = setting(help="per-view pose corrections", factory=CameraRefinement)
    appearance: AppearanceSettings = setting(help="per-view exposure and white-balance corrections",
                                             factory=AppearanceSettings)

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, data: dict[str, Any] | None, source: str = "config") -> TrainConfig:
        """Checked against the schema (keys named ``train.<section>.<key>``), then built."""
        return schema.from_dict(cls, data, source=source, root="train")

    def validate(self, source: str = "config") -> TrainConfig:
        """The schema's checks on the current values, and the ones between keys."""
        schema.check(TrainConfig, self.to_dict(), source=source, root="train")
        check_backend_name(self.backend, "train.backend")
        s = self.schedule
        if not s.volume_until <= s.specular_from:
            raise ConfigError(
                "train.schedule: need volume_until <= specular_from "
                f"(got {s.volume_until}, {s.specular_from})"
            )
        if s.coarse_downsample & (s.coarse_downsample - 1):
            raise ConfigError(
                f"{source}: train.schedule.coarse_downsample must be a power of two (1, 2, 4, 8, ...), got "
                f"{s.coarse_downsample}: the factor halves at each step of the progressive resolution"
            )
        if not self.ablations.joint_optimization and s.background_phase_end() >= s.iterations:
            raise ConfigError(
                f"{source}: train.schedule.separate_background_until ({s.background_phase_end()}) must be below "
                f"train.schedule.iterations ({s.iterations}) when ablations.joint_optimization is off: the "
                "background-only phase would take the whole run; lower it, or set it to null (half the run)"
            )
        return self


# Settings a resumed run may change without --resume-with-new-config: the run's length or time budget (to
# train longer or stop sooner; with schedule.densify_until null, density control follows the new length),
# how often it logs, evaluates and writes checkpoints, and where it runs (device, rasterizer backend).
RESUME_MAY_CHANGE = frozenset({
    "schedule.iterations", "schedule.seconds", "schedule.log_every", "schedule.eval_every", "schedule.checkpoint_every",
    "device", "backend",
})


def resume_differences(checkpoint_config: dict[str, Any], cfg: TrainConfig) -> list[str]:
    """``key: old -> new`` for each setting that differs between a checkpoint's config and ``cfg``,
    leaving out :data:`RESUME_MAY_CHANGE`."""
    return [f"train.{key}: {old!r} -> {new!r}"
            for key, old, new in schema.differences(checkpoint_config, cfg.to_dict())
            if key not in RESUME_MAY_CHANGE]


# Every setting counted in iterations, by section (log_every stays: it is a logging rate).
ITERATION_COUNTS = {
    "schedule": ("iterations", "volume_until", "specular_from", "separate_background_until", "densify_from",
                 "dense_start_densify_from", "densify_until", "densify_every", "reset_every", "sh_degree_every",
                 "full_resolution_from", "checkpoint_every", "eval_every"),
    "lr": ("position_max_steps",),
    "losses": ("perceptual_from", "normal_from"),
    "cameras": ("refine_from",),
    "appearance": ("learn_from",),
}


def scale_budget(cfg: TrainConfig, factor: float) -> TrainConfig:
    """The same training stretched or shrunk to ``factor`` x the iterations: every iteration count of
    :data:`ITERATION_COUNTS` is multiplied (rounded; counts that were > 0 stay >= 1), so stages,
    densification, resets and the SH-degree steps keep their place in the run. The iteration-budget
    knob of the benchmark."""
    if not factor > 0:
        raise ConfigError(f"budget factor must be > 0, got {factor}")
    sections = {}
    for section, names in ITERATION_COUNTS.items():
        current = getattr(cfg, section)
        changes = {}
        for name in names:
            value = getattr(current, name)
            if value is not None:  # None: a count that follows the run's length
                changes[name] = max(int(round(value * factor)), 1) if value > 0 else value
        sections[section] = dataclasses.replace(current, **changes)
    return dataclasses.replace(cfg, **sections)
