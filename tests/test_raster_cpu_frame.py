"""The ``cpu`` backend's numba projection and tile binning (:mod:`rtsplat.raster.cpu_frame`) against
the torch functions they replace (:func:`rtsplat.raster.projection.project_surfels`,
:func:`rtsplat.raster.binning.bin_tiles`), in float64 where both compute the same expressions: every
output, and the gradients of a random mix of the differentiable outputs with respect to the surfels,
the screen probe and the camera's pose (pose refinement learns it through the projection)."""

from __future__ import annotations

import math

import pytest
import torch

from rtsplat.camera import camera_from_fov
from rtsplat.raster import RasterSettings, Surfels, binning, cpu_frame, projection
from rtsplat.raster.cpu import kernels_available

pytestmark = pytest.mark.skipif(not kernels_available(), reason="numba is not installed")

DIFFERENTIABLE = ("ray_transform", "centers", "depths", "normals")
EXACT = ("radii", "valid")
BOXES = ("bbox_min", "bbox_max")


def hard_surfels(n: int, seed: int) -> Surfels:
    """Random surfels around the origin, and the hard cases in their first rows: a zero quaternion, a tiny
    one, zero, huge and mixed scales, the identity rotation, one behind the camera, one at its centre."""
    g = torch.Generator().manual_seed(seed)
    dt = torch.float64
    means = torch.randn(n, 3, generator=g, dtype=dt) * 0.7
    quats = torch.randn(n, 4, generator=g, dtype=dt)
    scales = torch.exp(torch.randn(n, 2, generator=g, dtype=dt) * 0.5 - 3.0)
    quats[0] = 0.0
    quats[1] = torch.tensor([1e-14, 0.0, 0.0, 0.0])
    scales[2] = 0.0
    scales[3] = torch.tensor([1e4, 1e4])
    scales[4] = torch.tensor([1e-12, 2.0])
    quats[5] = torch.tensor([1.0, 0.0, 0.0, 0.0])  # the identity: normal along +z
    means[6] = torch.tensor([6.0, 0.0, 0.0])  # behind the camera at (3, 0.5, 0.8) looking at the origin
    means[7] = torch.tensor([3.0, 0.5, 0.8])  # at the camera centre: depth 0
    n_feat = 2
    return Surfels(means, quats, scales, torch.rand(n, generator=g, dtype=dt), torch.rand(n, generator=g, dtype=dt),
                   torch.rand(n, n_feat, generator=g, dtype=dt), torch.rand(n, 3, generator=g, dtype=dt))


def project_with_grads(project, surfels: Surfels, settings: RasterSettings):
    """Project through a pose-corrected camera; backpropagate a random mix of the differentiable outputs."""
    leaves = {name: getattr(surfels, name).detach().clone().requires_grad_(True)
              for name in ("means", "quats", "scales")}
    s = Surfels(leaves["means"], leaves["quats"], leaves["scales"], surfels.occupancy, surfels.opacity,
                surfels.features, surfels.colors)
    correction = torch.tensor([0.01, -0.02, 0.03, 0.05, -0.04, 0.1], dtype=torch.float64, requires_grad=True)
    camera = camera_from_fov((3.0, 0.5, 0.8), (0.0, 0.0, 0.0), width=57, height=41, dtype=torch.float64)
    camera = camera.corrected(correction)
    probe = torch.zeros(len(s), 2, dtype=torch.float64, requires_grad=True)
    proj = project(s, camera, settings, probe)
    g = torch.Generator().manual_seed(1)
    loss = sum((getattr(proj, name) * torch.randn(getattr(proj, name).shape, generator=g, dtype=torch.float64)).sum()
               for name in DIFFERENTIABLE)
    loss.backward()
    grads = {name: leaf.grad for name, leaf in leaves.items()}
    grads["probe"] = probe.grad
    grads["camera"] = correction.grad
    return proj, grads


@pytest.mark.parametrize("seed", [0, 1])
def test_projection_matches_torch_with_surfel_probe_and_camera_gradients(seed):
    settings = RasterSettings()
    surfels = hard_surfels(500, seed)
    ref, ref_grads = project_with_grads(projection.project_surfels, surfels, settings)
    fast, fast_grads = project_with_grads(cpu_frame.project_surfels, surfels, settings)
    assert bool(ref.valid.any()) and not bool(ref.valid.all())  # the case covers culled surfels
    for name in DIFFERENTIABLE + BOXES:
        actual, expected = getattr(fast, name), getattr(ref, name)
        assert actual.dtype == expected.dtype and actual.shape == expected.shape, name
        torch.testing.assert_close(actual, expected, rtol=1e-12, atol=1e-12, equal_nan=True, msg=name)
    for name in EXACT:
        assert torch.equal(getattr(fast, name), getattr(ref, name)), name
    for name, expected in ref_grads.items():
        actual = fast_grads[name]
        assert torch.isfinite(actual).all(), name
        scale = max(float(expected.abs().max()), 1.0)
        torch.testing.assert_close(actual, expected, rtol=1e-10, atol=1e-12 * scale, msg=name)


