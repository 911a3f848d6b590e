"""``rtsplat sfm``: the stage's orchestrator, :func:`run_sfm`.

When ``sfm.use_dataset_model`` is set and the dataset has ``sparse/0``
(or, said in the log, the model files directly in ``sparse/``), that model is validated and
used as-is (no SfM). Otherwise SfM runs from the images, each step timed:

1. the matcher is chosen from the capture (:mod:`rtsplat.sfm.matching`: exhaustive for small sets,
   sequential for larger ordered captures, retrieval with a vocabulary tree when one is given);
2. attempts (:mod:`rtsplat.sfm.attempts`): SIFT extraction (one shared camera by default), matching,
   mapping. The first attempt uses the configured settings; while views are missing from its largest
   model, further attempts (at most ``sfm.max_attempts`` in all) retry with settings suited to the
   failure. The attempt whose largest model registers the most views at an acceptable reprojection
   error is kept. When the dataset has a ``sparse/0`` that is not used, every attempt's poses are
   compared with it after a similarity fit (:mod:`rtsplat.pose_eval`; the synthetic scenes ship their
   ground-truth cameras there);
3. with ``sfm.refine`` (default) the chosen model is refined (:mod:`rtsplat.sfm.refine`) unless it
   already registers every view at a mean reprojection error at most
   ``sfm.refine_skip_reprojection_error``; the refined model is written when it keeps every view at a
   lower mean reprojection error; the refinement (or why it was skipped) is listed in the summary
   either way, and ``pose_errors`` are those of the model written.

Either way, a camera model with distortion is undistorted to PINHOLE (images and model), and the
stage fails with a clear message (the unregistered images and the attempts) when too few images
register; the output folder is then left as it was. :mod:`rtsplat.sfm.stats` holds the model
statistics every step reports and the per-step seconds.

Output folder::

    sfm/summary.json     {"model_dir", "image_dir", "source": "dataset"|"sfm", "undistorted",
                          "registered", "total", "num_points", "mean_reprojection_error",
                          "mean_track_length", "unregistered", "matcher", "matcher_reason",
                          "attempts": [{"name", "reason", "settings", "registered", "models",
                          "mean_reprojection_error", "seconds", "step_seconds", "acceptable", ...}],
                          "chosen_attempt", "choice", "reference_model", "pose_errors",
                          "refinement": {"skipped", "verdict", "registered", "mean_reprojection_error_before",
                          "mean_reprojection_error", "seconds", "step_seconds", "kept", "pose_errors", ...},
                          "seconds", "step_seconds": {step: seconds},
                          "scene_dir", "photos": {name: fingerprint}, "images_fingerprint"}
    sfm/sparse/0/        the model (copied from the dataset or computed)
    sfm/undistorted/     images/ and sparse/ after undistortion (only when needed)

``model_dir``/``image_dir`` in the summary are what ``rtsplat prepare`` reads; ``photos`` (the content
fingerprint of each photo, :func:`rtsplat.io.manifest.photo_fingerprints`) is what it compares with the
scene's photos to refuse the SfM of another scene. ``--masks`` of other photos are refused the same way.
``step_seconds``
names the steps of :data:`rtsplat.sfm.stats.STEPS` that ran; an attempt's ``seconds`` include the
feature extraction and matching it was the first to need.
"""

from __future__ import annotations

import argparse
import json
import shutil
import tempfile
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from rtsplat.config import SfmConfig, add_config_arguments, stage_config_from_args
from rtsplat.errors import PipelineError
from rtsplat.io.atomic import write_json_atomic
from rtsplat.io.colmap import dataset_model_dir, load_model
from rtsplat.io.images import read_mask, validate_image_set, write_mask
from rtsplat.io.manifest import check_made_from_photos, photo_fingerprints, photos_fingerprint
from rtsplat.io.outputs import check_output_dir, output_dir
from rtsplat.pose_eval import compare_poses
from rtsplat.sfm.attempts import (
    AttemptResult,
    AttemptSettings,
    better,
    describe,
    first_settings,
    next_attempt,
    run_attempt,
)
from rtsplat.sfm.matching import FeatureStore, capture_order, choose_matcher
from rtsplat.sfm.refine import RefinementResult, describe_refinement, refine_model, refinement_needed
from rtsplat.sfm.stats import StepSeconds, model_stats


