"""The prepared-scene contract: round trips and validation."""

from __future__ import annotations

import json

import numpy as np
import pytest

from rtsplat.errors import PipelineError
from rtsplat.io.images import write_mask, write_png
from rtsplat.io.ply import write_points_ply
from rtsplat.scene import CameraRecord, PreparedScene, Roi


def _scene(n=3, transparency=True) -> PreparedScene:
    cams = []
    for i in range(n):
        a = 0.3 * i
        R = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1.0]])
        w2c = np.eye(4)
        w2c[:3, :3] = R
        w2c[:3, 3] = [0.1 * i, -0.2, 3.0]
        K = [[50.0, 0, 16.0], [0, 52.0, 12.0], [0, 0, 1]]
        split = "test" if i == 0 else "train"
        cams.append(CameraRecord(f"img{i}", split, 32, 24, K, w2c.tolist(), f"img{i}.jpg"))
    return PreparedScene(
        cams,
        Roi([0.0, 0.5, 1.0], 2.0, "estimated"),
        downsample=4,
        source="/data/x",
        has_transparency=transparency,
        versions={"rtsplat": "0.1.0"},
    )


def _write_files(scene: PreparedScene, d):
    (d / "images").mkdir(parents=True)
    (d / "masks").mkdir()
    for c in scene.cameras:
        write_png(d / "images" / f"{c.name}.png", np.full((c.height, c.width, 3), 0.5, np.float32))
        write_mask(d / "masks" / f"{c.name}.png", np.eye(c.height, c.width, dtype=bool))
    write_points_ply(d / "points.ply", np.random.default_rng(0).normal(size=(20, 3)))


def test_round_trip(tmp_path):
    scene = _scene()
    _write_files(scene, tmp_path)
    scene.save(tmp_path)
    loaded = PreparedScene.load(tmp_path)
    assert loaded == scene
    assert loaded.to_dict() == json.loads((tmp_path / "scene.json").read_text())
    assert [c.name for c in loaded.test_cameras] == ["img0"]
    assert loaded.load_mask("img1").shape == (24, 32)
    xyz, _ = loaded.load_points()
    assert xyz.shape == (20, 3)
    cam = loaded.cameras[1].to_camera()
    assert np.allclose(cam.world_to_camera.numpy(), loaded.cameras[1].w2c_array, atol=1e-6)


def test_no_transparency_has_no_masks(tmp_path):
    scene = _scene(transparency=False)
    _write_files(scene, tmp_path)
    scene.save(tmp_path)
    assert PreparedScene.load(tmp_path).load_mask("img0") is None


@pytest.mark.parametrize(
    "mutate, message",
    [
        (lambda d: d["cameras"][1].update(split="val"), "split must be 'train' or 'test'"),
        (lambda d: d["cameras"][1]["world_to_camera"][0].__setitem__(0, 2.0), "not a rigid transform"),
        (lambda d: d["cameras"][2].update(name="img1"), "not unique"),
        (lambda d: d["roi"].update(radius=0.0), "positive radius"),
        (lambda d: d["roi"].update(radius=float("nan")), "positive radius"),
        (lambda d: d["roi"].update(radius=float("inf")), "roi.radius inf must be finite"),
        (lambda d: d["roi"]["center"].__setitem__(1, float("nan")), r"roi.center \[0.0, nan, 1.0\] .* finite"),
        (lambda d: d["roi"].update(center=["a", 0, 0]), "must be numbers"),
        (lambda d: d.update(format=99), "format 99"),
        (lambda d: d["cameras"][0].pop("K"), "malformed"),
        (lambda d: d["cameras"][0].update(width=31), "is 32x24, camera img0 says 31x24"),
        (lambda d: d.update(exposure={"img0": [0.1, float("nan"), 0.0]}), "exposure of view 'img0' must be 3 finite"),
        (lambda d: d.update(exposure={"img1": [0.1]}), "exposure of view 'img1' must be 3 finite"),
        (lambda d: d.update(exposure_points={"img1": -3}), "exposure_points of view 'img1' must be a count"),
        (lambda d: d.update(exposure_points={"img1": 2.5}), "exposure_points of view 'img1' must be a count"),
        (lambda d: d.update(exposure_error={"img0": -0.1}), "exposure_error of view 'img0' must be a finite"),
    ],
)
def test_validation_names_the_problem(tmp_path, mutate, message):
    scene = _scene()
    _write_files(scene, tmp_path)
    scene.save(tmp_path)
    data = json.loads((tmp_path / "scene.json").read_text())
    mutate(data)
    (tmp_path / "scene.json").write_text(json.dumps(data))
    with pytest.raises(PipelineError, match=message) as err:
        PreparedScene.load(tmp_path)
    assert "scene.json" in str(err.value) and "rtsplat prepare" in str(err.value)


def test_missing_files_are_reported(tmp_path):
    scene = _scene()
    _write_files(scene, tmp_path)
    scene.save(tmp_path)
    (tmp_path / "masks" / "img2.png").unlink()
    with pytest.raises(PipelineError, match="missing file .*img2.png"):
        PreparedScene.load(tmp_path)
    assert PreparedScene.load(tmp_path, check_files=False).cameras[2].name == "img2"
    with pytest.raises(PipelineError, match="scene.json missing"):
        PreparedScene.load(tmp_path / "nowhere")
