"""Camera paths (geometry by hand) and ``rtsplat video`` on a trained toy run: the MP4 is decoded with the
same library (PyAV) and its frames are checked against the model's own renders."""

from __future__ import annotations

import json
import math
import shutil

import numpy as np
import pytest
import torch

from rtsplat.bench.toy_scene import train_quietly, write_scene
from rtsplat.camera import Camera, camera_from_fov
from rtsplat.camera_path import (
    camera_centers,
    camera_path,
    interpolated_path,
    mean_up,
    orbit_geometry,
    orbit_path,
    path_intrinsics,
    spiral_path,
)
from rtsplat.cli import main as cli
from rtsplat.errors import PipelineError
from rtsplat.io.images import read_image
from rtsplat.io.video import mp4_comment, read_mp4
from rtsplat.render import Edits, LoadedRun, decompose, load_run
from rtsplat.video import render_video

CODEC_TOLERANCE = 4 / 255  # mean |decoded - rendered| that H.264 at crf 18 in yuv420p stays under on these frames


def ring_cameras(center, distances, elevations, azimuths, up=(0.0, 0.0, 1.0)) -> torch.Tensor:
    """World-to-camera poses of cameras at the given distances, elevations and azimuths (radians) around
    ``center``, looking at it, with the world z axis up."""
    poses = []
    for d, e, a in zip(distances, elevations, azimuths, strict=True):
        eye = np.asarray(center) + d * np.array([math.cos(e) * math.cos(a), math.cos(e) * math.sin(a), math.sin(e)])
        poses.append(camera_from_fov(eye.tolist(), center, width=40, height=30, up=up,
                                     dtype=torch.float64).world_to_camera)
    return torch.stack(poses)


def looks_at(poses: torch.Tensor, center) -> bool:
    forward = poses[:, 2, :3]
    to_center = torch.as_tensor(center, dtype=torch.float64) - camera_centers(poses)
    return bool(torch.allclose(forward, to_center / to_center.norm(dim=1, keepdim=True), atol=1e-9))


def test_orbit_circles_the_centre_at_the_cameras_mean_distance_and_elevation():
    center = [0.5, -0.2, 0.3]
    distances, elevations = [2.0, 3.0, 2.5, 3.5], [0.1, 0.3, 0.2, 0.4]
    w2c = ring_cameras(center, distances, elevations, [0.3, 0.8, 1.1, 2.0])
    assert torch.allclose(mean_up(w2c) @ torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64),
                          torch.tensor(1.0, dtype=torch.float64), atol=0.1)
    poses = orbit_path(w2c, center, 24)
    assert poses.shape == (24, 4, 4) and looks_at(poses, center)
    geometry = orbit_geometry(w2c, center)
    assert geometry["distance"] == pytest.approx(np.mean(distances))
    offsets = camera_centers(poses) - torch.tensor(center, dtype=torch.float64)
    up = mean_up(w2c)
    np.testing.assert_allclose(offsets.norm(dim=1).numpy(), np.mean(distances), rtol=1e-9)
    np.testing.assert_allclose(torch.asin(offsets @ up / offsets.norm(dim=1)).numpy(), geometry["elevation"],
                               atol=1e-9)
    # a full turn in equal steps around the up axis, starting at the first camera's azimuth
    flat = offsets - (offsets @ up)[:, None] * up
    cos_steps = (flat[1:] * flat[:-1]).sum(1) / (flat[1:].norm(dim=1) * flat[:-1].norm(dim=1))
    np.testing.assert_allclose(cos_steps.numpy(), math.cos(2 * math.pi / 24), atol=1e-9)
    first = camera_centers(w2c[:1])[0] - torch.tensor(center, dtype=torch.float64)
    first_flat = first - (first @ up) * up
    assert float(first_flat @ flat[0]) / float(first_flat.norm() * flat[0].norm()) == pytest.approx(1.0, abs=1e-9)


def test_interpolation_passes_through_the_training_poses_in_order_and_moves_smoothly():
    w2c = ring_cameras([0.0, 0.0, 0.0], [3.0, 3.2, 2.9, 3.1, 3.0], [0.2, 0.25, 0.3, 0.2, 0.1],
                       [0.0, 0.3, 0.5, 0.9, 1.2])
    m = 6
    poses = interpolated_path(w2c, m * (len(w2c) - 1) + 1)
    np.testing.assert_allclose(poses[::m].numpy(), w2c.numpy(), atol=1e-9)
    rotations = poses[:, :3, :3]
    eye = torch.eye(3, dtype=torch.float64).expand_as(rotations)
    assert torch.allclose(rotations @ rotations.transpose(1, 2), eye, atol=1e-9)
    assert torch.allclose(torch.linalg.det(rotations), torch.ones(len(poses), dtype=torch.float64), atol=1e-9)
    steps = (camera_centers(poses)[1:] - camera_centers(poses)[:-1]).norm(dim=1)
    gaps = (camera_centers(w2c)[1:] - camera_centers(w2c)[:-1]).norm(dim=1)
    assert float(steps.max()) < 0.5 * float(gaps.min())  # no jumps: every step a fraction of a segment
    # an interpolated rotation lies between its two poses: its angle to each is at most their angle apart
    def angle(a, b):
        return math.acos(max(-1.0, min(1.0, (float(torch.trace(a @ b.T)) - 1) / 2)))
    for k in range(1, m):
        apart = angle(w2c[0, :3, :3], w2c[1, :3, :3])
        assert angle(poses[k, :3, :3], w2c[0, :3, :3]) <= apart + 1e-9
        assert angle(poses[k, :3, :3], w2c[1, :3, :3]) <= apart + 1e-9