def test_projection_of_float32_surfels_returns_float32_and_rounds_like_torch():
    surfels = hard_surfels(300, 2)
    surfels32 = Surfels(*[t.float() for t in (surfels.means, surfels.quats, surfels.scales, surfels.occupancy,
                                              surfels.opacity, surfels.features, surfels.colors)])
    camera = camera_from_fov((3.0, 0.5, 0.8), (0.0, 0.0, 0.0), width=57, height=41)
    ref = projection.project_surfels(surfels32, camera, RasterSettings())
    fast = cpu_frame.project_surfels(surfels32, camera, RasterSettings())
    assert torch.equal(fast.valid, ref.valid)
    for name in DIFFERENTIABLE:
        # culled surfels' centres are ratios of rounding errors (one sits on the camera centre)
        actual, expected = getattr(fast, name)[ref.valid], getattr(ref, name)[ref.valid]
        assert getattr(fast, name).dtype == torch.float32, name
        torch.testing.assert_close(actual, expected, rtol=1e-5, atol=1e-5, msg=name)


def test_a_camera_whose_intrinsics_need_a_gradient_is_projected_by_torch():
    surfels = hard_surfels(50, 3)
    camera = camera_from_fov((3.0, 0.5, 0.8), (0.0, 0.0, 0.0), width=57, height=41, dtype=torch.float64)
    camera.K.requires_grad_(True)
    proj = cpu_frame.project_surfels(surfels, camera, RasterSettings())
    proj.centers[proj.valid].sum().backward()
    assert camera.K.grad is not None and float(camera.K.grad.abs().sum()) > 0


def random_boxes(n: int, seed: int, width: int, height: int):
    g = torch.Generator().manual_seed(seed)
    centre = torch.rand(n, 2, generator=g, dtype=torch.float64) * torch.tensor([width * 1.4, height * 1.4]) - 0.2 * \
        torch.tensor([width, height])
    half = torch.rand(n, 2, generator=g, dtype=torch.float64) * 30
    bbox_min, bbox_max = centre - half, centre + half
    depths = torch.randint(1, 20, (n,), generator=g).double() / 4  # many ties: their order is the index order
    valid = torch.rand(n, generator=g) > 0.1
    # boxes far beyond the image and beyond the int64 range of tile indices
    bbox_max[0] = torch.tensor([1e30, 5.0])
    bbox_min[1] = torch.tensor([-1e30, -1e30])
    bbox_max[1] = torch.tensor([1e25, 1e25])
    bbox_min[2] = torch.tensor([float(width), 0.0])
    valid[:3] = True
    return bbox_min, bbox_max, depths, valid


@pytest.mark.parametrize("size,tile", [((100, 75), 16), ((37, 23), 8), ((16, 16), 16)])
def test_binning_gives_the_lists_of_torch(size, tile):
    width, height = size
    bbox_min, bbox_max, depths, valid = random_boxes(400, width, width, height)
    ref = binning.bin_tiles(bbox_min, bbox_max, depths, valid, width, height, tile)
    fast = cpu_frame.bin_tiles(bbox_min, bbox_max, depths, valid, width, height, tile)
    assert (fast.tiles_x, fast.tiles_y, fast.tile_size, fast.width, fast.height) == (
        ref.tiles_x, ref.tiles_y, ref.tile_size, ref.width, ref.height)
    for name in ("surfel_ids", "tile_start", "tile_count"):
        assert torch.equal(getattr(fast, name), getattr(ref, name)), name


def test_binning_visits_every_tile_a_huge_box_covers():
    """A box edge beyond the int64 range is clamped to the last tile, not wrapped to the first."""
    width, height, tile = 64, 32, 16
    bbox_min = torch.tensor([[-1e30, 3.0]], dtype=torch.float32)
    bbox_max = torch.tensor([[1e30, 5.0]], dtype=torch.float32)
    depths = torch.ones(1)
    valid = torch.ones(1, dtype=torch.bool)
    for bins in (binning.bin_tiles(bbox_min, bbox_max, depths, valid, width, height, tile),
                 cpu_frame.bin_tiles(bbox_min, bbox_max, depths, valid, width, height, tile)):
        assert bins.tile_count.tolist() == [1, 1, 1, 1, 0, 0, 0, 0]


def test_edge_on_and_degenerate_surfels_stay_finite():
    surfels = hard_surfels(20, 4)
    # exactly edge-on: the surfel's plane contains the camera centre
    surfels.quats[8] = torch.tensor([math.cos(math.pi / 4), 0.0, math.sin(math.pi / 4), 0.0], dtype=torch.float64)
    surfels.means[8] = torch.tensor([0.0, 0.5, 0.8], dtype=torch.float64)
    proj, grads = project_with_grads(cpu_frame.project_surfels, surfels, RasterSettings())
    for name in DIFFERENTIABLE:
        assert torch.isfinite(getattr(proj, name)[proj.valid]).all(), name
    for name, grad in grads.items():
        assert torch.isfinite(grad).all(), name


def test_projection_without_a_probe_backpropagates_to_the_surfels():
    surfels = hard_surfels(40, 5)
    means = surfels.means.clone().requires_grad_(True)
    s = Surfels(means, surfels.quats, surfels.scales, surfels.occupancy, surfels.opacity, surfels.features,
                surfels.colors)
    camera = camera_from_fov((3.0, 0.5, 0.8), (0.0, 0.0, 0.0), width=57, height=41, dtype=torch.float64)
    grads = []
    for project in (cpu_frame.project_surfels, projection.project_surfels):
        means.grad = None
        proj = project(s, camera, RasterSettings())
        proj.centers[proj.valid].sum().backward()
        grads.append(means.grad.clone())
    torch.testing.assert_close(grads[0], grads[1], rtol=1e-10, atol=1e-12)
