"""Check a synthetic dataset against structure from motion (pycolmap): registration, reprojection
error, and pose error after a similarity alignment to the ground truth.

Used by the test suite; also handy by hand::

    python -m rtsplat.synth.sfm_check <dataset dir> <work dir> [--focal F] [--colmap-thresholds]

SfM runs from the images alone (the dataset's ``sparse/0`` is not used): SIFT, exhaustive
matching, incremental mapping with one shared ``SIMPLE_PINHOLE`` camera whose focal length is
estimated unless ``--focal`` is given.
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np


@dataclass(frozen=True)
class Thresholds:
    """Geometric thresholds in pixels.

    COLMAP's defaults (4 px) suit multi-megapixel photos; at ~200 x 150 pixels 4 px is over a
    degree, and matches on view-dependent glass reflections that move by a few pixels survive and
    bias bundle adjustment. :data:`SMALL_IMAGES` is used for images up to 800 pixels wide.
    """

    two_view_max_error: float = 4.0  # RANSAC inlier threshold of the two-view geometry
    init_max_error: float = 4.0  # initial pair
    filter_max_reproj_error: float = 4.0  # observations with a larger error are dropped


COLMAP_DEFAULTS = Thresholds()
SMALL_IMAGES = Thresholds(two_view_max_error=1.5, init_max_error=2.0, filter_max_reproj_error=2.0)


def _image_size(image_dir: Path) -> tuple[int, int]:
    import cv2

    first = sorted(p for p in Path(image_dir).iterdir() if p.suffix.lower() == ".png")[0]
    h, w = cv2.imread(str(first), cv2.IMREAD_UNCHANGED).shape[:2]
    return w, h


def run_colmap(
    image_dir: Path,
    work_dir: Path,
    num_threads: int = 2,
    focal_px: float | None = None,
    thresholds: Thresholds | None = None,
    seed: int = 0,
):
    """SIFT + exhaustive matching + incremental mapping; returns the largest reconstruction (or None).

    ``focal_px``: a known focal length (a calibrated camera), kept fixed in bundle adjustment;
    by default COLMAP estimates it. ``thresholds``: default :data:`SMALL_IMAGES` for images up to
    800 pixels wide, else :data:`COLMAP_DEFAULTS`. ``seed``: RANSAC and mapper seed.
    """
    import cv2  # noqa: F401  (before pycolmap: importing pycolmap first breaks zlib users such as PNG writers)
    import pycolmap

    image_dir, work_dir = Path(image_dir), Path(work_dir)
    w, h = _image_size(image_dir)
    if thresholds is None:
        thresholds = SMALL_IMAGES if max(w, h) <= 800 else COLMAP_DEFAULTS
    work_dir.mkdir(parents=True, exist_ok=True)
    database = work_dir / "database.db"
    if database.exists():
        database.unlink()
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = "SIMPLE_PINHOLE"
    if focal_px is not None:
        reader.camera_params = f"{focal_px},{w / 2},{h / 2}"
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.num_threads = num_threads
    extraction.use_gpu = False
    pycolmap.extract_features(
        database,
        image_dir,
        camera_mode=pycolmap.CameraMode.SINGLE,
        reader_options=reader,
        extraction_options=extraction,
        device=pycolmap.Device.cpu,
    )
    matching = pycolmap.FeatureMatchingOptions()
    matching.num_threads = num_threads
    matching.use_gpu = False
    verification = pycolmap.TwoViewGeometryOptions()
    verification.ransac.max_error = thresholds.two_view_max_error
    verification.ransac.random_seed = seed
    pycolmap.match_exhaustive(
        database, matching_options=matching, verification_options=verification, device=pycolmap.Device.cpu
    )
    options = pycolmap.IncrementalPipelineOptions()
    options.num_threads = num_threads
    options.random_seed = seed
    options.mapper.init_max_error = thresholds.init_max_error
    options.mapper.filter_max_reproj_error = thresholds.filter_max_reproj_error
    if focal_px is not None:
        options.ba_refine_focal_length = False
        options.ba_refine_principal_point = False
        options.mapper.abs_pose_refine_focal_length = False
    recs = pycolmap.incremental_mapping(database, image_dir, work_dir / "sparse", options=options)
    if not recs:
        return None
    return max(recs.values(), key=lambda r: r.num_reg_images())


def similarity(src: np.ndarray, dst: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """Least-squares similarity (scale s, rotation R, translation t) with dst ~ s R src + t."""
    mu_s, mu_d = src.mean(0), dst.mean(0)
    a, b = src - mu_s, dst - mu_d
    u, sig, vt = np.linalg.svd(b.T @ a / len(src))
    d = np.ones(3)
    if np.linalg.det(u @ vt) < 0:
        d[2] = -1
    R = u @ np.diag(d) @ vt
    s = float((sig * d).sum() / (a**2).sum(axis=1).mean())
    return s, R, mu_d - s * R @ mu_s


def _angle_deg(R: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1.0, 1.0))))


def compare_to_ground_truth(rec, dataset_dir: Path) -> dict:
    """Registration ratio, mean reprojection error, and pose errors after similarity alignment.

    ``rotation_error_deg_*``: the similarity is fitted to the camera centres (as COLMAP's model
    aligner does) and each camera's orientation compared with the ground truth. Centres on an
    orbit constrain the tilt of that fit only weakly, so two alignment-free views are given too:
    ``orientation_aligned_*`` (the rotation fitted to the orientations) and ``relative_*`` (the
    rotation between every pair of cameras).
    """
    cams = json.loads((Path(dataset_dir) / "cameras.json").read_text())["cameras"]
    gt = {c["name"]: np.asarray(c["world_to_camera"], dtype=np.float64) for c in cams}
    names, est_R, est_c, gt_R, gt_c = [], [], [], [], []
    for image in rec.images.values():
        if image.name not in gt:
            continue
        m = np.asarray(image.cam_from_world().matrix(), dtype=np.float64)
        names.append(image.name)
        est_R.append(m[:, :3])
        est_c.append(-m[:, :3].T @ m[:, 3])
        gt_R.append(gt[image.name][:3, :3])
        gt_c.append(-gt[image.name][:3, :3].T @ gt[image.name][:3, 3])
    if len(names) < 3:
        return {"views": len(gt), "registered": len(names), "registered_ratio": len(names) / len(gt)}
    est_c, gt_c = np.array(est_c), np.array(gt_c)
    s, R, t = similarity(est_c, gt_c)
    aligned = (s * (R @ est_c.T)).T + t
    rot_err = [_angle_deg((Re @ R.T) @ Rg.T) for Re, Rg in zip(est_R, gt_R, strict=True)]
    u, _, vt = np.linalg.svd(sum(Rg.T @ Re for Re, Rg in zip(est_R, gt_R, strict=True)))
    R_o = u @ np.diag([1.0, 1.0, np.linalg.det(u @ vt)]) @ vt
    rot_err_o = [_angle_deg((Re @ R_o.T) @ Rg.T) for Re, Rg in zip(est_R, gt_R, strict=True)]
    n = len(est_R)
    rel = [_angle_deg((est_R[i] @ est_R[j].T) @ (gt_R[i] @ gt_R[j].T).T) for i in range(n) for j in range(i + 1, n)]
    extent = float(np.linalg.norm(gt_c - gt_c.mean(0), axis=1).mean())
    focal = [float(c.params[0]) for c in rec.cameras.values()]
    return {
        "views": len(gt),
        "registered": len(names),
        "registered_ratio": len(names) / len(gt),
        "mean_reprojection_error_px": float(rec.compute_mean_reprojection_error()),
        "points3D": int(rec.num_points3D()),
        "rotation_error_deg_mean": float(np.mean(rot_err)),
        "rotation_error_deg_max": float(np.max(rot_err)),
        "orientation_aligned_rotation_error_deg_mean": float(np.mean(rot_err_o)),
        "orientation_aligned_rotation_error_deg_max": float(np.max(rot_err_o)),
        "relative_rotation_error_deg_mean": float(np.mean(rel)),
        "relative_rotation_error_deg_max": float(np.max(rel)),
        "center_error_mean": float(np.linalg.norm(aligned - gt_c, axis=1).mean()),
        "center_error_relative": float(np.linalg.norm(aligned - gt_c, axis=1).mean() / extent),
        "focal_px_estimated": focal[0] if len(focal) == 1 else focal,
        "focal_px_true": float(cams[0]["K"][0][0]),
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m rtsplat.synth.sfm_check", description=__doc__.split("\n\n")[0])
    parser.add_argument("dataset", type=Path, help="a dataset written by 'rtsplat synth'")
    parser.add_argument("work", type=Path, help="work folder for COLMAP's database and models")
    parser.add_argument("--focal", type=float, default=None, help="known focal length in pixels (kept fixed)")
    parser.add_argument(
        "--colmap-thresholds", action="store_true", help="COLMAP's default 4 px thresholds even for small images"
    )
    args = parser.parse_args(argv)
    if not (args.dataset / "images").is_dir() or not (args.dataset / "cameras.json").is_file():
        print(f"sfm_check: error: {args.dataset} is not a synth dataset (images/ and cameras.json)", file=sys.stderr)
        return 2
    rec = run_colmap(
        args.dataset / "images",
        args.work,
        focal_px=args.focal,
        thresholds=COLMAP_DEFAULTS if args.colmap_thresholds else None,
    )
    if rec is None:
        print("no reconstruction")
        return 1
    print(json.dumps(compare_to_ground_truth(rec, args.dataset), indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
