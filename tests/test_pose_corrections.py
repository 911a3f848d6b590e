"""Per-view pose corrections: the rigid motion, fitting a view's pose to its image, and the trainer
and renderer carrying the corrections."""

from __future__ import annotations

import math

import numpy as np
import torch
from raster_scenes import random_surfels, small_camera
from scipy.spatial.transform import Rotation

from rtsplat.camera import rigid_motion
from rtsplat.model.checkpoint import read_checkpoint
from rtsplat.raster import rasterize
from rtsplat.render import corrected_cameras
from rtsplat.train.cameras import fit_corrections


def test_rigid_motion_is_the_rotation_of_the_rotation_vector_and_finite_at_zero():
    for vector in ([0.3, -0.2, 0.5], [1e-9, 0.0, 0.0], [0.0, 2.5, -1.0]):
        correction = torch.tensor([*vector, 0.1, -0.2, 0.3], dtype=torch.float64)
        motion = rigid_motion(correction).numpy()
        np.testing.assert_allclose(motion[:3, :3], Rotation.from_rotvec(vector).as_matrix(), atol=1e-12)
        np.testing.assert_allclose(motion[:3, 3], [0.1, -0.2, 0.3])
        np.testing.assert_array_equal(motion[3], [0, 0, 0, 1])
    zero = torch.zeros(6, dtype=torch.float64, requires_grad=True)
    np.testing.assert_array_equal(rigid_motion(zero).detach().numpy(), np.eye(4))
    (rigid_motion(zero) * torch.arange(16.0, dtype=torch.float64).reshape(4, 4)).sum().backward()
    assert torch.isfinite(zero.grad).all() and zero.grad.abs().sum() > 0
    camera = small_camera()
    assert torch.equal(camera.corrected(torch.zeros(6)).world_to_camera, camera.world_to_camera)


def _textured_scene():
    surfels = random_surfels(300, seed=3, spread=0.8, scale_range=(0.05, 0.15), occupancy_range=(0.6, 0.95))
    colors = torch.rand(300, 3, generator=torch.Generator().manual_seed(4), dtype=torch.float64)
    surfels.colors = colors
    return surfels


def test_fitting_a_test_view_recovers_a_perturbed_pose():
    surfels = _textured_scene()
    truth = small_camera(48, 36)

    def render(camera):
        return rasterize(surfels, camera).color

    image = render(truth).detach()
    error = torch.tensor([0.012, -0.008, 0.010, 0.02, -0.015, 0.01], dtype=torch.float64)  # ~0.9 degrees
    start_camera = truth.corrected(error)
    fitted = fit_corrections(render, [start_camera], [image], torch.zeros(1, 6, dtype=torch.float64), 1.0,
                             steps=60, lr=2e-3)
    moved = start_camera.corrected(fitted[0]).world_to_camera
    residual = moved @ torch.linalg.inv(truth.world_to_camera)
    before = math.degrees(Rotation.from_matrix(rigid_motion(error)[:3, :3].numpy()).magnitude())
    after = math.degrees(Rotation.from_matrix(residual[:3, :3].numpy()).magnitude())
    assert before > 0.8
    assert after < 0.25 * before
    l1 = lambda camera: float((render(camera) - image).abs().mean().detach())  # noqa: E731
    assert l1(start_camera.corrected(fitted[0])) < 0.5 * l1(start_camera)


def test_a_fit_never_ends_worse_than_it_started_and_leaves_the_model_gradients_alone():
    surfels = _textured_scene()
    surfels.colors.requires_grad_(True)
    truth = small_camera(32, 24)
    image = rasterize(surfels, truth).color.detach()
    start = torch.zeros(1, 6, dtype=torch.float64)
    # a learning rate far too large: the steps overshoot, the best correction seen is the start
    fitted = fit_corrections(lambda c: rasterize(surfels, c).color, [truth], [image], start, 1.0, steps=5, lr=0.5)
    assert torch.equal(fitted, start)
    assert surfels.colors.grad is None


def test_trainer_saves_every_views_correction_and_render_applies_them(tmp_path):
    from test_train import config

    from rtsplat.bench.toy_scene import write_scene
    from rtsplat.train.trainer import Trainer

    scene = write_scene(tmp_path / "scene", views=8, width=32, height=24)
    cfg = config(24, cameras={"refine_from": 0, "final_fit_steps": 3}, schedule={"eval_every": 12})
    summary = Trainer(scene, cfg, tmp_path / "run", progress=False, log=lambda m: None).train()
    corrections = read_checkpoint(tmp_path / "run" / "model.pt").training["camera_corrections"]
    prepared = scene
    assert sorted(corrections) == sorted(c.name for c in prepared.cameras)
    values = np.array(list(corrections.values()))
    assert np.isfinite(values).all()
    assert np.abs(values).max() > 0  # the training views moved
    assert summary["train_pose_correction_deg"] > 0
    cameras = corrected_cameras(prepared.train_cameras, corrections, "cpu")
    for rec, camera in zip(prepared.train_cameras, cameras, strict=True):
        expected = rigid_motion(torch.tensor(corrections[rec.name])) @ rec.to_camera().world_to_camera
        torch.testing.assert_close(camera.world_to_camera, expected)


def test_test_views_fit_their_poses_keep_them_by_name_and_a_fresh_set_restores_them():
    """rtsplat.train.evaluation.TestViews: the fit moves a perturbed test view towards its photo (higher
    PSNR), its rows name every view, and restoring them elsewhere gives the same cameras; a view the
    saved rows do not name keeps a zero correction."""
    from rtsplat.train.data import ViewSet
    from rtsplat.train.evaluation import TestViews, rows_by_name

    surfels = _textured_scene()

    def render(camera):
        return rasterize(surfels, camera).color

    truth = small_camera(48, 36)
    photo = render(truth).detach()
    start = truth.corrected(torch.tensor([0.010, -0.008, 0.012, 0.015, -0.01, 0.01], dtype=torch.float64))
    other = small_camera(48, 36)
    views = ViewSet(["a.png", "b.png"], [start, other], [photo, render(other).detach()], [None, None])
    test = TestViews(views, torch.device("cpu"), poses=True, appearance=False)
    before = test.psnr(render)["test_psnr"]
    test.fit(render, steps=40, extent=1.0, pose_lr=2e-3, appearance_prior=0.0)
    assert test.psnr(render)["test_psnr"] > before + 3.0
    assert test.seconds > 0 and test.poses[0].abs().max() > 0
    rows = rows_by_name(views.names, test.poses)
    assert sorted(rows) == ["a.png", "b.png"]
    fresh = TestViews(views, torch.device("cpu"), poses=True, appearance=False)
    fresh.restore({"a.png": rows["a.png"], "c.png": [1.0] * 6}, {})
    torch.testing.assert_close(fresh.cameras()[0].world_to_camera, test.cameras()[0].world_to_camera)
    assert torch.equal(fresh.poses[1], torch.zeros(6))
