"""COLMAP sparse models as plain numpy data: read with pycolmap, written (text and binary) for
ground-truth cameras (``rtsplat synth``) and test fixtures.

Poses are COLMAP's ``cam_from_world``, which is exactly rtsplat's ``world_to_camera`` (OpenCV axes,
pixel corner at (0, 0)); see :mod:`rtsplat.camera`.
"""

from __future__ import annotations

import struct
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
    # per image name, with load_model(observations=True): its observations of 3D points, as (pixel
    # coordinates [n, 2] with the pixel corner at (0, 0), the observed point's colour [n, 3] uint8)
    observations: dict[str, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)

    def view(self, name: str) -> ColmapView:
        for v in self.views:
            if v.name == name:
                return v
        raise KeyError(name)


def is_model_dir(path: str | Path) -> bool:
    path = Path(path)
    return all((path / f"{n}.bin").is_file() or (path / f"{n}.txt").is_file() for n in MODEL_FILES)


def dataset_model_dir(scene_dir: str | Path) -> Path | None:
    """The COLMAP model a dataset scene ships: ``sparse/0`` (COLMAP's own layout), else model files
    directly in ``sparse/`` (how some datasets and exports store the one model); None when it has neither."""
    sparse = Path(scene_dir) / "sparse"
    for candidate in (sparse / "0", sparse):
        if is_model_dir(candidate):
            return candidate
    return None


def load_model(path: str | Path, observations: bool = False) -> ColmapModel:
    """Read a COLMAP model directory (binary or text) into :class:`ColmapModel`; with ``observations``
    also every registered image's observations of 3D points (:attr:`ColmapModel.observations`)."""
    import pycolmap

    path = Path(path)
    if not is_model_dir(path):
        raise PipelineError(
            "not a COLMAP model (cameras, images and points3D .bin/.txt expected)",
            path=path,
            fix="point at the folder that holds cameras.bin, images.bin and points3D.bin (usually sparse/0)",
        )
    if all((path / f"{n}.bin").is_file() for n in MODEL_FILES):
        check_binary_model(path)  # before pycolmap: it trusts the counts a truncated file declares
    try:
        rec = pycolmap.Reconstruction(str(path))
    except Exception as exc:  # pycolmap raises plain RuntimeError/ValueError on corrupt files
        raise PipelineError(
            f"cannot read the COLMAP model ({exc})", path=path, fix="re-run SfM or restore the model files"
        ) from exc
    for camera_id, cam in rec.cameras.items():
        _check_camera(path, camera_id, int(cam.width), int(cam.height), np.asarray(cam.params, dtype=np.float64),
                      list(cam.focal_length_idxs()), list(cam.principal_point_idxs()))
    views = []
    for image_id in sorted(rec.reg_image_ids()):
        image = rec.image(image_id)
        if image.camera_id not in rec.cameras:
            raise PipelineError(f"image {image.name!r} refers to camera {image.camera_id}, which is not in the model",
                                path=path / "images.bin", fix=_REDO)
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
    for view in views:
        if not np.isfinite(view.world_to_camera).all():
            raise PipelineError(f"the pose of image {view.name!r} is not finite", path=path, fix=_REDO)
    if not np.isfinite(xyz).all():
        bad = int((~np.isfinite(xyz).all(1)).sum())
        raise PipelineError(f"{bad} 3D point(s) have a non-finite position", path=path, fix=_REDO)
    return ColmapModel(sorted(views, key=lambda v: v.name), xyz, rgb, err,
                       _observations(rec) if observations else {})


def _observations(rec) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    colours = {point_id: point.color for point_id, point in rec.points3D.items()}
    out = {}
    for image_id in rec.reg_image_ids():
        image = rec.image(image_id)
        seen = [(p.xy, colours[p.point3D_id]) for p in image.get_observation_points2D()
                if p.point3D_id in colours]
        xy = np.array([s[0] for s in seen], dtype=np.float64).reshape(-1, 2)
        rgb = np.array([s[1] for s in seen], dtype=np.uint8).reshape(-1, 3)
        out[image.name] = (xy, rgb)
    return out


