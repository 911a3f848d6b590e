"""Camera poses against reference poses: a similarity fit, then rotation and centre errors.

SfM recovers cameras up to a similarity (scale, rotation, translation). :func:`compare_poses` fits
that similarity to the camera centres (least squares, as COLMAP's model aligner does) and compares
each camera's orientation and centre with the reference. Centres on an orbit constrain the tilt
of that fit only weakly, so two alignment-free measures come with it: the rotation fitted to the
orientations alone, and the rotation between every pair of cameras.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class PoseErrors:
    """Errors of the cameras found in both sets, after a similarity fit to the centres."""

    compared: int  # cameras present in both the estimate and the reference
    rotation_error_deg_mean: float
    rotation_error_deg_max: float
    orientation_aligned_rotation_error_deg_mean: float
    orientation_aligned_rotation_error_deg_max: float
    relative_rotation_error_deg_mean: float
    relative_rotation_error_deg_max: float
    center_error_mean: float  # in the reference's units
    center_error_relative: float  # center_error_mean / mean distance of the reference centres to their mean


def similarity(src: np.ndarray, dst: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """Least-squares similarity (scale s, rotation R, translation t) with ``dst ~ s R src + t``.

    ``src``, ``dst``: [N, 3] corresponding points, N >= 3 and not all on one line.
    """
    mu_s, mu_d = src.mean(0), dst.mean(0)
    a, b = src - mu_s, dst - mu_d
    u, sig, vt = np.linalg.svd(b.T @ a / len(src))
    d = np.ones(3)
    if np.linalg.det(u @ vt) < 0:
        d[2] = -1
    R = u @ np.diag(d) @ vt
    s = float((sig * d).sum() / (a**2).sum(axis=1).mean())
    return s, R, mu_d - s * R @ mu_s


def rotation_angle_deg(R: np.ndarray) -> float:
    """Angle of a rotation matrix in degrees."""
    return float(np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1.0, 1.0))))


def camera_center(world_to_camera: np.ndarray) -> np.ndarray:
    """Centre of a camera given its [3, 4] or [4, 4] world-to-camera matrix."""
    return -world_to_camera[:3, :3].T @ world_to_camera[:3, 3]


def compare_poses(estimate: dict[str, np.ndarray], reference: dict[str, np.ndarray]) -> PoseErrors | None:
    """Compare world-to-camera matrices ([3, 4] or [4, 4]) keyed by image name.

    Only the names in both dicts are compared; None when fewer than 3 are.
    """
    names = sorted(set(estimate) & set(reference))
    if len(names) < 3:
        return None
    est_R = [np.asarray(estimate[n], dtype=np.float64)[:3, :3] for n in names]
    ref_R = [np.asarray(reference[n], dtype=np.float64)[:3, :3] for n in names]
    est_c = np.stack([camera_center(np.asarray(estimate[n], dtype=np.float64)) for n in names])
    ref_c = np.stack([camera_center(np.asarray(reference[n], dtype=np.float64)) for n in names])
    s, R, t = similarity(est_c, ref_c)
    aligned = (s * (R @ est_c.T)).T + t
    # a camera rotation maps world to camera: R_est = R_ref R (est world -> ref world by R)
    rot = [rotation_angle_deg((Re @ R.T) @ Rr.T) for Re, Rr in zip(est_R, ref_R, strict=True)]
    u, _, vt = np.linalg.svd(sum(Rr.T @ Re for Re, Rr in zip(est_R, ref_R, strict=True)))
    R_o = u @ np.diag([1.0, 1.0, np.linalg.det(u @ vt)]) @ vt
    rot_o = [rotation_angle_deg((Re @ R_o.T) @ Rr.T) for Re, Rr in zip(est_R, ref_R, strict=True)]
    n = len(names)
    rel = [
        rotation_angle_deg((est_R[i] @ est_R[j].T) @ (ref_R[i] @ ref_R[j].T).T)
        for i in range(n)
        for j in range(i + 1, n)
    ]
    centre_err = np.linalg.norm(aligned - ref_c, axis=1)
    extent = float(np.linalg.norm(ref_c - ref_c.mean(0), axis=1).mean())
    return PoseErrors(
        compared=n,
        rotation_error_deg_mean=float(np.mean(rot)),
        rotation_error_deg_max=float(np.max(rot)),
        orientation_aligned_rotation_error_deg_mean=float(np.mean(rot_o)),
        orientation_aligned_rotation_error_deg_max=float(np.max(rot_o)),
        relative_rotation_error_deg_mean=float(np.mean(rel)),
        relative_rotation_error_deg_max=float(np.max(rel)),
        center_error_mean=float(centre_err.mean()),
        center_error_relative=float(centre_err.mean() / extent) if extent > 0 else float("nan"),
    )


__all__ = ["PoseErrors", "camera_center", "compare_poses", "rotation_angle_deg", "similarity"]