@dataclass
class SfmSummary:
    source: str  # "dataset" (sparse/0 was given) or "sfm"
    registered: int
    total: int
    num_points: int
    mean_reprojection_error: float | None  # None: the model has no point observations
    undistorted: bool
    camera_model: str
    model_dir: str
    image_dir: str
    matcher: str = ""  # matcher of the chosen attempt ("" for a dataset model)
    matcher_reason: str = ""  # why that matcher (the first attempt's choice, and the retry's when it changed it)
    mean_track_length: float | None = None  # observations per 3D point of the written model
    unregistered: list[str] = field(default_factory=list)
    attempts: list[dict] = field(default_factory=list)  # AttemptResult fields, in the order they ran
    chosen_attempt: int | None = None  # index into attempts
    choice: str = ""  # why that attempt
    reference_model: str | None = None  # the dataset's sparse/0 the poses were compared with
    pose_errors: dict | None = None  # PoseErrors fields of the written model against reference_model
    refinement: dict | None = None  # RefinementResult fields (None: sfm.refine off, or a dataset model)
    seconds: float = 0.0
    scene_dir: str = ""  # the dataset scene it was made from (for messages)
    images_fingerprint: str = ""  # rtsplat.io.manifest.photos_fingerprint of its photos
    photos: dict[str, str] = field(default_factory=dict)  # rtsplat.io.manifest.photo_fingerprints of its photos
    step_seconds: dict[str, float] = field(default_factory=dict)  # seconds per step (rtsplat.sfm.stats.STEPS)


def _check_registration(
    registered: list[str], names: list[str], cfg: SfmConfig, where: Path, computed: bool, attempts: str = "",
    images_dir: Path | None = None,
) -> None:
    total = len(names)
    by_fraction = int(round(cfg.min_registered_fraction * total))
    need = max(cfg.min_registered_images, by_fraction)
    if total < cfg.min_registered_images:
        raise PipelineError(
            f"the scene has {total} image(s) but sfm.min_registered_images is {cfg.min_registered_images}: "
            "at least that many must be registered",
            path=images_dir or where,
            fix=f"add photos (at least {cfg.min_registered_images} overlapping views in all), or lower "
            f"sfm.min_registered_images (2 at the least) in the config",
        )
    if len(registered) < need:
        limit = (f"sfm.min_registered_images is {need}" if need == cfg.min_registered_images
                 else f"sfm.min_registered_fraction {cfg.min_registered_fraction:g} of {total}")
        missing = sorted(set(names) - set(registered))
        shown = ", ".join(missing[:5]) + (f" and {len(missing) - 5} more" if len(missing) > 5 else "")
        if attempts:
            shown = ", ".join(missing) + "; attempts:" + attempts
        fix = (
            "take more overlapping, textured photos; raise sfm.max_attempts; or lower "
            "sfm.min_registered_fraction / sfm.min_registered_images"
            if computed
            else f"re-run COLMAP on all images, or delete {where} so 'rtsplat sfm' computes a model, "
            "or lower sfm.min_registered_fraction / sfm.min_registered_images"
        )
        raise PipelineError(
            f"only {len(registered)} of {total} images are registered in the COLMAP model "
            f"(need at least {need}: {limit}); not registered: {shown}",
            path=where,
            fix=fix,
        )


def _colmap_masks(image_names: list[str], masks_dir: Path, out: Path) -> None:
    """COLMAP feature masks: black where the transparent mask is white (no features on glass)."""
    out.mkdir(parents=True, exist_ok=True)
    for name in image_names:
        src = masks_dir / f"{Path(name).stem}.png"
        if src.is_file():
            write_mask(out / f"{name}.png", ~read_mask(src))


def _reference_poses(scene_dir: Path) -> tuple[Path, dict[str, np.ndarray]] | None:
    """World-to-camera matrices of the dataset's own model (``sparse/0`` or ``sparse/``), when it has one."""
    given = dataset_model_dir(scene_dir)
    if given is None:
        return None
    try:
        model = load_model(given)
    except PipelineError:
        return None  # a broken reference only loses the check
    return given, {v.name: v.world_to_camera for v in model.views}


