"""The fast ``cpu`` backend against the torch reference (the oracle).

Both backends composite in the same order with the same tests; the cpu kernels work in float64
internally. Tolerances:

* float64 inputs: outputs and every gradient agree to rtol 1e-7 / atol 1e-9 (only summation order
  differs: per-(tile, surfel) gradient buffers reduced with ``index_add_``);
* float32 inputs: outputs to atol 5e-5 (max seen: 2.3e-5, a normal), gradients to rtol 1e-3 / atol 1e-4 relative to the
  largest gradient of the parameter (the reference accumulates transmittance products in float32,
  the kernels in float64; near the 1/255 skip and the 1e-4 transmittance cut-off a float32
  rounding can flip one pair's test, which is what bounds these tolerances).
"""

from __future__ import annotations

import math
import subprocess
import sys

import pytest
import torch
from raster_scenes import SURFEL_FIELDS, random_surfels, replace, small_camera, with_grad
from test_raster_hard_cases import CAMERA_EYE, IMAGE_OUTPUTS, surfels_at

from rtsplat.raster import Surfels, default_backend, rasterize
from rtsplat.raster.cpu import kernels_available

pytestmark = pytest.mark.skipif(not kernels_available(), reason="numba is not installed")


def run(surfels: Surfels, camera, backend: str, seed: int = 0):
    s = with_grad(surfels)
    out = rasterize(s, camera, backend=backend)
    g = torch.Generator().manual_seed(seed)
    loss = sum((getattr(out, name) * torch.rand(getattr(out, name).shape, generator=g,
                                                  dtype=getattr(out, name).dtype)).sum() for name in IMAGE_OUTPUTS)
    grads = {}
    if loss.requires_grad:
        loss.backward()
        grads = {name: getattr(s, name).grad for name in SURFEL_FIELDS}
        grads["screen_probe"] = out.screen_probe.grad
    return out, grads


def assert_parity(surfels: Surfels, camera, *, out_atol, grad_rtol, grad_atol):
    ref, ref_grads = run(surfels, camera, "reference")
    fast, fast_grads = run(surfels, camera, "cpu")
    for name in IMAGE_OUTPUTS:
        torch.testing.assert_close(getattr(fast, name), getattr(ref, name), rtol=0, atol=out_atol, msg=name)
        assert torch.isfinite(getattr(fast, name)).all(), name
    assert torch.equal(fast.visible, ref.visible)
    torch.testing.assert_close(fast.radii, ref.radii)
    torch.testing.assert_close(fast.means2d, ref.means2d)
    for name, expected in ref_grads.items():
        actual = fast_grads[name]
        if expected is None:
            assert actual is None or actual.abs().max() == 0, name
            continue
        assert actual is not None and torch.isfinite(actual).all(), name
        scale = float(expected.abs().max()) if expected.numel() else 0.0
        torch.testing.assert_close(actual, expected, rtol=grad_rtol, atol=grad_atol * max(scale, 1.0), msg=name)


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_random_scenes_float64(seed):
    camera = small_camera(37, 29, torch.float64)  # not a multiple of the tile size
    surfels = random_surfels(60, seed, dtype=torch.float64, n_features=4)
    assert_parity(surfels, camera, out_atol=1e-9, grad_rtol=1e-7, grad_atol=1e-9)


@pytest.mark.parametrize("seed", [10, 11])
def test_random_scenes_float32(seed):
    camera = small_camera(48, 32, torch.float32)
    surfels = random_surfels(150, seed, dtype=torch.float32, n_features=12)
    assert_parity(surfels, camera, out_atol=5e-5, grad_rtol=1e-3, grad_atol=1e-4)


def _hard_scenes():
    f64 = torch.float64
    yield "edge_on", small_camera(33, 33, f64, eye=CAMERA_EYE), surfels_at([[0, 0, 0]], (1.0, 0, 0), 0.5, f64)
    base = random_surfels(30, 1, dtype=f64)
    for scale in (0.0, 1e-30, 1e4):
        yield f"scale_{scale}", small_camera(32, 24, f64), replace(base, scales=torch.full_like(base.scales, scale))
    for occ in (0.0, 1.0):
        for opa in (0.0, 1.0):
            s = replace(base, occupancy=torch.full_like(base.occupancy, occ),
                        opacity=torch.full_like(base.opacity, opa))
            yield f"occ{occ}_opa{opa}", small_camera(32, 24, f64), s
    yield "behind", small_camera(32, 24, f64, eye=CAMERA_EYE), surfels_at(
        [[0.0, -4.0, 0.0], [0.0, -3.1, 0.0], [0.0, -3.0, 0.0]], (0.0, 1.0, 0.0), 1.0, f64)
    yield "near_plane", small_camera(32, 24, f64, eye=(0.0, -3.0, 0.3)), surfels_at(
        [[0.0, -2.5, 0.0]], (0.0, 0.0, 1.0), 2.0, f64)
    n = 3000
    means = torch.stack([torch.zeros(n), torch.linspace(-1.0, 1.0, n), torch.zeros(n)], 1)
    yield "stack_3000", small_camera(16, 16, f64, eye=CAMERA_EYE), surfels_at(
        means, (0.0, 1.0, 0.0), 0.02, f64, occupancy=0.5, opacity=0.3)
    yield "grazing", small_camera(24, 16, f64, eye=CAMERA_EYE), surfels_at(
        [[0.0, -2.0, 0.0]], (math.sin(math.pi / 2 - 1e-7), -math.cos(math.pi / 2 - 1e-7), 0.0), 0.5, f64)
    yield "empty", small_camera(20, 12, f64), random_surfels(0, 0, dtype=f64)


@pytest.mark.parametrize("name,camera,surfels", list(_hard_scenes()), ids=[h[0] for h in _hard_scenes()])
def test_hard_cases_float64(name, camera, surfels):
    assert_parity(surfels, camera, out_atol=1e-8, grad_rtol=1e-6, grad_atol=1e-8)


def test_auto_picks_cpu_and_reference_stays_selectable():
    assert default_backend(torch.device("cpu")) == "cpu"
    camera = small_camera(16, 12, torch.float32)
    surfels = random_surfels(10, 0, dtype=torch.float32)
    with torch.no_grad():
        a = rasterize(surfels, camera, backend="reference").color
        b = rasterize(surfels, camera).color
    torch.testing.assert_close(a, b, rtol=0, atol=1e-5)


def test_importing_rtsplat_does_not_import_numba():
    code = "import sys, rtsplat, rtsplat.raster, rtsplat.raster.cpu; print('numba' in sys.modules)"
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert result.stdout.strip() == "False"