_REDO = "re-run 'rtsplat sfm' (or COLMAP) or restore the model files"


def _check_camera(path: Path, camera_id: int, width: int, height: int, params: np.ndarray, focal_idx: list[int],
                  principal_idx: list[int]) -> None:
    """A camera with a positive size, finite parameters, positive focal lengths and its principal point
    inside the image; else a :class:`PipelineError` naming it."""
    where = f"camera {camera_id}"
    if width <= 0 or height <= 0:
        raise PipelineError(f"{where} has the size {width}x{height}", path=path, fix=_REDO)
    if not np.isfinite(params).all():
        raise PipelineError(f"{where} has non-finite parameters {params.tolist()}", path=path, fix=_REDO)
    focal = params[focal_idx]
    if (focal <= 0).any():
        raise PipelineError(f"{where} has a focal length <= 0 ({focal.tolist()} px)", path=path, fix=_REDO)
    if len(principal_idx) == 2:
        cx, cy = params[principal_idx]
        if not (0 <= cx <= width and 0 <= cy <= height):
            raise PipelineError(f"{where}'s principal point ({cx:g}, {cy:g}) lies outside its {width}x{height} "
                                "image", path=path, fix=_REDO)


class _Reader:
    """Sequential little-endian reads of one binary model file, with a clear error at its end."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.data = path.read_bytes()
        self.pos = 0

    def truncated(self, what: str) -> PipelineError:
        return PipelineError(f"the file is truncated or corrupt ({len(self.data)} bytes; it ends inside {what})",
                             path=self.path, fix=_REDO)

    def read(self, fmt: str, what: str) -> tuple:
        size = struct.calcsize(fmt)
        if self.pos + size > len(self.data):
            raise self.truncated(what)
        values = struct.unpack_from(fmt, self.data, self.pos)
        self.pos += size
        return values

    def skip(self, size: int, what: str) -> None:
        if self.pos + size > len(self.data):
            raise self.truncated(what)
        self.pos += size

    def count(self, record_size: int, what: str) -> int:
        """The leading record count, checked against the file size (records take >= ``record_size``)."""
        if not self.data:
            raise PipelineError("the file is empty (0 bytes)", path=self.path, fix=_REDO)
        (n,) = self.read("<Q", "its record count")
        if n * record_size > len(self.data) - self.pos:
            raise PipelineError(f"the file declares {n} {what} but holds only {len(self.data)} bytes "
                                "(truncated or corrupt)", path=self.path, fix=_REDO)
        return n


def _param_count(model_id: int, path: Path, camera_id: int) -> int:
    import pycolmap

    try:
        return len(pycolmap.Camera.create_from_model_id(1, model_id, 1.0, 1, 1).params)
    except ValueError:
        raise PipelineError(f"camera {camera_id} has the unknown camera model id {model_id}", path=path,
                            fix=_REDO) from None


def check_binary_model(path: str | Path) -> None:
    """Walk ``cameras.bin``, ``images.bin`` and ``points3D.bin`` of ``path``: a :class:`PipelineError`
    naming the file when one is empty, truncated or declares more records than it holds, or an image
    refers to a camera the model lacks. Cheap next to reading the model (2D points and tracks are
    skipped, not decoded)."""
    path = Path(path)
    cams = _Reader(path / "cameras.bin")
    camera_ids = set()
    for _ in range(cams.count(24, "cameras")):
        camera_id, model_id, _w, _h = cams.read("<iiQQ", "a camera")
        cams.skip(8 * _param_count(model_id, cams.path, camera_id), f"the parameters of camera {camera_id}")
        camera_ids.add(camera_id)
    images = _Reader(path / "images.bin")
    for _ in range(images.count(73, "images")):
        image_id, *_pose, camera_id = images.read("<i7di", "an image")
        end = images.data.find(b"\x00", images.pos)
        if end < 0:
            raise images.truncated(f"the name of image {image_id}")
        name = images.data[images.pos:end].decode("utf-8", "replace")
        images.pos = end + 1
        if camera_id not in camera_ids:
            raise PipelineError(f"image {name!r} refers to camera {camera_id}, which cameras.bin does not hold",
                                path=images.path, fix=_REDO)
        (n2d,) = images.read("<Q", f"the 2D point count of image {name!r}")
        images.skip(24 * n2d, f"the 2D points of image {name!r}")
    points = _Reader(path / "points3D.bin")
    for _ in range(points.count(51, "3D points")):
        point_id, *_xyz_rgb_err, track = points.read("<Q3d3BdQ", "a 3D point")
        points.skip(8 * track, f"the track of 3D point {point_id}")


def write_model(
    path: str | Path,
    views: list[tuple[str, np.ndarray, np.ndarray, int, int]],
    xyz: np.ndarray | None = None,
    rgb: np.ndarray | None = None,
) -> None:
    """Write a COLMAP model of PINHOLE cameras: ``views`` = [(name, K, world_to_camera, w, h)].

    Points get empty tracks (grey when ``rgb`` is None); this is meant for known-pose datasets and
    test fixtures. See :func:`write_sparse_model`.
    """
    images = [ColmapImage(name, np.asarray(K, np.float64), np.asarray(w2c, np.float64), int(w), int(h))
              for name, K, w2c, w, h in views]
    xyz = np.zeros((0, 3)) if xyz is None else np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
    colors = np.full((len(xyz), 3), 128, np.uint8) if rgb is None else np.asarray(rgb, np.uint8).reshape(-1, 3)
    write_sparse_model(path, images, ColmapPoints(xyz, colors, [[] for _ in range(len(xyz))]))


PINHOLE_MODEL_ID = 1


@dataclass
class ColmapImage:
    name: str
    K: np.ndarray  # 3x3
    world_to_camera: np.ndarray  # 4x4
    width: int
    height: int
    points2d: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))  # [M, 2] pixels
    point3d_ids: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))  # [M]


@dataclass
class ColmapPoints:
    xyz: np.ndarray  # [N, 3]
    rgb: np.ndarray  # [N, 3] uint8
    tracks: list[list[tuple[int, int]]]  # per point: (image_id, point2D index)


def rotation_to_quaternion(R: np.ndarray) -> np.ndarray:
    """3x3 rotation -> unit quaternion (w, x, y, z) with w >= 0."""
    R = np.asarray(R, dtype=np.float64)
    m = (
        np.array(
            [
                [R[0, 0] - R[1, 1] - R[2, 2], 0, 0, 0],
                [R[0, 1] + R[1, 0], R[1, 1] - R[0, 0] - R[2, 2], 0, 0],
                [R[0, 2] + R[2, 0], R[1, 2] + R[2, 1], R[2, 2] - R[0, 0] - R[1, 1], 0],
                [R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1], R[0, 0] + R[1, 1] + R[2, 2]],
            ]
        )
        / 3.0
    )
    # The eigenvector of the largest eigenvalue of this symmetric matrix is (x, y, z, w).
    vals, vecs = np.linalg.eigh(m)
    x, y, z, w = vecs[:, np.argmax(vals)]
    q = np.array([w, x, y, z])
    return q if q[0] >= 0 else -q


def quaternion_to_rotation(q: np.ndarray) -> np.ndarray:
    """Unit quaternion (w, x, y, z) -> 3x3 rotation."""
    w, x, y, z = np.asarray(q, dtype=np.float64) / np.linalg.norm(q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def _camera_groups(images: list[ColmapImage]) -> tuple[list[tuple], list[int]]:
    """Distinct intrinsics -> camera list [(width, height, fx, fy, cx, cy)] and per-image ids."""
    cams: list[tuple] = []
    ids: list[int] = []
    for im in images:
        key = (
            int(im.width),
            int(im.height),
            float(im.K[0, 0]),
            float(im.K[1, 1]),
            float(im.K[0, 2]),
            float(im.K[1, 2]),
        )
        if key not in cams:
            cams.append(key)
        ids.append(cams.index(key) + 1)
    return cams, ids


def write_sparse_model(path: str | Path, images: list[ColmapImage], points: ColmapPoints) -> None:
    """Write ``cameras``, ``images``, ``points3D`` as ``.txt`` and ``.bin`` into ``path``: PINHOLE cameras
    (images with equal intrinsics share one), ``cam_from_world`` poses as a unit quaternion (w, x, y, z)
    and a translation, the images' 2D points and the points' tracks, in the layout COLMAP, pycolmap
    and 3DGS-style loaders read."""
    path = Path(path)
    path.mkdir(parents=True, exist_ok=True)
    cams, cam_ids = _camera_groups(images)
    poses = []
    for im in images:
        w2c = np.asarray(im.world_to_camera, dtype=np.float64)
        poses.append((rotation_to_quaternion(w2c[:3, :3]), w2c[:3, 3]))

    # cameras
    with open(path / "cameras.txt", "w") as f:
        f.write("# Camera list with one line of data per camera:\n")
        f.write("#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]\n")
        f.write(f"# Number of cameras: {len(cams)}\n")
        for cid, (w, h, fx, fy, cx, cy) in enumerate(cams, start=1):
            f.write(f"{cid} PINHOLE {w} {h} {fx!r} {fy!r} {cx!r} {cy!r}\n")
    with open(path / "cameras.bin", "wb") as f:
        f.write(struct.pack("<Q", len(cams)))
        for cid, (w, h, fx, fy, cx, cy) in enumerate(cams, start=1):
            f.write(struct.pack("<iiQQdddd", cid, PINHOLE_MODEL_ID, w, h, fx, fy, cx, cy))

    # images
    with open(path / "images.txt", "w") as f:
        f.write("# Image list with two lines of data per image:\n")
        f.write("#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME\n")
        f.write("#   POINTS2D[] as (X, Y, POINT3D_ID)\n")
        f.write(f"# Number of images: {len(images)}\n")
        for iid, (im, (q, t), cid) in enumerate(zip(images, poses, cam_ids, strict=True), start=1):
            f.write(f"{iid} {' '.join(repr(float(v)) for v in (*q, *t))} {cid} {im.name}\n")
            f.write(
                " ".join(
                    f"{x!r} {y!r} {int(p)}" for (x, y), p in zip(im.points2d.tolist(), im.point3d_ids, strict=True)
                )
                + "\n"
            )
    with open(path / "images.bin", "wb") as f:
        f.write(struct.pack("<Q", len(images)))
        for iid, (im, (q, t), cid) in enumerate(zip(images, poses, cam_ids, strict=True), start=1):
            f.write(struct.pack("<i7di", iid, *q, *t, cid))
            f.write(im.name.encode("utf-8") + b"\x00")
            f.write(struct.pack("<Q", len(im.point3d_ids)))
            for (x, y), p in zip(im.points2d.tolist(), im.point3d_ids, strict=True):
                f.write(struct.pack("<ddq", x, y, int(p)))

    # points3D (ids start at 1)
    n = len(points.xyz)
    with open(path / "points3D.txt", "w") as f:
        f.write("# 3D point list with one line of data per point:\n")
        f.write("#   POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[] as (IMAGE_ID, POINT2D_IDX)\n")
        f.write(f"# Number of points: {n}\n")
        for pid in range(n):
            x, y, z = (float(v) for v in points.xyz[pid])
            r, g, b = (int(c) for c in points.rgb[pid])
            track = " ".join(f"{i} {j}" for i, j in points.tracks[pid])
            f.write(f"{pid + 1} {x!r} {y!r} {z!r} {r} {g} {b} 0.0 {track}\n")
    with open(path / "points3D.bin", "wb") as f:
        f.write(struct.pack("<Q", n))
        for pid in range(n):
            f.write(
                struct.pack(
                    "<Q3d3Bd", pid + 1, *(float(v) for v in points.xyz[pid]), *(int(c) for c in points.rgb[pid]), 0.0
                )
            )
            f.write(struct.pack("<Q", len(points.tracks[pid])))
            for i, j in points.tracks[pid]:
                f.write(struct.pack("<ii", i, j))