def _rec_poses(rec) -> dict[str, np.ndarray]:
    return {
        rec.image(i).name: np.asarray(rec.image(i).cam_from_world().matrix(), dtype=np.float64)
        for i in rec.reg_image_ids()
    }


def _reconstruct(store: FeatureStore, first, reference: dict[str, np.ndarray] | None, log):
    """Attempts until every view registers or the ladder ends.

    Returns (chosen rec, attempts, its index, choice).
    """
    cfg, names = store.cfg, store.names
    attempts: list[AttemptResult] = []
    recs = []
    best: int | None = None
    step: tuple | None = ("configured", "the configured settings", first)
    while step is not None and len(attempts) < cfg.max_attempts:
        name, reason, settings = step
        log(f"sfm attempt {len(attempts) + 1}/{cfg.max_attempts}: {name} ({reason})")
        result, rec = run_attempt(store, len(attempts), name, reason, settings)
        if rec is not None and reference is not None:
            errors = compare_poses(_rec_poses(rec), reference)
            result.pose_errors = asdict(errors) if errors else None
        attempts.append(result)
        recs.append(rec)
        log(f"sfm attempt {len(attempts)}: {describe(result, len(names))}")
        if best is None or better(result, attempts[best]):
            best = len(attempts) - 1
        chosen = attempts[best]
        if chosen.acceptable and not chosen.unregistered:
            break
        missing = chosen.unregistered if chosen.registered else list(names)
        poor = store.poorly_matched(settings, settings.matcher, missing)
        step = next_attempt([a.name for a in attempts], first, chosen if chosen.registered else None, poor)
    chosen = attempts[best]
    if len(attempts) == 1:
        choice = (
            "the first attempt registered every view" if not chosen.unregistered else "no retries (sfm.max_attempts 1)"
        )
    else:
        others = ", ".join(f"{a.name} {a.registered}" for i, a in enumerate(attempts) if i != best)
        why = "registers the most views" + (" at an acceptable reprojection error" if chosen.acceptable else "")
        choice = f"attempt {best + 1} ({chosen.name}, {chosen.registered}/{len(names)}) {why}; others: {others}"
        if chosen.unregistered and len(attempts) < cfg.max_attempts:
            choice += "; no further step suits the failure"
    return recs[best], attempts, best, choice


def _attempts_text(attempts: list[AttemptResult], total: int) -> str:
    return "".join(f"\n    {i + 1}. {describe(a, total)}" for i, a in enumerate(attempts))


def _log(message: str) -> None:
    print(message, flush=True)


