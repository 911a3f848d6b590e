import math

import pytest
import torch

from rtsplat.camera import Camera, camera_from_colmap, camera_from_fov, intrinsics, look_at


def test_look_at_puts_target_at_image_centre_and_up_upwards():
    cam = camera_from_fov((1.0, -4.0, 2.0), (0.2, 0.1, 0.3), width=64, height=48, dtype=torch.float64)
    torch.testing.assert_close(cam.center, torch.tensor([1.0, -4.0, 2.0], dtype=torch.float64))
    pix, z = cam.project(torch.tensor([[0.2, 0.1, 0.3], [0.2, 0.1, 1.3]], dtype=torch.float64))
    torch.testing.assert_close(pix[0], torch.tensor([32.0, 24.0], dtype=torch.float64))
    assert z[0] > 0
    assert pix[1, 1] < pix[0, 1]  # world +z (up) appears higher in the image (smaller y)
    R = cam.rotation
    torch.testing.assert_close(R @ R.T, torch.eye(3, dtype=torch.float64))
    assert torch.det(R) > 0


def test_horizontal_field_of_view():
    cam = camera_from_fov((0, 0, 0), (0, 1, 0), width=100, height=50, fov_x_deg=90.0, dtype=torch.float64)
    edge = torch.tensor([[math.tan(math.radians(45)), 1.0, 0.0]], dtype=torch.float64)
    pix, _ = cam.project(edge)
    assert abs(float(pix[0, 0]) - 100.0) < 1e-9  # right image border


def test_scaled_camera_projects_exactly_to_scaled_pixels():
    cam = camera_from_fov((0.5, -3, 1), (0, 0, 0), width=200, height=150, dtype=torch.float64)
    points = torch.randn(20, 3, dtype=torch.float64) * 0.5
    pix, _ = cam.project(points)
    half = cam.scaled(2)
    assert (half.width, half.height) == (100, 75)
    pix_half, _ = half.project(points)
    torch.testing.assert_close(pix_half, pix / 2)


def test_colmap_pose_is_copied_without_flips():
    w2c = look_at((1, 2, 3), (0, 0, 0), dtype=torch.float64)
    cam = camera_from_colmap(100.0, 110.0, 32.0, 24.0, 64, 48, w2c[:3, :4].numpy(), dtype=torch.float64)
    torch.testing.assert_close(cam.world_to_camera, w2c)
    torch.testing.assert_close(cam.K, intrinsics(100.0, 110.0, 32.0, 24.0, dtype=torch.float64))


def test_invalid_cameras_are_rejected_with_a_clear_message():
    with pytest.raises(ValueError, match="K must be 3x3"):
        Camera(torch.eye(4), torch.eye(4), 10, 10)
    with pytest.raises(ValueError, match="4x4"):
        Camera(torch.eye(3), torch.eye(3), 10, 10)
    with pytest.raises(ValueError, match="positive"):
        Camera(torch.eye(3), torch.eye(4), 0, 10)
    with pytest.raises(ValueError, match="parallel"):
        look_at((0, 0, 0), (0, 0, 1), up=(0, 0, 1))


def test_pixel_rays_project_back_to_their_pixels():
    from rtsplat.camera import pixel_rays

    cam = camera_from_fov((1.0, -3.0, 2.0), (0.2, 0.1, 0.3), width=64, height=48, fov_x_deg=55.0, dtype=torch.float64)
    cam = Camera(intrinsics(70.0, 64.0, 30.5, 25.0, dtype=torch.float64), cam.world_to_camera, 64, 48)
    u = torch.tensor([0.0, 0.5, 31.25, 63.9])
    v = torch.tensor([0.0, 47.5, 12.0, 30.0])
    origin, dirs = pixel_rays(cam, u, v)
    assert torch.allclose(origin, cam.center) and torch.allclose(dirs.norm(dim=-1), torch.ones(4, dtype=torch.float64))
    pix, depth = cam.project(origin + 2.5 * dirs)
    assert (depth > 0).all() and torch.allclose(pix, torch.stack([u, v], -1).double(), atol=1e-9)
