"""The prepared scene: the contract between ``rtsplat prepare`` and the trainer / renderer / metrics.

On disk::

    prepared/
      scene.json          this module's PreparedScene (format below)
      images/<name>.png   downsampled sRGB images (8- or 16-bit)
      masks/<name>.png    transparent-surface masks (white = see-through), same size; only when
                          has_transparency is true (masks exist and at least one pixel is white)
      points.ply          SfM points with colours (initialisation), may hold zero points
      transparent_surface.npz   optional, scenes with masks: points on the camera-facing surface of
                          the masks' visual hull and their outward normals (xyz, normal [N,3]);
                          the trainer starts clear surfels there (the see-through surface)

``scene.json``::

    {
      "format": 1,
      "cameras": [{"name": "IMG_0001", "image": "IMG_0001.JPG", "split": "train" | "test",
                   "width": W, "height": H, "K": 3x3, "world_to_camera": 4x4}, ...],
      "roi": {"center": [x, y, z], "radius": r, "source": "config" | "masks" | "estimated"},
      "roi_warning": "",  # why the masks' region of interest was not used, in words ("" when it was, when
                          # none was asked for, and in scenes written before it; rtsplat.prepare.checked_mask_roi)
      "downsample": 4,
      "resolution": 800 | null,   # prepare.resolution (longest side in pixels) when it chose the factor
      "source": "/path/to/dataset/scene",
      "has_transparency": true,
      "versions": {"rtsplat": "0.1.0", ...},
      "inputs": {"images": fp, "sfm": fp, "masks": fp | null},  # content fingerprints of what it was made
                                            # from (rtsplat.io.manifest); {} in scenes written before them
      "exposure": {"IMG_0001": [r, g, b] | null, ...},  # each photo's log gain against the SfM points' colours
                                            # (median over its observations; {} in scenes written before it)
      "exposure_points": {"IMG_0001": 412, ...},  # the observations off the see-through surface it used
      "exposure_error": {"IMG_0001": 0.004 | null, ...}  # the gain's standard error ({} in older scenes)
    }

Cameras follow :mod:`rtsplat.camera` (OpenCV axes, world-to-camera, pixel corner at (0, 0)), sorted
by name; the test split is every ``test_every``-th camera of that order starting with the first.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np

from rtsplat.errors import PipelineError

FORMAT_VERSION = 1
SCENE_FILE = "scene.json"
IMAGES_DIR = "images"
MASKS_DIR = "masks"
POINTS_FILE = "points.ply"
# scenes with transparent masks: points on the masks' visual hull that face the cameras, with outward
# normals (npz: xyz [N,3], normal [N,3]); where the see-through surface is
TRANSPARENT_SURFACE_FILE = "transparent_surface.npz"
GT_LAYERS_DIR = "gt_layers"  # synthetic scenes only: <name>/<stem>.png for name in reflection, transmission
# synthetic scenes only, in GT_LAYERS_DIR: what the true reflection of the glass shows (rtsplat.synth.reach)
REFLECTION_REACH_FILE = "reflection_reach.json"


@dataclass
class CameraRecord:
    name: str
    split: Literal["train", "test"]
    width: int
    height: int
    K: list[list[float]]
    world_to_camera: list[list[float]]
    image: str = ""  # the source image file name in the dataset

    @property
    def K_array(self) -> np.ndarray:
        return np.asarray(self.K, dtype=np.float64)

    @property
    def w2c_array(self) -> np.ndarray:
        return np.asarray(self.world_to_camera, dtype=np.float64)

    def to_camera(self, dtype=None, device=None):
        """This camera as :class:`rtsplat.camera.Camera` (torch tensors)."""
        import torch

        from rtsplat.camera import Camera

        dtype = dtype or torch.float32
        return Camera(
            torch.tensor(self.K, dtype=dtype, device=device),
            torch.tensor(self.world_to_camera, dtype=dtype, device=device),
            int(self.width),
            int(self.height),
        )


@dataclass
class Roi:
    center: list[float]
    radius: float
    source: Literal["config", "masks", "estimated"]


@dataclass
class PreparedScene:
    cameras: list[CameraRecord]
    roi: Roi
    downsample: int = 1
    resolution: int | None = None  # the longest side asked for (prepare.resolution) when it chose the factor
    source: str = ""
    has_transparency: bool = False
    versions: dict[str, str] = field(default_factory=dict)
    inputs: dict[str, str | None] = field(default_factory=dict)  # content fingerprints: images, sfm, masks
    # per view: its photo's log gain per channel against the SfM points it observed (prepare); None where too
    # few observations; {} in scenes written before it
    exposure: dict[str, list[float] | None] = field(default_factory=dict)
    # per view: how many observations outside the see-through surface measured its gain, and the gain's standard
    # error (None where there is no gain; rtsplat.model.appearance.GainEstimate); {} in scenes written before them
    exposure_points: dict[str, int] = field(default_factory=dict)
    exposure_error: dict[str, float | None] = field(default_factory=dict)
    # the views whose masks were marked when the others' were propagated from them (masks.source: propagate);
    # [] when every mask was given, and in scenes written before it
    marked_views: list[str] = field(default_factory=list)
    # why prepare did not use the masks' region of interest (rtsplat.prepare.checked_mask_roi; roi.source says which
    # one it used instead), in words; "" when it did, when none was asked for, and in scenes written before it
    roi_warning: str = ""
    format: int = FORMAT_VERSION
    root: Path | None = field(default=None, compare=False, repr=False)

    # -- access ------------------------------------------------------------------------------
    @property
    def train_cameras(self) -> list[CameraRecord]:
        return [c for c in self.cameras if c.split == "train"]

    @property
    def test_cameras(self) -> list[CameraRecord]:
        return [c for c in self.cameras if c.split == "test"]

    def _root(self) -> Path:
        if self.root is None:
            raise ValueError("this PreparedScene has no directory (load() or save() it first)")
        return self.root

    def image_path(self, name: str) -> Path:
        return self._root() / IMAGES_DIR / f"{name}.png"

    def mask_path(self, name: str) -> Path:
        return self._root() / MASKS_DIR / f"{name}.png"

    @property
    def points_path(self) -> Path:
        return self._root() / POINTS_FILE

    def load_image(self, name: str) -> np.ndarray:
        from rtsplat.io.images import read_image

        return read_image(self.image_path(name))

    def load_mask(self, name: str) -> np.ndarray | None:
        """The camera's mask (bool [H, W]), or None when the scene has no transparency."""
        if not self.has_transparency:
            return None
        from rtsplat.io.images import read_mask

        return read_mask(self.mask_path(name))

    def load_points(self) -> tuple[np.ndarray, np.ndarray]:
        from rtsplat.io.ply import read_points_ply

        return read_points_ply(self.points_path)

    def load_transparent_surface(self) -> tuple[np.ndarray, np.ndarray] | None:
        """Points and outward normals on the transparent masks' visual hull, or None (no such file)."""
        path = self._root() / TRANSPARENT_SURFACE_FILE
        if not path.is_file():
            return None
        with np.load(path) as data:
            xyz, normal = np.asarray(data["xyz"], np.float64), np.asarray(data["normal"], np.float64)
        if xyz.ndim != 2 or xyz.shape[1:] != (3,) or normal.shape != xyz.shape or not np.isfinite(xyz).all():
            raise PipelineError(f"xyz and normal must be finite [N,3] arrays, got {xyz.shape} and {normal.shape}",
                                path=path, fix="rerun `rtsplat prepare` for this scene")
        return xyz, normal

    # -- identity ----------------------------------------------------------------------------
    def data_record(self) -> dict[str, Any]:
        """What a training run records of the prepared scene it trains on (in its checkpoints and
        ``model.pt``): ``path`` (for messages), ``fingerprint`` (:func:`rtsplat.io.manifest.folder_fingerprint`
        of the whole prepared folder: a resume refuses another one) and ``inputs`` (the photos, SfM model and
        masks it was prepared from: render refuses a scene of other photos or another SfM model)."""
        from rtsplat.io.manifest import folder_fingerprint

        root = self._root()
        return {"path": str(root.resolve()), "fingerprint": folder_fingerprint(root), "inputs": dict(self.inputs)}

    def check_run_belongs(self, recorded: dict[str, Any] | None, run: str | Path) -> None:
        """Refuse to render the run at ``run`` on this scene when the scene it was trained on
        (``recorded``: its :meth:`data_record`) was prepared from other photos or another SfM model (so
        another scene, or another world frame). A run or scene without the record passes."""
        theirs = (recorded or {}).get("inputs") or {}
        ours = self.inputs or {}
        differs = [key for key in ("images", "sfm") if theirs.get(key) and ours.get(key) and theirs[key] != ours[key]]
        if not differs:
            return
        what = {"images": "photos", "sfm": "SfM model"}
        detail = ", ".join(f"{what[k]} {theirs[k]} vs {ours[k]}" for k in differs)
        raise PipelineError(
            f"the run {run} was trained on the prepared scene {recorded.get('path', '?')}, which was made from "
            f"other {' and '.join(what[k] for k in differs)} than this one, {self._root()} ({detail})",
            path=self._root(),
            fix=f"pass --data {recorded.get('path', 'the prepared scene the run was trained on')}, or train a run "
            "on this prepared scene",
        )

    # -- (de)serialisation -------------------------------------------------------------------
    def to_dict(self) -> dict[str, Any]:
        data = asdict(self)
        data.pop("root")
        return data

    @classmethod
    def from_dict(cls, data: dict[str, Any], where: str = SCENE_FILE) -> PreparedScene:
        try:
            cams = [CameraRecord(**c) for c in data["cameras"]]
            roi = Roi(**data["roi"])
            keys = ("downsample", "resolution", "source", "has_transparency", "versions", "inputs", "exposure",
                    "exposure_points", "exposure_error", "marked_views", "roi_warning", "format")
            rest = {k: data[k] for k in keys if k in data}
        except (KeyError, TypeError) as exc:
            raise PipelineError(
                f"malformed prepared scene ({exc})", path=where, fix="re-run 'rtsplat prepare' for this scene"
            ) from exc
        scene = cls(cameras=cams, roi=roi, **rest)
        scene.validate(check_files=False, where=where)
        return scene

    def save(self, directory: str | Path) -> Path:
        """Write ``scene.json`` into ``directory`` (images/masks/points are written by the caller)."""
        self.validate(check_files=False)
        directory = Path(directory)
        directory.mkdir(parents=True, exist_ok=True)
        path = directory / SCENE_FILE
        path.write_text(json.dumps(self.to_dict(), indent=1) + "\n")
        self.root = directory
        return path

    @classmethod
    def load(cls, directory: str | Path, check_files: bool = True) -> PreparedScene:
        directory = Path(directory)
        path = directory / SCENE_FILE
        if not path.is_file():
            raise PipelineError(
                "no prepared scene here (scene.json missing)",
                path=directory,
                fix="run 'rtsplat prepare' for this scene first",
            )
        try:
            data = json.loads(path.read_text())
        except json.JSONDecodeError as exc:
            raise PipelineError(
                f"scene.json is not valid JSON ({exc})", path=path, fix="re-run 'rtsplat prepare'"
            ) from exc
        scene = cls.from_dict(data, where=str(path))
        scene.root = directory
        if check_files:
            scene.validate(check_files=True, where=str(path))
        return scene

    # -- validation --------------------------------------------------------------------------
    def validate(self, check_files: bool = False, where: str | Path = SCENE_FILE) -> None:
        """Raise :class:`PipelineError` when the scene breaks the contract (see the module docstring)."""

        def bad(problem: str) -> PipelineError:
            return PipelineError(problem, path=where, fix="re-run 'rtsplat prepare' for this scene")

        if self.format != FORMAT_VERSION:
            raise bad(f"format {self.format} is not supported (expected {FORMAT_VERSION})")
        if not self.cameras:
            raise bad("no cameras")
        names = [c.name for c in self.cameras]
        if len(set(names)) != len(names):
            raise bad("camera names are not unique")
        if not any(c.split == "train" for c in self.cameras):
            raise bad("no training cameras")
        for c in self.cameras:
            if c.split not in ("train", "test"):
                raise bad(f"camera {c.name}: split must be 'train' or 'test', got {c.split!r}")
            if int(c.width) <= 0 or int(c.height) <= 0:
                raise bad(f"camera {c.name}: size {c.width}x{c.height} is not positive")
            K, w2c = np.asarray(c.K, dtype=float), np.asarray(c.world_to_camera, dtype=float)
            if K.shape != (3, 3) or w2c.shape != (4, 4):
                raise bad(f"camera {c.name}: K must be 3x3 and world_to_camera 4x4")
            if not (np.all(np.isfinite(K)) and np.all(np.isfinite(w2c))):
                raise bad(f"camera {c.name}: non-finite intrinsics or pose")
            if K[0, 0] <= 0 or K[1, 1] <= 0 or not np.allclose(K[2], [0, 0, 1]):
                raise bad(f"camera {c.name}: K is not a pinhole intrinsic matrix")
            R = w2c[:3, :3]
            if (
                not np.allclose(R @ R.T, np.eye(3), atol=1e-4)
                or abs(np.linalg.det(R) - 1) > 1e-4
                or not np.allclose(w2c[3], [0, 0, 0, 1])
            ):
                raise bad(f"camera {c.name}: world_to_camera is not a rigid transform")
        try:
            center = np.asarray(self.roi.center, dtype=float)
            radius = float(self.roi.radius)
        except (TypeError, ValueError):
            raise bad(f"roi: center {self.roi.center!r} and radius {self.roi.radius!r} must be numbers") from None
        if center.shape != (3,) or not radius > 0:
            raise bad("roi must have a 3D center and a positive radius")
        if not (np.all(np.isfinite(center)) and np.isfinite(radius)):
            raise bad(f"roi.center {self.roi.center} and roi.radius {self.roi.radius} must be finite")
        if self.roi.source not in ("config", "masks", "estimated"):
            raise bad(f"roi.source must be 'config', 'masks' or 'estimated', got {self.roi.source!r}")
        if not isinstance(self.roi_warning, str):
            raise bad(f"roi_warning must be a string, got {self.roi_warning!r}")
        unknown = sorted(set(self.marked_views) - set(names))
        if unknown:
            raise bad(f"marked_views names no camera: {', '.join(unknown)}")
        for name, gain in (self.exposure or {}).items():
            if gain is not None and not (len(gain) == 3 and np.all(np.isfinite(np.asarray(gain, dtype=float)))):
                raise bad(f"exposure of view {name!r} must be 3 finite numbers or null, got {gain!r}")
        for name, points in (self.exposure_points or {}).items():
            if isinstance(points, bool) or not isinstance(points, int) or points < 0:
                raise bad(f"exposure_points of view {name!r} must be a count (an integer >= 0), got {points!r}")
        for name, error in (self.exposure_error or {}).items():
            if error is not None and not (isinstance(error, (int, float)) and np.isfinite(error) and error >= 0):
                raise bad(f"exposure_error of view {name!r} must be a finite number >= 0 or null, got {error!r}")
        if check_files:
            self._check_files(bad)

    def _check_files(self, bad) -> None:
        from rtsplat.io.images import read_header

        for c in self.cameras:
            paths = [self.image_path(c.name)] + ([self.mask_path(c.name)] if self.has_transparency else [])
            for p in paths:
                if not p.is_file():
                    raise bad(f"missing file {p}")
                h = read_header(p)
                if (h.width, h.height) != (int(c.width), int(c.height)):
                    raise bad(f"{p} is {h.width}x{h.height}, camera {c.name} says {c.width}x{c.height}")
        if not self.points_path.is_file():
            raise bad(f"missing file {self.points_path}")