def run_sfm(
    scene_dir: str | Path,
    out_dir: str | Path,
    cfg: SfmConfig | None = None,
    masks_dir: str | Path | None = None,
    progress: bool = True,
    log=_log,
) -> SfmSummary:
    """Poses for ``<scene_dir>/images`` into ``out_dir`` (atomically); see the module docstring.

    ``log``: called with one line per attempt (default: print).
    """
    import pycolmap

    t0 = time.perf_counter()
    cfg = cfg or SfmConfig()
    scene_dir = Path(scene_dir)
    images_dir = scene_dir / "images"
    out_dir = Path(out_dir)
    check_output_dir(out_dir, "sfm", inputs=[scene_dir, masks_dir])
    times = StepSeconds()
    with times.step("image_check"):
        headers = validate_image_set(images_dir, decode=True, progress=progress, log=log)
    names = [h.path.name for h in headers]
    photos = photo_fingerprints(images_dir)
    if masks_dir is not None and (Path(masks_dir) / "summary.json").is_file():
        masks_summary = json.loads((Path(masks_dir) / "summary.json").read_text())
        check_made_from_photos(masks_dir, masks_summary, "masks", images_dir, photos, "--masks")
    given = dataset_model_dir(scene_dir)
    if given is not None and given.name == "sparse":
        log(f"sfm: {given} holds a COLMAP model directly (no sparse/0 folder); "
            + ("using it" if cfg.use_dataset_model else "comparing the computed poses with it"))
    attempts: list[AttemptResult] = []
    chosen, choice, pose_errors, reference_dir, refinement = None, "", None, None, None
    matcher, matcher_reason = "", ""
    with output_dir(out_dir, "sfm", inputs=[scene_dir, masks_dir]) as tmp:
        model_dir = tmp / "sparse" / "0"
        if cfg.use_dataset_model and given is not None:
            model = load_model(given)  # validates
            absent = [v.name for v in model.views if not (images_dir / v.name).is_file()]
            if absent:
                shown = ", ".join(absent[:5]) + (f" and {len(absent) - 5} more" if len(absent) > 5 else "")
                raise PipelineError(
                    f"the COLMAP model lists {len(absent)} image(s) that are not in {images_dir}: {shown}",
                    path=given,
                    fix="restore those images, or set sfm.use_dataset_model: false (or delete sparse/0) so "
                    "'rtsplat sfm' computes a model from the images that are there",
                )
            _check_registration([v.name for v in model.views], names, cfg, given, computed=False,
                                images_dir=images_dir)
            rec = pycolmap.Reconstruction(str(given))
            source = "dataset"
        else:
            if len(names) < 2:
                raise PipelineError(
                    "SfM needs at least 2 images", path=images_dir, fix="add more overlapping photos of the scene"
                )
            ref = _reference_poses(scene_dir)
            order = capture_order(images_dir, names)
            matcher, matcher_reason = choose_matcher(cfg, order)
            log(f"sfm: {matcher} matching: {matcher_reason}")
            with tempfile.TemporaryDirectory(prefix="rtsplat-sfm-", dir=tmp) as work:
                mask_dir = None
                if masks_dir is not None and cfg.use_masks:
                    mask_dir = Path(work) / "colmap_masks"
                    _colmap_masks(names, Path(masks_dir), mask_dir)
                store = FeatureStore(images_dir, order, Path(work), cfg, mask_dir, times)
                first = first_settings(cfg, matcher)
                rec, attempts, chosen, choice = _reconstruct(store, first, ref[1] if ref else None, log)
                best = attempts[chosen]
                if best.settings["matcher"] != first.matcher:
                    matcher_reason = (
                        f"first {first.matcher} ({matcher_reason}); the chosen attempt {best.name}: {best.reason}"
                    )
                matcher = best.settings["matcher"]
                log(f"sfm: chose {choice}")
                if rec is None or best.registered == 0:
                    raise PipelineError(
                        f"SfM registered no images ({len(names)} given) in {len(attempts)} attempt(s):"
                        + _attempts_text(attempts, len(names)),
                        path=images_dir,
                        fix="take more overlapping, textured photos, or try sfm.matcher: exhaustive",
                    )
                _check_registration(
                    [n for n in names if n not in best.unregistered],
                    names,
                    cfg,
                    images_dir,
                    computed=True,
                    attempts=_attempts_text(attempts, len(names)),
                    images_dir=images_dir,
                )
                if not best.acceptable:
                    raise PipelineError(
                        f"no SfM attempt gave an acceptable model (the best: {best.verdict}); attempts:"
                        + _attempts_text(attempts, len(names)),
                        path=images_dir,
                        fix="raise sfm.max_reprojection_error or lower sfm.min_points_per_image if the model is "
                        "good enough for you, or take sharper, more overlapping photos",
                    )
                if ref is not None:
                    pose_errors = best.pose_errors
                if cfg.refine:
                    needed, why = refinement_needed(best, len(names), cfg)
                    if not needed:
                        refinement = RefinementResult(
                            settings=best.settings,
                            rounds=0,
                            max_reprojection_error=cfg.refine_max_reprojection_error,
                            skipped=True,
                            features=cfg.refine_features,
                            verdict=why,
                        )
                    else:
                        log(f"sfm refinement of attempt {chosen + 1} ({best.name}): {why}")
                        chosen_settings = AttemptSettings(**best.settings)
                        refinement, refined = refine_model(
                            rec, store, chosen_settings, first, cfg, Path(work) / "refined"
                        )
                        if ref is not None:
                            errors = compare_poses(_rec_poses(refined), ref[1])
                            refinement.pose_errors = asdict(errors) if errors else None
                        if refinement.kept:
                            rec = refined
                            pose_errors = refinement.pose_errors
                    log(f"sfm refinement: {describe_refinement(refinement)}")
            if ref is not None:
                reference_dir = str(ref[0])
            source = "sfm"
        model_dir.mkdir(parents=True)
        rec.write_binary(str(model_dir))
        cams = [rec.camera(cid) for cid in rec.cameras]
        distorted = any(c.model_name not in ("SIMPLE_PINHOLE", "PINHOLE") for c in cams)
        final_model, final_images = out_dir / "sparse" / "0", images_dir.resolve()
        if distorted:
            und = tmp / "undistorted"
            with times.step("undistortion"):
                pycolmap.undistort_images(str(und), str(model_dir), str(images_dir), output_type="COLMAP")
            final_model = out_dir / "undistorted" / "sparse"
            final_images = out_dir.resolve() / "undistorted" / "images"
            rec = pycolmap.Reconstruction(str(und / "sparse"))
            shutil.rmtree(und / "stereo", ignore_errors=True)  # dense-stereo scaffolding we do not use
            for script in und.glob("*.sh"):
                script.unlink()
        stats = model_stats(rec, names)
        summary = SfmSummary(
            source=source,
            registered=stats.registered,
            total=len(names),
            num_points=stats.num_points,
            mean_reprojection_error=stats.mean_reprojection_error,
            mean_track_length=stats.mean_track_length,
            undistorted=distorted,
            camera_model=",".join(sorted({c.model_name for c in cams})),
            model_dir=str(final_model.resolve()),
            image_dir=str(final_images),
            matcher=matcher,
            matcher_reason=matcher_reason,
            unregistered=stats.unregistered,
            attempts=[asdict(a) for a in attempts],
            chosen_attempt=chosen,
            choice=choice,
            reference_model=reference_dir,
            pose_errors=pose_errors,
            refinement=asdict(refinement) if refinement else None,
            seconds=time.perf_counter() - t0,
            scene_dir=str(scene_dir.resolve()),
            images_fingerprint=photos_fingerprint(photos),
            photos=photos,
            step_seconds=times.as_dict(),
        )
        write_json_atomic(tmp / "summary.json", asdict(summary))
    return summary


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--scene-dir", type=Path, required=True, help="dataset scene (<data>/<scene>)")
    parser.add_argument("--out", type=Path, required=True, help="output folder (results/<scene>/sfm)")
    parser.add_argument("--masks", type=Path, help="output of 'rtsplat masks' (used when sfm.use_masks)")
    parser.add_argument(
        "--matcher", choices=["auto", "exhaustive", "sequential", "vocabtree"], help="override sfm.matcher"
    )
    parser.add_argument("--num-threads", type=int, help="override sfm.num_threads (the workflow passes its threads)")
    add_config_arguments(parser)


