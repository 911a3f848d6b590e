"""Refinement of the chosen SfM model: denser tracks, then robust global bundle adjustment.

The mapping attempts build their tracks from the features they matched, and on small views of
scenes with glass these tracks are few and partly wrong (features on reflections and refractions
that do not sit on one 3D point). :func:`refine_model` keeps the chosen model's cameras and
rebuilds the structure:

1. features and matches with :func:`rtsplat.sfm_attempts.denser_features` (more, weaker SIFT
   features and guided matching; reused when the ladder already ran that step);
2. tracks triangulated with the model's poses fixed (``pycolmap.triangulate_points``, then every
   view's untriangulated matches again and the pairs that should share tracks); the model is first
   renumbered to the denser database's image, camera, rig and frame ids, matched by image name
   (:func:`with_database_ids`: extraction on several threads numbers the images in the order they
   are written, so the two databases can disagree);
3. ``sfm.refine_rounds`` rounds at most of global bundle adjustment with a Cauchy loss (poses,
   points and the focal length), track completion and merging, and removal of the observations
   that reproject farther than ``sfm.refine_max_reprojection_error``; the rounds stop early when
   few observations change.

The refined model replaces the chosen one only when it keeps every registered view, is
acceptable by the attempts' criteria (:func:`rtsplat.sfm_attempts.judge`) and has a lower mean
reprojection error; otherwise the chosen model stays and the result says why.
"""

from __future__ import annotations

import copy
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


def with_database_ids(rec, db_path: Path):
    """A pycolmap.Reconstruction with ``rec``'s poses and calibration under the ids of the database at ``db_path``.

    Feature extraction numbers images, cameras, rigs and frames in the order its threads write
    them, so two databases of the same images can number them differently. The result takes every
    id, rig and frame from the database and matches the views to ``rec``'s by image name: a frame
    gets the pose of the ``rec`` frame that holds the same-named image (unregistered when ``rec``
    has no pose for it), a camera the calibration of the ``rec`` camera of its images. Images
    carry no 2D points (``pycolmap.triangulate_points`` reads them from the database).
    """
    import pycolmap

    db = pycolmap.Database.open(str(db_path))
    try:
        db_cameras = {c.camera_id: c for c in db.read_all_cameras()}
        db_rigs = db.read_all_rigs()
        db_frames = db.read_all_frames()
        db_images = db.read_all_images()
    finally:
        db.close()
    by_name = {im.name: im for im in rec.images.values()}
    out = pycolmap.Reconstruction()
    for camera_id, db_camera in sorted(db_cameras.items()):
        matched = [by_name[im.name] for im in db_images if im.camera_id == camera_id and im.name in by_name]
        camera = copy.copy(rec.camera(matched[0].camera_id)) if matched else db_camera
        camera.camera_id = camera_id
        out.add_camera(camera)
    for rig in db_rigs:
        out.add_rig(rig)
    db_names = {im.image_id: im.name for im in db_images}
    posed = []
    for frame in db_frames:
        for data_id in frame.image_ids:
            model_image = by_name.get(db_names.get(data_id.id))
            if model_image is not None and rec.frame(model_image.frame_id).has_pose():
                frame.rig_from_world = rec.frame(model_image.frame_id).rig_from_world
                posed.append(frame.frame_id)
                break
        out.add_frame(frame)
    for db_image in db_images:
        image = pycolmap.Image(name=db_image.name, camera_id=db_image.camera_id, image_id=db_image.image_id)
        image.frame_id = db_image.frame_id
        out.add_image(image)
    for frame_id in posed:
        out.register_frame(frame_id)
    return out


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
            with_database_ids(rec, db_path), str(db_path), str(runner.images_dir), str(work), clear_points=True
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


__all__ = ["RefinementResult", "describe_refinement", "refine_model", "with_database_ids"]
