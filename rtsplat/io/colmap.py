"""COLMAP sparse models as plain numpy data (read with pycolmap, written for test fixtures).

Poses are COLMAP's ``cam_from_world``, which is exactly rtsplat's ``world_to_camera`` (OpenCV axes,
pixel corner at (0, 0)); see :mod:`rtsplat.camera`.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from rtsplat.errors import PipelineError

MODEL_FILES = ("cameras", "images", "points3D")
# COLMAP camera models without distortion parameters
UNDISTORTED_MODELS = ("SIMPLE_PINHOLE", "PINHOLE")


@dataclass
class ColmapView:
    name: str
    width: int
    height: int
    model: str
    params: np.ndarray
    K: np.ndarray  # [3, 3]
    world_to_camera: np.ndarray  # [4, 4]

    @property
    def has_distortion(self) -> bool:
        return self.model not in UNDISTORTED_MODELS

    @property
    def center(self) -> np.ndarray:
        R, t = self.world_to_camera[:3, :3], self.world_to_camera[:3, 3]
        return -R.T @ t

    @property
    def forward(self) -> np.ndarray:
        """Viewing direction (camera +z) in world coordinates."""
        return self.world_to_camera[2, :3].copy()


@dataclass
class ColmapModel:
    views: list[ColmapView]
    xyz: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    rgb: np.ndarray = field(default_factory=lambda: np.zeros((0, 3), dtype=np.uint8))
    errors: np.ndarray = field(default_factory=lambda: np.zeros((0,)))

    def view(self, name: str) -> ColmapView:
        for v in self.views:
            if v.name == name:
                return v
        raise KeyError(name)


def is_model_dir(path: str | Path) -> bool:
    path = Path(path)
    return all((path / f"{n}.bin").is_file() or (path / f"{n}.txt").is_file() for n in MODEL_FILES)


def load_model(path: str | Path) -> ColmapModel:
    """Read a COLMAP model directory (binary or text) into :class:`ColmapModel`."""
    import pycolmap

    path = Path(path)
    if not is_model_dir(path):
        raise PipelineError(
            "not a COLMAP model (cameras, images and points3D .bin/.txt expected)",
            path=path,
            fix="point at the folder that holds cameras.bin, images.bin and points3D.bin (usually sparse/0)",
        )
    try:
        rec = pycolmap.Reconstruction(str(path))
    except Exception as exc:  # pycolmap raises plain RuntimeError/ValueError on corrupt files
        raise PipelineError(
            f"cannot read the COLMAP model ({exc})", path=path, fix="re-run SfM or restore the model files"
        ) from exc
    views = []
    for image_id in sorted(rec.reg_image_ids()):
        image = rec.image(image_id)
        cam = rec.camera(image.camera_id)
        w2c = np.eye(4)
        w2c[:3, :4] = np.asarray(image.cam_from_world().matrix(), dtype=np.float64)
        views.append(
            ColmapView(
                name=image.name,
                width=int(cam.width),
                height=int(cam.height),
                model=str(cam.model_name),
                params=np.asarray(cam.params, dtype=np.float64),
                K=np.asarray(cam.calibration_matrix(), dtype=np.float64),
                world_to_camera=w2c,
            )
        )
    pts = list(rec.points3D.values())
    xyz = np.array([p.xyz for p in pts], dtype=np.float64).reshape(-1, 3)
    rgb = np.array([p.color for p in pts], dtype=np.uint8).reshape(-1, 3)
    err = np.array([p.error for p in pts], dtype=np.float64)
    return ColmapModel(sorted(views, key=lambda v: v.name), xyz, rgb, err)


def write_model(
    path: str | Path,
    views: list[tuple[str, np.ndarray, np.ndarray, int, int]],
    xyz: np.ndarray | None = None,
    rgb: np.ndarray | None = None,
) -> None:
    """Write a binary COLMAP model of PINHOLE cameras: ``views`` = [(name, K, world_to_camera, w, h)].

    Points get empty tracks; this is meant for known-pose datasets and test fixtures.
    """
    import pycolmap

    rec = pycolmap.Reconstruction()
    for i, (name, K, w2c, w, h) in enumerate(views, start=1):
        cam = pycolmap.Camera.create_from_model_name(
            i, "PINHOLE", float(K[0, 0]), int(w), int(h)
        )
        cam.params = [float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2])]
        rec.add_camera_with_trivial_rig(cam)
        image = pycolmap.Image(name=name, camera_id=i, image_id=i)
        rec.add_image_with_trivial_frame(image, pycolmap.Rigid3d(np.asarray(w2c, dtype=np.float64)[:3, :4]))
    if xyz is not None:
        colors = np.full((len(xyz), 3), 128, np.uint8) if rgb is None else np.asarray(rgb, np.uint8)
        for p, c in zip(np.asarray(xyz, dtype=np.float64), colors, strict=True):
            rec.add_point3D(p, pycolmap.Track(), c)
    Path(path).mkdir(parents=True, exist_ok=True)
    rec.write_binary(str(path))