def test_spiral_turns_around_the_mean_camera_and_looks_at_the_centre():
    center = [0.0, 0.0, 0.0]
    w2c = ring_cameras(center, [3.0, 3.0, 3.0, 3.0], [0.1, 0.3, 0.1, 0.3], [1.4, 1.4, 1.7, 1.7])
    poses = spiral_path(w2c, center, 30)
    assert poses.shape == (30, 4, 4) and looks_at(poses, center)
    positions, mean = camera_centers(poses), camera_centers(w2c).mean(0)
    spread = (camera_centers(w2c) - mean).norm(dim=1).max()
    assert float((positions - mean).norm(dim=1).max()) <= 2 * float(spread)
    assert float((positions - mean).norm(dim=1).min()) > 0  # it moves around the mean, not through it only


def test_bad_path_settings_are_clear_errors():
    w2c = ring_cameras([0.0, 0.0, 0.0], [3.0, 3.0], [0.1, 0.2], [0.0, 0.5])
    with pytest.raises(PipelineError, match="at least 2 frames"):
        camera_path("orbit", w2c, [0, 0, 0], 1)
    with pytest.raises(PipelineError, match="unknown camera path 'zigzag'"):
        camera_path("zigzag", w2c, [0, 0, 0], 10)
    with pytest.raises(PipelineError, match="needs at least 2 training camera"):
        interpolated_path(w2c[:1], 10)
    with pytest.raises(PipelineError, match="sits at the centre"):
        orbit_path(w2c, camera_centers(w2c[:1])[0].tolist(), 10)


def test_intrinsics_are_the_training_cameras_scaled_to_an_even_frame_size():
    K = torch.tensor([[50.0, 0, 20.5], [0, 52.0, 15.5], [0, 0, 1]], dtype=torch.float64)
    same, w, h = path_intrinsics([K, K], [41, 41], [31, 31])
    assert (w, h) == (40, 30) and torch.allclose(same, K)  # the odd edge cropped, not rescaled
    double, w, h = path_intrinsics([K], [41], [31], width=82)
    assert (w, h) == (82, 62) and torch.allclose(double[:2], 2 * K[:2])


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    root = tmp_path_factory.mktemp("video")
    scene = write_scene(root / "scene", views=8, width=40, height=30)
    train_quietly(scene, root / "run",
                  {"iterations": 12, "volume_until": 3, "specular_from": 6, "densify_from": 1000,
                   "reset_every": 0, "checkpoint_every": 0, "log_every": 6, "eval_every": 0},
                  {"env_height": 16, "env_width": 32, "env_levels": 3, "mlp_width": 32})
    return root


def test_video_cli_writes_an_mp4_of_the_panels_with_poster_and_frames(trained, tmp_path, capsys):
    out, poster, frames = tmp_path / "orbit.mp4", tmp_path / "poster.png", tmp_path / "frames"
    code = cli(["video", "--run", str(trained / "run"), "--data", str(trained / "scene"), "--out", str(out),
                "--path", "orbit", "--frames", "48", "--fps", "12", "--width", "40", "--panels", "--poster",
                str(poster), "--keep-frames", str(frames), "--quiet"])
    assert code == 0, capsys.readouterr().err
    video, rate = read_mp4(out)
    assert video.shape == (48, 30, 5 * 40, 3) and rate == pytest.approx(12)
    info = json.loads(mp4_comment(out).split(" ", 2)[2])
    assert info["path"] == "orbit" and info["panels"] == ["color", "reflection", "transmission", "normal", "depth"]
    kept = sorted(frames.glob("frame_*.png"))
    assert len(kept) == 48
    for k in (0, 17, 47):  # the MP4 shows the kept frames, up to the codec's loss
        assert np.abs(video[k] / 255.0 - read_image(kept[k])).mean() < CODEC_TOLERANCE
    assert np.array_equal(read_image(poster), read_image(kept[0]))
    # consecutive frames differ smoothly: neighbours less than the first and the middle frame (half a turn
    # apart), and on average by much less (7.5 degree steps around a wall seen from 40x30 pixels)
    image = video[..., :40, :].astype(np.float64)
    neighbours = np.abs(np.diff(image, axis=0)).mean(axis=(1, 2, 3))
    half_turn = np.abs(image[24] - image[0]).mean()
    assert neighbours.max() < 0.8 * half_turn and neighbours.mean() < 0.4 * half_turn


