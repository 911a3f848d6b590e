"""Exact identities of the two weight sets, checked against an independent brute-force loop.

The brute force below shares no code with rtsplat.raster: it intersects each pixel's world-space
ray with each surfel's plane (instead of the homogeneous ray transform), gets rotations from
scipy, and composites with an explicit per-pixel Python loop, following 2DGS's rules (alpha
clamp 0.99, skip below 1/255, near test, stop before transmittance drops below 1e-4).

Scenes here either keep every effective alpha <= 0.35 (so a pair beyond the 3-sigma screen box
has alpha < 1/255 and the tile culling of the rasterizer is invisible) or use surfels that
cover the whole image.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch
from raster_scenes import facing_quat, random_surfels, replace, small_camera
from scipy.spatial.transform import Rotation

from rtsplat.raster import RasterSettings, Surfels, rasterize

SET = RasterSettings()


def brute_force_blend(surfels: Surfels, camera, base_alpha: np.ndarray, values: np.ndarray) -> dict:
    """Plain 2DGS alpha blending with per-surfel opacity ``base_alpha`` of per-surfel ``values``."""
    K = camera.K.numpy()
    w2c = camera.world_to_camera.numpy()
    R, t = w2c[:3, :3], w2c[:3, 3]
    eye = -R.T @ t
    K_inv = np.linalg.inv(K)
    means = surfels.means.numpy()
    q = surfels.quats.numpy()
    rot = Rotation.from_quat(q[:, [1, 2, 3, 0]]).as_matrix()  # scipy wants (x, y, z, w)
    scales = surfels.scales.numpy()
    cam_means = means @ R.T + t
    order = np.argsort(cam_means[:, 2], kind="stable")
    proj = cam_means @ K.T
    centers = proj[:, :2] / proj[:, 2:3]
    H, W = camera.height, camera.width
    C = values.shape[1]
    out = {k: np.zeros((H, W, c)) for k, c in
           [("value", C), ("alpha", 1), ("depth", 1), ("median", 1), ("distortion", 1)]}
    far, near = SET.far, SET.near
    for row in range(H):
        for col in range(W):
            pix = np.array([col + 0.5, row + 0.5])
            ray = R.T @ (K_inv @ np.array([pix[0], pix[1], 1.0]))
            T = 1.0
            acc = np.zeros(C)
            weight_sum = depth_sum = m1 = m2 = dist = 0.0
            median = 0.0
            for i in order:
                if cam_means[i, 2] <= near:
                    continue
                n, tu, tv = rot[i][:, 2], rot[i][:, 0], rot[i][:, 1]
                denom = n @ ray
                rho3d = np.inf
                if abs(denom) > 1e-12 and scales[i].min() > 0:
                    hit = eye + ray * (n @ (means[i] - eye)) / denom
                    u = (hit - means[i]) @ tu / scales[i, 0]
                    v = (hit - means[i]) @ tv / scales[i, 1]
                    rho3d = u * u + v * v
                    z_hit = (R @ hit + t)[2]
                rho2d = 2.0 * np.sum((centers[i] - pix) ** 2)
                if rho3d <= rho2d:
                    rho, z = rho3d, z_hit
                else:
                    rho, z = rho2d, cam_means[i, 2]
                if z < near:
                    continue
                a = min(0.99, base_alpha[i] * np.exp(-0.5 * rho))
                if a < 1.0 / 255.0:
                    continue
                if T * (1 - a) < 1e-4:
                    break
                w = a * T
                m = far / (far - near) * (1 - near / z)
                dist += w * (m * m * weight_sum + m2 - 2 * m * m1)
                if T > 0.5:
                    median = z
                acc += w * values[i]
                weight_sum += w
                depth_sum += w * z
                m1 += w * m
                m2 += w * m * m
                T *= 1 - a
            out["value"][row, col] = acc
            out["alpha"][row, col] = weight_sum
            out["depth"][row, col] = depth_sum / weight_sum if weight_sum > 0 else 0.0
            out["median"][row, col] = median
            out["distortion"][row, col] = dist
    return out


def _surface_values(surfels: Surfels, camera) -> np.ndarray:
    """Features and camera-facing world normals, as the rasterizer's surface set blends them."""
    rot = Rotation.from_quat(surfels.quats.numpy()[:, [1, 2, 3, 0]]).as_matrix()
    normals = rot[:, :, 2]
    to_camera = camera.center.numpy()[None] - surfels.means.numpy()
    normals = np.where((np.sum(normals * to_camera, 1) < 0)[:, None], -normals, normals)
    return np.concatenate([surfels.features.numpy(), normals], 1)