def run(args: argparse.Namespace) -> int:
    cfg = stage_config_from_args(args, "sfm", {"matcher": args.matcher, "num_threads": args.num_threads})
    s = run_sfm(args.scene_dir, args.out, cfg, args.masks)
    err = "n/a" if s.mean_reprojection_error is None else f"{s.mean_reprojection_error:.3f} px"
    how = "model from the dataset" if s.source == "dataset" else f"SfM ({s.matcher} matching: {s.matcher_reason})"
    pose = ""
    if s.pose_errors:
        pose = (
            f"; against {s.reference_model}: rotation error {s.pose_errors['rotation_error_deg_mean']:.3f} deg "
            f"mean, centre error {100 * s.pose_errors['center_error_relative']:.2f}% of the camera spread"
        )
    print(
        f"sfm {args.scene_dir}: {how}: {s.registered}/{s.total} images registered, {s.num_points} points, "
        f"mean reprojection error {err}, camera {s.camera_model}"
        + (", undistorted to PINHOLE" if s.undistorted else "")
        + (f", {len(s.attempts)} attempt(s)" if s.attempts else "")
        + (", refined" if s.refinement and s.refinement["kept"] else "")
        + (", refinement skipped" if s.refinement and s.refinement["skipped"] else "")
        + (f", {s.seconds:.0f} s" if s.attempts else "")
        + pose
    )
    if s.attempts:
        print("sfm seconds per step: " + ", ".join(f"{k} {v:.1f}" for k, v in s.step_seconds.items()))
    return 0


__all__ = ["SfmSummary", "add_arguments", "run", "run_sfm"]