def test_interpolated_video_starts_on_the_first_training_view_as_the_model_renders_it(trained, tmp_path):
    out = tmp_path / "interp.mp4"
    render_video(trained / "run", trained / "scene", out, path="interpolate", frames=24, progress=False)
    video, _ = read_mp4(out)
    assert video.shape == (24, 30, 40, 3)
    run = load_run(trained / "run", trained / "scene", split="train")
    first = min(range(len(run.records)), key=lambda i: run.records[i].name)
    with torch.inference_mode():
        expected = decompose(run.render(run.cameras[first]), Edits())["color"].clamp(0, 1).numpy()
    assert np.abs(video[0] / 255.0 - expected).mean() < CODEC_TOLERANCE
    image = video.astype(np.float64)
    assert np.abs(np.diff(image, axis=0)).mean(axis=(1, 2, 3)).max() < 0.5 * np.abs(image[12] - image[0]).mean()


def test_edits_apply_to_the_video(trained, tmp_path):
    plain, tinted = tmp_path / "plain.mp4", tmp_path / "tinted.mp4"
    render_video(trained / "run", trained / "scene", plain, frames=3, panels=True, progress=False)
    render_video(trained / "run", trained / "scene", tinted, frames=3, panels=True, progress=False,
                 edits=Edits(tint=(0.0, 0.0, 0.0)))
    transmission = slice(2 * 40, 3 * 40)
    assert read_mp4(plain)[0][:, :, transmission].mean() / 255 > 0.1
    assert read_mp4(tinted)[0][:, :, transmission].mean() / 255 < 0.02  # black, up to the codec


def test_a_failed_video_leaves_no_partial_mp4_and_keeps_the_previous_one(trained, tmp_path, monkeypatch):
    out = tmp_path / "video.mp4"
    render_video(trained / "run", trained / "scene", out, frames=3, progress=False)
    before = out.read_bytes()
    calls = []
    real_render = LoadedRun.render

    def failing(self, camera: Camera):
        calls.append(camera)
        if len(calls) == 4:
            raise RuntimeError("render failed")
        return real_render(self, camera)

    monkeypatch.setattr(LoadedRun, "render", failing)
    with pytest.raises(RuntimeError, match="render failed"):
        render_video(trained / "run", trained / "scene", out, frames=8, poster=tmp_path / "p.png",
                     keep_frames=tmp_path / "frames", progress=False)
    assert out.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["video.mp4"]  # no temporary file, poster or frames
    calls.clear()
    with pytest.raises(RuntimeError, match="render failed"):
        render_video(trained / "run", trained / "scene", tmp_path / "new.mp4", frames=8, progress=False)
    assert not (tmp_path / "new.mp4").exists()


def test_bad_video_settings_are_clear_errors(trained, tmp_path, capsys):
    args = ["video", "--run", str(trained / "run"), "--data", str(trained / "scene"), "--quiet"]
    assert cli([*args, "--out", str(tmp_path / "a.mp4"), "--frames", "1"]) == 1
    assert "video.frames" in capsys.readouterr().err
    with pytest.raises(SystemExit) as exc:
        cli([*args, "--out", str(tmp_path / "a.mp4"), "--path", "zigzag"])
    assert exc.value.code == 2 and "invalid choice: 'zigzag'" in capsys.readouterr().err
    assert cli([*args, "--out", str(tmp_path / "a.gif")]) == 1
    assert "ending in .mp4" in capsys.readouterr().err
    (tmp_path / "mine.mp4").write_text("not a video of rtsplat")
    assert cli([*args, "--out", str(tmp_path / "mine.mp4")]) == 1
    assert "not a result of 'rtsplat video'" in capsys.readouterr().err
    assert (tmp_path / "mine.mp4").read_text() == "not a video of rtsplat"
    (tmp_path / "unfinished_run").mkdir()
    assert cli(["video", "--run", str(tmp_path / "unfinished_run"), "--data", str(trained / "scene"), "--out",
                str(tmp_path / "b.mp4")]) == 1
    assert "no trained model here" in capsys.readouterr().err
    # a prepared scene without training views: no cameras to derive a path from
    scene = tmp_path / "test_only"
    shutil.copytree(trained / "scene", scene)
    data = json.loads((scene / "scene.json").read_text())
    for camera in data["cameras"]:
        camera["split"] = "test"
    (scene / "scene.json").write_text(json.dumps(data))
    assert cli(["video", "--run", str(trained / "run"), "--data", str(scene), "--out", str(tmp_path / "c.mp4")]) == 1
    assert "no training cameras" in capsys.readouterr().err
    assert not list(tmp_path.glob("*.mp4.tmp*")) and not list(tmp_path.glob(".*tmp*"))
