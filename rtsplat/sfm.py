"""``rtsplat sfm``: camera poses and sparse points with pycolmap.

Function API :func:`run_sfm`. When the dataset already has ``sparse/0`` the model is validated and
used as-is (no SfM). Otherwise: SIFT extraction (one shared camera by default), matching
(exhaustive for small sets, sequential for ordered captures; both vocabulary-free), incremental
mapping; the largest model is kept. Either way, a camera model with distortion is undistorted to
PINHOLE (images and model), and the stage fails with a clear message when too few images register.

Output folder::

    sfm/summary.json     {"model_dir", "image_dir", "source": "dataset"|"sfm", "undistorted",
                          "registered", "total", "mean_reprojection_error", ...}
    sfm/sparse/0/        the model (copied from the dataset or computed)
    sfm/undistorted/     images/ and sparse/ after undistortion (only when needed)

``model_dir``/``image_dir`` in the summary are what ``rtsplat prepare`` reads.
"""

from __future__ import annotations

import argparse
import shutil
import tempfile
from dataclasses import asdict, dataclass
from pathlib import Path

from rtsplat.config import SfmConfig, add_config_arguments, stage_config_from_args
from rtsplat.errors import PipelineError
from rtsplat.io.atomic import atomic_dir, write_json_atomic
from rtsplat.io.colmap import is_model_dir, load_model
from rtsplat.io.images import list_images, read_mask, validate_image_set, write_mask


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
    matcher: str = ""


