"""Refinement of the chosen SfM model: tracks rebuilt with its poses, then robust global bundle adjustment.

The mapping attempts build their tracks from the features they matched, and on small views of
scenes with glass these tracks are few and partly wrong (features on reflections and refractions
that do not sit on one 3D point). :func:`refine_model` keeps the chosen model's cameras and
rebuilds the structure:

1. the tracks' features and matches (``sfm.refine_features``): ``attempt`` reuses the chosen
   attempt's own database (no extraction, no matching); ``denser`` extracts more, weaker SIFT
   features (:func:`rtsplat.sfm.attempts.denser_features`) and matches them, guided by the two-view
   geometry, only on the pairs the model needs (:func:`refinement_pairs`: pairs that share 3D points
   in the chosen model, and each view's nearest views by camera centre); a ladder step that already
   matched those features is reused; ``auto`` (:func:`refinement_features`) takes ``denser`` where the
   attempt found few features per image (small or plain photos: sparse tracks, and denser features
   that are cheap to match) and ``attempt`` where it found many (guided matching costs about the
   square of the features per pair: on 8192-feature photos it did not finish in 10 minutes);
2. tracks triangulated with the model's poses fixed (``pycolmap.triangulate_points``, then every
   view's untriangulated matches again and the pairs that should share tracks); the model is first
   renumbered to the database's image, camera, rig and frame ids, matched by image name
   (:func:`with_database_ids`: extraction on several threads numbers the images in the order they
   are written, so two databases can disagree);
3. ``sfm.refine_rounds`` rounds at most of global bundle adjustment with a Cauchy loss (poses,
   points and the focal length), track completion and merging, and removal of the observations
   that reproject farther than ``sfm.refine_max_reprojection_error``; the rounds stop early when
   few observations change.

:func:`refinement_needed` skips all of it when the chosen model registers every view at a mean
reprojection error at most ``sfm.refine_skip_reprojection_error``. The refined model replaces the
chosen one only when it keeps every registered view, is acceptable by the attempts' criteria
(:func:`rtsplat.sfm.stats.judge`) and has a lower mean reprojection error; otherwise the chosen
model stays and the result says why.
"""

from __future__ import annotations

import copy
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from rtsplat.config import SfmConfig
from rtsplat.sfm.attempts import AttemptResult, AttemptSettings, denser_features
from rtsplat.sfm.matching import FeatureStore
from rtsplat.sfm.stats import judge, model_stats, px

# image pairs with fewer matches give no tracks (the mappers' default)
_MIN_MATCHES = 15
# rounds stop once fewer than this fraction of the observations changed (COLMAP's own default)
_MIN_CHANGE = 0.0005
# refinement_pairs: views that share this many 3D points of the chosen model are matched again
_MIN_SHARED_POINTS = 15


@dataclass
class RefinementResult:
    """What the refinement did to the chosen model."""

    settings: dict  # the AttemptSettings whose features and matches gave the tracks
    rounds: int
    max_reprojection_error: float
    skipped: bool = False  # the chosen model was accurate enough (refinement_needed)
    features: str = ""  # the tracks' features, "attempt" or "denser" (auto resolved); skipped: the config's value
    features_reason: str = ""  # why those features
    matched_pairs: int | None = None  # pairs matched for the refinement (None: matches reused)
    registered: int = 0  # views of the refined model
    num_points_before: int = 0
    num_points: int = 0
    mean_reprojection_error_before: float | None = None
    mean_reprojection_error: float | None = None
    focal_length_before: list[float] | None = None  # per camera
    focal_length: list[float] | None = None
    mean_track_length_before: float | None = None
    mean_track_length: float | None = None
    seconds: float = 0.0
    step_seconds: dict[str, float] = field(default_factory=dict)
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


def refinement_needed(chosen: AttemptResult, total: int, cfg: SfmConfig) -> tuple[bool, str]:
    """(refine, why): the refinement is skipped when the chosen model registers all ``total`` views at a
    mean reprojection error at most ``sfm.refine_skip_reprojection_error``."""
    if not cfg.refine:
        return False, "sfm.refine is off"
    err = chosen.mean_reprojection_error
    threshold = cfg.refine_skip_reprojection_error
    if chosen.registered == total and err is not None and err <= threshold:
        return False, (
            f"skipped: the chosen model registers every view at {err:.3f} px, at most "
            f"sfm.refine_skip_reprojection_error {threshold:g} px"
        )
    missing = total - chosen.registered
    why = f"{missing} view(s) unregistered" if missing else f"mean reprojection error {px(err)} above {threshold:g} px"
    return True, why


def mean_features_per_image(database: Path) -> float:
    """The mean number of SIFT keypoints per image of a COLMAP database."""
    import pycolmap

    db = pycolmap.Database.open(str(database))
    try:
        images = db.num_images()
        return db.num_keypoints() / images if images else 0.0
    finally:
        db.close()


def refinement_features(cfg: SfmConfig, mean_features: float | None) -> tuple[str, str]:
    """("attempt" or "denser", why) for ``sfm.refine_features``; ``auto`` decides from the chosen attempt's
    ``mean_features`` per image against ``sfm.refine_denser_max_features`` (only ``auto`` reads it: None
    otherwise)."""
    if cfg.refine_features != "auto":
        return cfg.refine_features, f"sfm.refine_features is {cfg.refine_features}"
    limit = cfg.refine_denser_max_features
    if mean_features <= limit:
        return "denser", (f"auto: the attempt found {mean_features:.0f} features per image, at most "
                          f"sfm.refine_denser_max_features {limit}: denser features")
    return "attempt", (f"auto: the attempt found {mean_features:.0f} features per image, more than "
                       f"sfm.refine_denser_max_features {limit}: the attempt's own tracks")


