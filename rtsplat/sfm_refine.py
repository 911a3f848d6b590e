"""Refinement of the chosen SfM model: denser tracks, then robust global bundle adjustment.

The mapping attempts build their tracks from the features they matched, and on small views of
scenes with glass these tracks are few and partly wrong (features on reflections and refractions
that do not sit on one 3D point). :func:`refine_model` keeps the chosen model's cameras and
rebuilds the structure:

1. features and matches with :func:`rtsplat.sfm_attempts.denser_features` (more, weaker SIFT
   features and guided matching; reused when the ladder already ran that step);
2. tracks triangulated with the model's poses fixed (``pycolmap.triangulate_points``, then every
   view's untriangulated matches again and the pairs that should share tracks);
3. ``sfm.refine_rounds`` rounds at most of global bundle adjustment with a Cauchy loss (poses,
   points and the focal length), track completion and merging, and removal of the observations
   that reproject farther than ``sfm.refine_max_reprojection_error``; the rounds stop early when
   few observations change.

The refined model replaces the chosen one only when it keeps every registered view, is
acceptable by the attempts' criteria (:func:`rtsplat.sfm_attempts.judge`) and has a lower mean
reprojection error; otherwise the chosen model stays and the result says why.
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass
from pathlib import Path

from rtsplat.config import SfmConfig
from rtsplat.sfm_attempts import AttemptRunner, AttemptSettings, denser_features, judge, model_stats

# image pairs with fewer matches give no tracks (the mappers' default)
_MIN_MATCHES = 15
# rounds stop once fewer than this fraction of the observations changed (COLMAP's own default)
_MIN_CHANGE = 0.0005


@dataclass
class RefinementResult:
    """What the refinement did to the chosen model."""

    settings: dict  # the AttemptSettings whose features and matches gave the tracks
    rounds: int
    max_reprojection_error: float
    registered: int = 0  # views of the refined model
    num_points_before: int = 0
    num_points: int = 0
    mean_reprojection_error_before: float | None = None
    mean_reprojection_error: float | None = None
    focal_length_before: list[float] | None = None  # per camera
    focal_length: list[float] | None = None
    seconds: float = 0.0
    kept: bool = False  # the refined model replaced the chosen one
    verdict: str = ""
    pose_errors: dict | None = None  # of the refined model against a reference model


def _focal_lengths(rec) -> list[float]:
    return [float(rec.camera(cid).mean_focal_length()) for cid in sorted(rec.cameras)]


def refine_model(rec, runner: AttemptRunner, first: AttemptSettings, cfg: SfmConfig, work: Path):
    """Refine ``rec`` (a pycolmap.Reconstruction, left unchanged); returns (RefinementResult, refined model).

    The refined model is returned whether or not it is kept (``result.kept``; ``rec`` itself when the
    triangulation failed); ``runner`` supplies the
    features and matches, ``work`` is an empty folder for the triangulation's output.
    """
    import pycolmap

    t0 = time.perf_counter()
    settings = denser_features(first)
    before = model_stats(rec, runner.names)
    result = RefinementResult(
        settings=asdict(settings),
        rounds=cfg.refine_rounds,
        max_reprojection_error=cfg.refine_max_reprojection_error,
        num_points_before=before.num_points,
        mean_reprojection_error_before=before.mean_reprojection_error,
        focal_length_before=_focal_lengths(rec),
    )
    db_path = runner.match_database(settings)
    work.mkdir(parents=True, exist_ok=True)
    try:
        refined = pycolmap.triangulate_points(
            pycolmap.Reconstruction(rec), str(db_path), str(runner.images_dir), str(work), clear_points=True
        )
    except (ValueError, RuntimeError) as exc:  # pycolmap's failed checks
        result.verdict = f"the triangulation with the denser features failed ({exc}); the chosen model stays"
        result.seconds = time.perf_counter() - t0
        return result, rec
    db = pycolmap.Database.open(str(db_path))
    try:
        cache_options = pycolmap.DatabaseCacheOptions()
        cache_options.min_num_matches = _MIN_MATCHES
        cache = pycolmap.DatabaseCache.create(db, cache_options)
    finally:
        db.close()
    mapper = pycolmap.IncrementalMapper(cache)
    mapper.begin_reconstruction(refined)
    triangulation = pycolmap.IncrementalTriangulatorOptions()
    triangulation.random_seed = cfg.seed
    options = pycolmap.IncrementalMapperOptions()
    options.filter_max_reproj_error = cfg.refine_max_reprojection_error
    options.num_threads = cfg.num_threads
    options.random_seed = cfg.seed
    ba = pycolmap.BundleAdjustmentOptions()
    ba.print_summary = False
    ba.refine_focal_length = True
    ba.ceres.loss_function_type = pycolmap.LossFunctionType.CAUCHY
    ba.ceres.solver_options.num_threads = cfg.num_threads
    for image_id in refined.reg_image_ids():
        mapper.triangulate_image(triangulation, image_id)
    mapper.retriangulate(triangulation)
    mapper.complete_and_merge_tracks(triangulation)
    mapper.iterative_global_refinement(cfg.refine_rounds, _MIN_CHANGE, options, ba, triangulation, True)
    mapper.end_reconstruction(False)

    after = model_stats(refined, runner.names)
    result.registered = after.registered
    result.num_points = after.num_points
    result.mean_reprojection_error = after.mean_reprojection_error
    result.focal_length = _focal_lengths(refined)
    acceptable, verdict = judge(after, cfg)
    lost = sorted(set(after.unregistered) - set(before.unregistered))
    if lost:
        result.verdict = f"the refined model lost {len(lost)} view(s): {', '.join(lost[:5])}"
    elif not acceptable:
        result.verdict = f"the refined model is not acceptable: {verdict}"
    elif before.mean_reprojection_error is not None and (
        after.mean_reprojection_error is None or after.mean_reprojection_error >= before.mean_reprojection_error
    ):
        result.verdict = "the refined model's mean reprojection error is not lower"
    else:
        result.kept = True
        result.verdict = "kept: every view, a lower mean reprojection error"
    result.seconds = time.perf_counter() - t0
    return result, refined


def describe_refinement(r: RefinementResult) -> str:
    """One line for the log."""

    def px(v: float | None) -> str:
        return "n/a" if v is None else f"{v:.3f} px"

    pose = ""
    if r.pose_errors:
        pose = (
            f", vs reference: rotation {r.pose_errors['rotation_error_deg_mean']:.3f} deg mean, "
            f"centre {100 * r.pose_errors['center_error_relative']:.2f}%"
        )
    focal = ""
    if r.focal_length_before and r.focal_length:
        focal = f", focal {r.focal_length_before[0]:.2f} -> {r.focal_length[0]:.2f} px"
    return (
        f"{r.registered} registered, {r.num_points_before} -> {r.num_points} points, "
        f"{px(r.mean_reprojection_error_before)} -> {px(r.mean_reprojection_error)}{focal}, "
        f"{r.seconds:.1f} s{pose}; {r.verdict}"
    )


__all__ = ["RefinementResult", "describe_refinement", "refine_model"]