def _check_registration(registered: list[str], names: list[str], cfg: SfmConfig, where: Path, computed: bool) -> None:
    total = len(names)
    need = max(cfg.min_registered_images, int(round(cfg.min_registered_fraction * total)))
    if len(registered) < need:
        missing = sorted(set(names) - set(registered))
        shown = ", ".join(missing[:5]) + (f" and {len(missing) - 5} more" if len(missing) > 5 else "")
        fix = (
            "take more overlapping, textured photos; try sfm.matcher: exhaustive; or lower "
            "sfm.min_registered_fraction / sfm.min_registered_images"
            if computed
            else "re-run COLMAP on all images, or delete sparse/0 so 'rtsplat sfm' computes a model, "
            "or lower sfm.min_registered_fraction"
        )
        raise PipelineError(
            f"only {len(registered)} of {total} images are registered in the COLMAP model "
            f"(need at least {need}); not registered: {shown}",
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


def _reconstruct(images_dir: Path, names: list[str], work: Path, cfg: SfmConfig, masks_dir: Path | None):
    import pycolmap

    db = work / "database.db"
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = cfg.camera_model
    if masks_dir is not None and cfg.use_masks:
        _colmap_masks(names, masks_dir, work / "colmap_masks")
        reader.mask_path = str(work / "colmap_masks")
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.max_image_size = cfg.max_image_size
    extraction.num_threads = cfg.num_threads
    extraction.use_gpu = False
    extraction.sift.max_num_features = cfg.max_num_features
    mode = pycolmap.CameraMode.SINGLE if cfg.single_camera else pycolmap.CameraMode.AUTO
    pycolmap.extract_features(
        db,
        images_dir,
        image_names=names,
        camera_mode=mode,
        reader_options=reader,
        extraction_options=extraction,
        device=pycolmap.Device.cpu,
    )
    matcher = cfg.matcher
    if matcher == "auto":
        matcher = "exhaustive" if len(names) <= cfg.exhaustive_max_images else "sequential"
    matching = pycolmap.FeatureMatchingOptions()
    matching.use_gpu = False
    matching.num_threads = cfg.num_threads
    if matcher == "exhaustive":
        pycolmap.match_exhaustive(db, matching_options=matching, device=pycolmap.Device.cpu)
    else:
        pairing = pycolmap.SequentialPairingOptions()
        pairing.overlap = cfg.sequential_overlap
        pairing.loop_detection = False  # needs a vocabulary tree
        pycolmap.match_sequential(db, matching_options=matching, pairing_options=pairing, device=pycolmap.Device.cpu)
    options = pycolmap.IncrementalPipelineOptions()
    options.num_threads = cfg.num_threads
    options.random_seed = cfg.seed
    options.min_model_size = 2
    recs = pycolmap.incremental_mapping(db, images_dir, work / "models", options=options)
    return recs, matcher


def run_sfm(
    scene_dir: str | Path,
    out_dir: str | Path,
    cfg: SfmConfig | None = None,
    masks_dir: str | Path | None = None,
    progress: bool = True,
) -> SfmSummary:
    """Poses for ``<scene_dir>/images`` into ``out_dir`` (atomically); see the module docstring."""
    import pycolmap

    cfg = cfg or SfmConfig()
    scene_dir = Path(scene_dir)
    images_dir = scene_dir / "images"
    out_dir = Path(out_dir)
    headers = validate_image_set(images_dir, decode=True, progress=progress)
    names = [h.path.name for h in headers]
    given = scene_dir / "sparse" / "0"
    matcher = ""
    with atomic_dir(out_dir) as tmp:
        model_dir = tmp / "sparse" / "0"
        if cfg.use_dataset_model and is_model_dir(given):
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
            _check_registration([v.name for v in model.views], names, cfg, given, computed=False)
            rec = pycolmap.Reconstruction(str(given))
            source = "dataset"
        else:
            if len(names) < 2:
                raise PipelineError(
                    "SfM needs at least 2 images", path=images_dir, fix="add more overlapping photos of the scene"
                )
            with tempfile.TemporaryDirectory(prefix="rtsplat-sfm-", dir=tmp) as work:
                recs, matcher = _reconstruct(images_dir, names, Path(work), cfg, Path(masks_dir) if masks_dir else None)
                if not recs:
                    raise PipelineError(
                        f"SfM registered no images ({len(names)} given): no image pair could be matched",
                        path=images_dir,
                        fix="take more overlapping, textured photos, or try sfm.matcher: exhaustive",
                    )
                rec = max(recs.values(), key=lambda r: r.num_reg_images())
                reg = [rec.image(i).name for i in rec.reg_image_ids()]
                _check_registration(reg, names, cfg, images_dir, computed=True)
            source = "sfm"
        model_dir.mkdir(parents=True)
        rec.write_binary(str(model_dir))
        cams = [rec.camera(cid) for cid in rec.cameras]
        distorted = any(c.model_name not in ("SIMPLE_PINHOLE", "PINHOLE") for c in cams)
        final_model, final_images = out_dir / "sparse" / "0", images_dir.resolve()
        if distorted:
            und = tmp / "undistorted"
            pycolmap.undistort_images(str(und), str(model_dir), str(images_dir), output_type="COLMAP")
            final_model = out_dir / "undistorted" / "sparse"
            final_images = out_dir.resolve() / "undistorted" / "images"
            rec = pycolmap.Reconstruction(str(und / "sparse"))
            shutil.rmtree(und / "stereo", ignore_errors=True)  # dense-stereo scaffolding we do not use
            for script in und.glob("*.sh"):
                script.unlink()
        summary = SfmSummary(
            source=source,
            registered=int(rec.num_reg_images()),
            total=len(names),
            num_points=int(rec.num_points3D()),
            mean_reprojection_error=(
                float(rec.compute_mean_reprojection_error()) if rec.compute_num_observations() > 0 else None
            ),
            undistorted=distorted,
            camera_model=",".join(sorted({c.model_name for c in cams})),
            model_dir=str(final_model.resolve()),
            image_dir=str(final_images),
            matcher=matcher,
        )
        write_json_atomic(tmp / "summary.json", asdict(summary))
    return summary


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--scene-dir", type=Path, required=True, help="dataset scene (<data>/<scene>)")
    parser.add_argument("--out", type=Path, required=True, help="output folder (results/<scene>/sfm)")
    parser.add_argument("--masks", type=Path, help="output of 'rtsplat masks' (used when sfm.use_masks)")
    parser.add_argument("--matcher", choices=["auto", "exhaustive", "sequential"], help="override sfm.matcher")
    parser.add_argument("--num-threads", type=int, help="override sfm.num_threads (the workflow passes its threads)")
    add_config_arguments(parser)


def run(args: argparse.Namespace) -> int:
    cfg = stage_config_from_args(args, "sfm", {"matcher": args.matcher, "num_threads": args.num_threads})
    s = run_sfm(args.scene_dir, args.out, cfg, args.masks)
    err = "n/a" if s.mean_reprojection_error is None else f"{s.mean_reprojection_error:.3f} px"
    how = "model from the dataset" if s.source == "dataset" else f"SfM ({s.matcher} matching)"
    print(
        f"sfm {args.scene_dir}: {how}: {s.registered}/{s.total} images registered, {s.num_points} points, "
        f"mean reprojection error {err}, camera {s.camera_model}"
        + (", undistorted to PINHOLE" if s.undistorted else "")
    )
    return 0


__all__ = ["SfmSummary", "run_sfm", "list_images"]
