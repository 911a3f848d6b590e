"""Configuration of the RT-Splatting model and trainer (one dataclass tree).

Every ablation of the paper is a switch in :class:`Ablations`; each changes only the computation
it names. :class:`Effects` decides which branches run (``auto`` decides from the prepared scene).
Defaults follow METHOD.md sections 1-6 except the iteration counts, which are sized for a CPU.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any, Literal

from rtsplat.raster import RasterSettings


class ConfigError(ValueError):
    """A configuration value or key is wrong; the message names it and the fix."""


@dataclass
class Ablations:
    occupancy: bool = True  # off: one opacity does both jobs (surface weights = volume weights)
    joint_optimization: bool = True  # off: background first (transparent pixels masked), then frozen
    scattering: bool = True  # off: no C_scatter / tau (C_sub = C_trans)
    attenuation: bool = True  # off: beta = 1
    gating: bool = True  # off: g = 1 (no specular-aware gradient gating)
    mask_loss: bool = True  # off: no transparent-mask BCE


@dataclass
class Effects:
    """Which branches run. ``auto``: transmission iff the training masks have transparent pixels;
    specular iff the scene has a region of interest (reflections requested)."""

    transmission: Literal["auto", "on", "off"] = "auto"
    specular: Literal["auto", "on", "off"] = "auto"


@dataclass
class Gating:
    k: float = 4.0
    # "weighted_std": the reference code's weighted standard deviation (weights 1 - surface alpha,
    # reflect-padded 3x3 window), the default because it is what produced the paper's numbers;
    # "variance": the paper's equation, plain 3x3 variance of C_spec.
    mode: Literal["weighted_std", "variance"] = "weighted_std"


@dataclass
class Schedule:
    iterations: int = 3000
    volume_until: int = 300  # stage 1: volume colour only
    specular_from: int = 600  # stage 3 (full model) from here; stage 2 in between (no specular)
    separate_background_until: int = 1000  # joint_optimization off: background-only phase length
    densify_from: int = 500
    # last iteration (exclusive) of density control and resets; None: half the run, the 2DGS ratio (15000
    # of 30000), so that the second half refines a fixed set of surfels
    densify_until: int | None = None
    densify_every: int = 100
    reset_every: int = 1500  # alternating occupancy / opacity resets
    sh_degree_every: int = 1000  # one more SH degree every N iterations (3DGS), up to model.sh_degree
    log_every: int = 10
    checkpoint_every: int = 500
    def densify_stop(self) -> int:
        return self.iterations // 2 if self.densify_until is None else self.densify_until

    # test-view PSNR (entire / transparent) every N iterations into the log, for accuracy-against-
    # time curves; 0: only at the end. Evaluation time is not counted in the log's "seconds".
    eval_every: int = 0


@dataclass
class LearningRates:
    position_init: float = 1.6e-4
    position_final: float = 1.6e-6
    position_max_steps: int = 30000
    sh_dc: float = 2e-3  # rest / 20
    occupancy: float = 0.05
    opacity: float = 0.05
    scaling: float = 5e-3
    rotation: float = 1e-3
    reflectance: float = 5e-3
    roughness: float = 2e-3
    transmissivity: float = 1e-2
    scatter: float = 2e-3
    material: float = 2e-3
    env_map: float = 2e-3
    mlp: float = 5e-4
    background: float = 1e-2

    def scaled(self, factor: float) -> LearningRates:
        values = {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}
        return LearningRates(**{k: (v * factor if isinstance(v, float) else v) for k, v in values.items()})


@dataclass
class Losses:
    ssim_weight: float = 0.2
    perceptual_weight: float = 0.01
    perceptual_from: int = 15000
    lpips_weights: str = ""  # path to LPIPS-VGG weights; empty: look in the torch hub cache
    normal_weight: float = 0.05
    normal_from: int = 0
    mask_weight: float = 0.01
    distortion_weight: float = 0.0
    transmissivity_bce_weight: float = 0.0  # reference extra, off in the paper
    occupancy_decay_weight: float = 0.0  # reference extra, off in the paper


@dataclass
class Densification:
    grad_threshold: float = 2e-4
    percent_dense: float = 0.01  # clone if max scale <= percent_dense * extent, else split
    # "halves": a split surfel becomes two surfels that tile it along its longer tangent axis (centres at
    # +-0.6 x that scale, that scale x 0.6, the other kept), which changes the image 3x less than
    # "random" (3DGS/2DGS: two surfels at N(0, scale) offsets, both scales / split_factor)
    split_mode: Literal["halves", "random"] = "halves"
    split_factor: float = 1.6
    # a clone and its original share what the original covered: occupancy 1 - sqrt(1 - occupancy) and
    # occupancy x opacity likewise, so two coincident copies cover what one did at its centre (the
    # opacity correction of Rota Bulo et al. 2024); 3DGS keeps both at the original's values, which
    # doubles their coverage
    clone_preserves_coverage: bool = True
    prune_occupancy: float = 0.05
    max_screen_size: float = 0.0  # prune surfels larger than this many pixels (0: off)
    max_world_scale: float = 0.1  # prune surfels larger than this fraction of the scene extent
    reset_value: float = 0.01
    max_surfels: int = 200_000


@dataclass
class ModelSettings:
    sh_degree: int = 3
    env_channels: int = 16
    env_height: int = 512
    env_width: int = 1024
    env_levels: int = 9
    mlp_width: int = 256
    occupancy_init: float = 0.1
    opacity_init: float = 0.5
    transmissivity_init: float = 0.5
    roughness_init: float = 0.1
    reflectance_init: float = 0.5
    shade_alpha_threshold: float = 0.05
    # radiance where the volume transmittance is left (rtsplat/model/background.py), the same for every
    # method: "learned" (a direction-indexed RGB map), "black", "white", or "random" (a random colour per
    # training step, black when evaluating and rendering; for views whose empty pixels carry no colour)
    background: Literal["learned", "black", "white", "random"] = "learned"
    background_height: int = 256  # finest level; 0.7 degrees per texel, about a pixel of the demo views
    background_width: int = 512
    background_levels: int = 5


@dataclass
class TrainConfig:
    seed: int = 0
    backend: str = "auto"
    device: str = "cpu"
    # resolution knob: train on the training views box-filtered by this factor (cameras scaled to match);
    # test views, evaluation and `rtsplat render` stay at the prepared resolution
    train_downsample: int = 1
    ablations: Ablations = field(default_factory=Ablations)
    effects: Effects = field(default_factory=Effects)
    gating: Gating = field(default_factory=Gating)
    schedule: Schedule = field(default_factory=Schedule)
    lr: LearningRates = field(default_factory=LearningRates)
    losses: Losses = field(default_factory=Losses)
    densify: Densification = field(default_factory=Densification)
    model: ModelSettings = field(default_factory=ModelSettings)
    raster: RasterSettings = field(default_factory=RasterSettings)

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, data: dict[str, Any] | None) -> TrainConfig:
        return _build(cls, data or {}, "train")

    def validate(self) -> TrainConfig:
        s = self.schedule
        if s.iterations <= 0:
            raise ConfigError("train.schedule.iterations must be > 0")
        if not 0 <= s.volume_until <= s.specular_from:
            raise ConfigError(
                "train.schedule: need 0 <= volume_until <= specular_from "
                f"(got {s.volume_until}, {s.specular_from})"
            )
        if s.densify_until is not None and (isinstance(s.densify_until, bool) or not isinstance(s.densify_until, int)
                                            or s.densify_until < 0):
            raise ConfigError(f"train.schedule.densify_until must be an iteration >= 0 or null (half the run), "
                              f"got {s.densify_until!r}")
        if self.train_downsample < 1:
            raise ConfigError(f"train.train_downsample must be >= 1, got {self.train_downsample}")
        if self.gating.k < 0:
            raise ConfigError("train.gating.k must be >= 0")
        for name in ("transmission", "specular"):
            if getattr(self.effects, name) not in ("auto", "on", "off"):
                raise ConfigError(f"train.effects.{name} must be auto, on or off")
        if self.densify.split_mode not in ("halves", "random"):
            raise ConfigError(f"train.densify.split_mode must be halves or random, got {self.densify.split_mode!r}")
        if self.gating.mode not in ("weighted_std", "variance"):
            raise ConfigError("train.gating.mode must be 'weighted_std' or 'variance'")
        m = self.model
        if m.background not in ("learned", "black", "white", "random"):
            raise ConfigError(f"train.model.background must be learned, black, white or random, got {m.background!r}")
        if m.background_height < 2 or m.background_width < 2 or m.background_levels < 1:
            raise ConfigError("train.model: background_height, background_width >= 2 and background_levels >= 1 "
                              "required")
        if self.model.env_levels < 1 or self.model.env_height < 2 or self.model.env_width < 2:
            raise ConfigError("train.model: env_levels >= 1 and env_height/env_width >= 2 required")
        return self


def _build(cls, data: dict[str, Any], where: str):
    if not isinstance(data, dict):
        raise ConfigError(f"{where} must be a mapping, got {type(data).__name__}")
    fields = {f.name: f for f in dataclasses.fields(cls)}
    unknown = sorted(set(data) - set(fields))
    if unknown:
        raise ConfigError(
            f"unknown key(s) {', '.join(where + '.' + k for k in unknown)}; valid keys: {', '.join(sorted(fields))}"
        )
    values = {}
    defaults = cls()
    for name, value in data.items():
        default = getattr(defaults, name)
        if dataclasses.is_dataclass(default):
            values[name] = _build(type(default), value, f"{where}.{name}")
        elif isinstance(default, bool):
            if not isinstance(value, bool):
                raise ConfigError(f"{where}.{name} must be true or false, got {value!r}")
            values[name] = value
        elif value is None and default is None:
            values[name] = None
        elif isinstance(default, (int, float)) and not isinstance(default, bool):
            if isinstance(value, bool) or not isinstance(value, (int, float)):
                raise ConfigError(f"{where}.{name} must be a number, got {value!r}")
            values[name] = type(default)(value) if isinstance(default, float) or float(value).is_integer() else value
        elif isinstance(default, tuple):
            values[name] = tuple(value)
        else:
            values[name] = value
    return cls(**values)


# Every setting counted in iterations, by section (log_every stays: it is a logging rate).
ITERATION_COUNTS = {
    "schedule": ("iterations", "volume_until", "specular_from", "separate_background_until", "densify_from",
                 "densify_until", "densify_every", "reset_every", "sh_degree_every", "checkpoint_every",
                 "eval_every"),
    "lr": ("position_max_steps",),
    "losses": ("perceptual_from", "normal_from"),
}


def scale_budget(cfg: TrainConfig, factor: float) -> TrainConfig:
    """The same training stretched or shrunk to ``factor`` x the iterations: every iteration count of
    :data:`ITERATION_COUNTS` is multiplied (rounded; counts that were > 0 stay >= 1), so stages,
    densification and resets keep their place in the run. The iteration-budget knob of the benchmark."""
    if not factor > 0:
        raise ConfigError(f"budget factor must be > 0, got {factor}")
    sections = {}
    for section, names in ITERATION_COUNTS.items():
        current = getattr(cfg, section)
        changes = {}
        for name in names:
            value = getattr(current, name)
            if value is not None:
                changes[name] = max(int(round(value * factor)), 1) if value > 0 else value
        sections[section] = dataclasses.replace(current, **changes)
    return dataclasses.replace(cfg, **sections)
