"""What the SfM stage measures and records: a model's statistics and the seconds of each step.

:class:`ModelStats` is the one description of a pycolmap.Reconstruction that the attempts, the
refinement and the summary use (registration, points, reprojection error, track length, points per
image); :func:`judge` says whether a model is acceptable. :class:`StepSeconds` adds up the seconds
of the named steps (feature extraction, matching, mapping, refinement, ...) for the summary.
"""

from __future__ import annotations

import time
from contextlib import contextmanager
from dataclasses import dataclass, field

from rtsplat.config import SfmConfig

# the steps a summary's ``step_seconds`` can name, in the order they run
STEPS = (
    "image_check",
    "feature_extraction",
    "matching",
    "mapping",
    "refinement_feature_extraction",
    "refinement_matching",
    "refinement_triangulation",
    "refinement_bundle_adjustment",
    "undistortion",
)


class StepSeconds:
    """Seconds spent per named step, added up over every time the step ran."""

    def __init__(self) -> None:
        self.seconds: dict[str, float] = {}

    @contextmanager
    def step(self, name: str):
        if name not in STEPS:
            raise ValueError(f"unknown SfM step {name!r}")
        t0 = time.perf_counter()
        try:
            yield
        finally:
            self.seconds[name] = self.seconds.get(name, 0.0) + time.perf_counter() - t0

    def as_dict(self) -> dict[str, float]:
        """The steps that ran, in the order of :data:`STEPS`."""
        return {name: round(self.seconds[name], 3) for name in STEPS if name in self.seconds}

    def since(self, before: dict[str, float]) -> dict[str, float]:
        """Seconds added per step since ``before`` (an earlier :meth:`as_dict`)."""
        now = self.as_dict()
        return {k: round(v - before.get(k, 0.0), 3) for k, v in now.items() if v - before.get(k, 0.0) > 0}


@dataclass
class ModelStats:
    """A model's registration and structure, as :func:`judge` and the summary read them."""

    registered: int = 0
    num_points: int = 0
    mean_reprojection_error: float | None = None  # None: no point observations
    median_points_per_image: float | None = None
    mean_track_length: float | None = None  # observations per 3D point
    num_observations: int = 0
    unregistered: list[str] = field(default_factory=list)


def model_stats(rec, names: list[str]) -> ModelStats:
    """Statistics of a pycolmap.Reconstruction (or None) over the images ``names``."""
    if rec is None or rec.num_reg_images() == 0:
        return ModelStats(unregistered=list(names))
    registered = {rec.image(i).name for i in rec.reg_image_ids()}
    per_image = sorted(rec.image(i).num_points3D for i in rec.reg_image_ids())
    observations = int(rec.compute_num_observations())
    return ModelStats(
        registered=len(registered),
        num_points=int(rec.num_points3D()),
        mean_reprojection_error=float(rec.compute_mean_reprojection_error()) if observations > 0 else None,
        median_points_per_image=float(per_image[len(per_image) // 2]),
        mean_track_length=float(rec.compute_mean_track_length()) if rec.num_points3D() > 0 else None,
        num_observations=observations,
        unregistered=[n for n in names if n not in registered],
    )


def judge(r: ModelStats, cfg: SfmConfig) -> tuple[bool, str]:
    """(acceptable, why) for a model's statistics (or anything with the same fields)."""
    if r.registered == 0:
        return False, "no model"
    if r.mean_reprojection_error is None:
        return False, "the model has no 3D points"
    if r.mean_reprojection_error > cfg.max_reprojection_error:
        return False, (
            f"mean reprojection error {r.mean_reprojection_error:.3f} px is above "
            f"sfm.max_reprojection_error {cfg.max_reprojection_error:g}"
        )
    if r.median_points_per_image is not None and r.median_points_per_image < cfg.min_points_per_image:
        return False, (
            f"its images see a median of {r.median_points_per_image:.0f} 3D points, fewer than "
            f"sfm.min_points_per_image {cfg.min_points_per_image}"
        )
    return True, "acceptable"


def px(value: float | None) -> str:
    """A reprojection error for a log line."""
    return "n/a" if value is None else f"{value:.3f} px"


__all__ = ["STEPS", "ModelStats", "StepSeconds", "judge", "model_stats", "px"]