def refinement_pairs(rec, neighbours: int) -> list[tuple[str, str]]:
    """Image-name pairs to match for the refinement: registered views that share at least
    ``_MIN_SHARED_POINTS`` 3D points of ``rec``, and each registered view with its ``neighbours``
    nearest registered views by camera centre that look the same way (viewing directions within 90 degrees)."""
    ids = sorted(rec.reg_image_ids())
    index = {image_id: k for k, image_id in enumerate(ids)}
    shared = np.zeros((len(ids), len(ids)), dtype=np.int64)
    for point in rec.points3D.values():
        seen = sorted({index[el.image_id] for el in point.track.elements if el.image_id in index})
        for a_pos, a in enumerate(seen):
            for b in seen[a_pos + 1 :]:
                shared[a, b] += 1
    keep = {(a, b) for a, b in zip(*np.nonzero(shared >= _MIN_SHARED_POINTS), strict=True)}
    if neighbours > 0 and len(ids) > 1:
        poses = [rec.image(i).cam_from_world() for i in ids]
        centres = np.stack([np.asarray(p.inverse().translation) for p in poses])
        axes = np.stack([np.asarray(p.rotation.matrix())[2] for p in poses])  # viewing directions in the world
        dist = np.linalg.norm(centres[:, None] - centres[None], axis=-1)
        dist[axes @ axes.T <= 0.0] = np.inf
        np.fill_diagonal(dist, np.inf)
        for a in range(len(ids)):
            for b in np.argsort(dist[a])[:neighbours]:
                if np.isfinite(dist[a, b]):
                    keep.add((min(a, int(b)), max(a, int(b))))
    names = [rec.image(i).name for i in ids]
    return sorted((names[a], names[b]) for a, b in keep)


def refine_model(
    rec, store: FeatureStore, chosen: AttemptSettings, first: AttemptSettings, cfg: SfmConfig, work: Path
):
    """Refine ``rec`` (a pycolmap.Reconstruction, left unchanged); returns (RefinementResult, refined model).

    ``chosen``: the settings of the attempt that gave ``rec`` (its database is reused with
    ``sfm.refine_features: attempt``); ``first``: the first attempt's settings, made denser with
    ``sfm.refine_features: denser`` (``auto`` chooses between them: :func:`refinement_features`). The
    refined model is returned whether or not it is kept (``result.kept``; ``rec`` itself when the
    triangulation failed); ``work`` is an empty folder for the triangulation's output.
    """
    import pycolmap

    t0 = time.perf_counter()
    steps_before = store.times.as_dict()
    before = model_stats(rec, store.names)
    mean_features = mean_features_per_image(store.features(chosen)) if cfg.refine_features == "auto" else None
    features, features_reason = refinement_features(cfg, mean_features)
    settings = chosen if features == "attempt" else denser_features(first)
    result = RefinementResult(
        settings=asdict(settings),
        rounds=cfg.refine_rounds,
        max_reprojection_error=cfg.refine_max_reprojection_error,
        features=features,
        features_reason=features_reason,
        num_points_before=before.num_points,
        mean_reprojection_error_before=before.mean_reprojection_error,
        mean_track_length_before=before.mean_track_length,
        focal_length_before=_focal_lengths(rec),
    )

    def finish():
        result.seconds = time.perf_counter() - t0
        result.step_seconds = store.times.since(steps_before)

    if features == "attempt":
        db_path = store.matches(chosen, chosen.matcher)  # the chosen attempt's own: no extraction, no matching
    else:
        db_path = store.existing_matches(settings)  # a ladder step already matched these features
    if db_path is None:
        pairs = refinement_pairs(rec, cfg.refine_pose_neighbours)
        result.matched_pairs = len(pairs)
        db_path = store.matches_for_pairs(settings, pairs, "refinement_matching", "refinement_feature_extraction")
    work.mkdir(parents=True, exist_ok=True)
    with store.times.step("refinement_triangulation"):
        try:
            refined = pycolmap.triangulate_points(
                with_database_ids(rec, db_path), str(db_path), str(store.images_dir), str(work), clear_points=True
            )
        except (ValueError, RuntimeError) as exc:  # pycolmap's failed checks
            refined = None
            failure = exc
    if refined is None:
        result.verdict = f"the triangulation with the refinement's features failed ({failure}); the chosen model stays"
        finish()
        return result, rec
    with store.times.step("refinement_bundle_adjustment"):
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

    after = model_stats(refined, store.names)
    result.registered = after.registered
    result.num_points = after.num_points
    result.mean_reprojection_error = after.mean_reprojection_error
    result.mean_track_length = after.mean_track_length
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
    finish()
    return result, refined


def describe_refinement(r: RefinementResult) -> str:
    """One line for the log."""

    if r.skipped:
        return r.verdict
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
        + ("" if r.matched_pairs is None else f" ({r.matched_pairs} pairs matched)")
        + (f"; tracks from {r.features} features ({r.features_reason})" if r.features_reason else "")
    )


__all__ = [
    "RefinementResult",
    "describe_refinement",
    "mean_features_per_image",
    "refine_model",
    "refinement_features",
    "refinement_needed",
    "refinement_pairs",
    "with_database_ids",
]