def assert_close(actual: torch.Tensor, expected: np.ndarray, name: str, atol: float = 1e-9) -> None:
    err = np.abs(actual.detach().numpy() - expected).max()
    assert err <= atol, f"{name}: max abs error {err:.3e} > {atol:.1e}"


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_low_alpha_scene_matches_brute_force_for_both_weight_sets(seed):
    camera = small_camera()
    surfels = random_surfels(14, seed, occupancy_range=(0.05, 0.35), opacity_range=(0.0, 1.0))
    out = rasterize(surfels, camera, backend="reference")
    surface = brute_force_blend(surfels, camera, surfels.occupancy.numpy(), _surface_values(surfels, camera))
    F = surfels.features.shape[1]
    assert_close(out.features, surface["value"][..., :F], "features")
    assert_close(out.normal, surface["value"][..., F:], "normal")
    assert_close(out.alpha, surface["alpha"], "alpha")
    assert_close(out.depth, surface["depth"], "depth")
    assert_close(out.depth_median, surface["median"], "depth_median")
    assert_close(out.distortion, surface["distortion"], "distortion")
    volume = brute_force_blend(
        surfels, camera, (surfels.occupancy * surfels.opacity).numpy(), surfels.colors.numpy()
    )
    assert_close(out.color, volume["value"], "color")
    assert_close(out.volume_alpha, volume["alpha"], "volume_alpha")
    assert_close(out.volume_depth, volume["depth"], "volume_depth")
    assert out.alpha.max() > 0.3, "scene too empty to test anything"


@pytest.mark.parametrize("seed", [3, 4])
def test_full_occupancy_volume_equals_plain_2dgs_with_that_opacity(seed):
    """occupancy = 1, opacity = x: the volume set is plain 2DGS blending with opacity x."""
    camera = small_camera()
    base = random_surfels(14, seed, opacity_range=(0.05, 0.35))
    surfels = replace(base, occupancy=torch.ones_like(base.occupancy))
    out = rasterize(surfels, camera, backend="reference")
    plain = brute_force_blend(base, camera, base.opacity.numpy(), base.colors.numpy())
    assert_close(out.color, plain["value"], "color")
    assert_close(out.volume_alpha, plain["alpha"], "volume_alpha")
    assert_close(out.volume_depth, plain["depth"], "volume_depth")
    # the surface set, with occupancy 1, is far more opaque than the volume set here
    assert (out.alpha - out.volume_alpha).max() > 0.3


@pytest.mark.parametrize("seed", [5, 6])
def test_unit_opacity_makes_volume_weights_equal_surface_weights(seed):
    camera = small_camera()
    base = random_surfels(20, seed, occupancy_range=(0.1, 1.0), n_features=3)
    surfels = replace(base, opacity=torch.ones_like(base.opacity), features=base.colors)
    out = rasterize(surfels, camera, backend="reference")
    # the weights are bit-identical (same sums in the same order); the blended values differ
    # only by the summation order of the two matrix products (float64 rounding)
    assert torch.equal(out.alpha, out.volume_alpha)
    torch.testing.assert_close(out.features, out.color, rtol=0, atol=1e-14)
    assert torch.equal(out.depth, out.volume_depth)
    assert out.alpha.max() > 0.5


def test_stacked_full_screen_layers_clamp_and_stop_like_2dgs():
    """Opaque screen-filling surfels: alpha clamp 0.99 and early termination before T < 1e-4."""
    camera = small_camera(eye=(0.0, -3.0, 0.0))
    n = 4
    depths = torch.tensor([-0.6, -0.2, 0.2, 0.6], dtype=torch.float64)
    means = torch.stack([torch.zeros(n), depths, torch.zeros(n)], 1).double()
    quats = facing_quat((0.0, 1.0, 0.0)).expand(n, 4).clone()
    surfels = Surfels(
        means=means, quats=quats, scales=torch.full((n, 2), 4.0, dtype=torch.float64),
        occupancy=torch.tensor([0.97, 1.0, 0.98, 1.0], dtype=torch.float64),
        opacity=torch.tensor([1.0, 0.5, 1.0, 1.0], dtype=torch.float64),
        features=torch.eye(n, dtype=torch.float64), colors=torch.rand(n, 3, dtype=torch.float64),
    )
    out = rasterize(surfels, camera, backend="reference")
    surface = brute_force_blend(surfels, camera, surfels.occupancy.numpy(), _surface_values(surfels, camera))
    assert_close(out.features, surface["value"][..., :n], "features")
    assert_close(out.alpha, surface["alpha"], "alpha")
    assert_close(out.depth_median, surface["median"], "depth_median")
    assert_close(out.distortion, surface["distortion"], "distortion")
    volume = brute_force_blend(surfels, camera, (surfels.occupancy * surfels.opacity).numpy(),
                               surfels.colors.numpy())
    assert_close(out.color, volume["value"], "color")
    # at the image centre (G ~ 1) layer 2 (occupancy 1) is clamped to alpha 0.99; the two layers
    # leave T = 0.03 * 0.01 = 3e-4, and layer 3 (alpha 0.98) would bring it below 1e-4: it is
    # never composited there, nor is layer 4
    centre = out.features.detach()[camera.height // 2, camera.width // 2]
    assert abs(float(centre[1]) - 0.99 * (1.0 - float(centre[0]))) < 1e-12
    assert float(centre[0]) > 0.96
    assert centre[2:].abs().max() == 0
