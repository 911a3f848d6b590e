"""The ``triton`` backend against the torch reference (the oracle), in Triton's interpreter or on a GPU.

Without a CUDA device, ``TRITON_INTERPRET=1`` is set before triton is first imported, so the kernels'
Python bodies run on CPU tensors with numpy semantics: the same kernel source as on a GPU, no GPU
needed. The interpreter costs ~0.1 s per (tile, surfel) step, so the scenes are tiny (a few 16x16
tiles, a dozen surfels): this is an oracle of the semantics, not a speed test. Compiling the same
kernels for a CUDA target is checked in ``test_raster_triton_aot.py``. With a CUDA device the
interpreter is left off and the same tests compare the compiled kernels with the reference, both on
the GPU.

The checks and tolerances are those of the cpu backend's parity tests (``test_raster_cpu.py``):
every image output, ``visible``/``radii``/``means2d``, and the gradient of a random mix of every
output with respect to every surfel parameter and the screen probe. float64 inputs run the kernels
in float64, float32 inputs in float32 (the reference then also accumulates in float32).
"""

from __future__ import annotations

import importlib.util
import math
import os

import pytest
import torch

if importlib.util.find_spec("triton") is None:
    pytest.skip("triton is not installed", allow_module_level=True)
ON_GPU = torch.cuda.is_available()
if not ON_GPU:
    # read when triton.language and the kernels are decorated, i.e. on their first import: set it before
    os.environ["TRITON_INTERPRET"] = "1"
DEVICE = torch.device("cuda" if ON_GPU else "cpu")

from raster_scenes import SURFEL_FIELDS, random_surfels, replace, small_camera, with_grad  # noqa: E402
from test_raster_cpu import (  # noqa: E402
    F32,
    F32_ILL,
    F64,
    F64_HARD,
    ILL_CONDITIONED_FLOAT32,
    _extreme_mixtures,
    _python,
    _scale,
    assert_as_accurate_as_reference,
    assert_mostly_close,
    assert_parity,
)
from test_raster_hard_cases import CAMERA_EYE, surfels_at  # noqa: E402

from rtsplat.bench.raster import sphere_scene, surfels_to  # noqa: E402
from rtsplat.raster import RasterSettings, Surfels, default_backend, rasterize  # noqa: E402
from rtsplat.raster.gpu import kernels_interpreted  # noqa: E402


@pytest.fixture(autouse=True)
def _interpreted():
    if not ON_GPU and not kernels_interpreted():
        pytest.skip("triton was imported without TRITON_INTERPRET=1 earlier in this process")


def parity(surfels, camera, tolerances, **kw):
    """assert_parity of the triton backend against the reference, both on ``DEVICE``."""
    return assert_parity(surfels_to(surfels, DEVICE), camera.to(DEVICE), backend="triton", **tolerances, **kw)


def as_accurate_as_reference(surfels32, camera32, camera64, **kw):
    return assert_as_accurate_as_reference(
        surfels_to(surfels32, DEVICE), camera32.to(DEVICE), camera64.to(DEVICE), backend="triton", **kw
    )


# -- random scenes ---------------------------------------------------------------------------------


@pytest.mark.parametrize("seed,n_features", [(0, 4), (2, 0)])
def test_random_scenes_float64(seed, n_features):
    camera = small_camera(27, 19, torch.float64)  # 2x2 tiles, the border ones partly outside the image
    parity(random_surfels(10, seed, dtype=torch.float64, n_features=n_features), camera, F64)


def test_random_scene_float32_with_a_wide_g_buffer():
    camera = small_camera(32, 24, torch.float32)
    parity(random_surfels(10, 10, dtype=torch.float32, n_features=12), camera, F32)


@pytest.mark.parametrize("tile_size", [8, 6])  # 6: 36 pixels on 64 lanes, the rest masked
def test_custom_settings_reach_the_kernels(tile_size):
    settings = RasterSettings(
        tile_size=tile_size, near=2.5, far=20.0, alpha_max=0.9, alpha_min=0.02, transmittance_min=0.05,
        lowpass_inv_var=0.5,
    )
    camera = small_camera(2 * tile_size, 2 * tile_size - 3, torch.float64)
    parity(random_surfels(8, 5, dtype=torch.float64, n_features=3), camera, F64, settings=settings)


def test_layered_sphere_float32_terminates_early_like_the_reference():
    # front and back layers of an object, large and dense: both weight sets stop on about half the pixels
    camera = small_camera(16, 16, torch.float32, eye=CAMERA_EYE)
    scene = sphere_scene(24, seed=3, n_features=2)
    scene = replace(
        scene, scales=2.0 * scene.scales, occupancy=0.5 + 0.5 * scene.occupancy, opacity=0.5 + 0.5 * scene.opacity
    )
    ref, fast = parity(scene, camera, F32)
    t_min = RasterSettings().transmittance_min
    assert (ref.alpha > 1.0 - 2 * t_min).float().mean() > 0.2
    assert (ref.volume_alpha > 1.0 - 2 * t_min).float().mean() > 0.2
    assert (fast.alpha <= 1.0 - t_min + 1e-6).all() and (fast.volume_alpha <= 1.0 - t_min + 1e-6).all()


def test_float32_triton_is_as_accurate_as_float32_reference():
    scene = sphere_scene(30, seed=4, n_features=2)
    as_accurate_as_reference(
        scene, small_camera(16, 16, torch.float32, eye=CAMERA_EYE), small_camera(16, 16, torch.float64, eye=CAMERA_EYE)
    )


# -- hard cases (the catalogue of test_raster_hard_cases.py, on fewer surfels) ---------------------


def _hard_scenes(dtype):
    yield "edge_on", small_camera(17, 17, dtype, eye=CAMERA_EYE), surfels_at([[0, 0, 0]], (1.0, 0, 0), 0.5, dtype)
    base = random_surfels(6, 1, dtype=dtype)
    for scale in (0.0, 1e4):
        yield f"scale_{scale}", small_camera(20, 16, dtype), replace(base, scales=torch.full_like(base.scales, scale))
    mixed = torch.stack([torch.zeros(6, dtype=dtype), torch.full((6,), 1e4, dtype=dtype)], 1)
    yield "scale_0_and_1e4", small_camera(20, 16, dtype), replace(base, scales=mixed)
    for occ, opa in ((0.0, 1.0), (1.0, 0.0), (1.0, 1.0)):
        s = replace(base, occupancy=torch.full_like(base.occupancy, occ), opacity=torch.full_like(base.opacity, opa))
        yield f"occ{occ}_opa{opa}", small_camera(20, 16, dtype), s
    yield (
        "behind",
        small_camera(16, 16, dtype, eye=CAMERA_EYE),
        surfels_at([[0.0, -4.0, 0.0], [0.0, -3.1, 0.0], [0.0, -3.0, 0.0]], (0.0, 1.0, 0.0), 1.0, dtype),
    )
    yield (
        "near_plane",
        small_camera(20, 16, dtype, eye=(0.0, -3.0, 0.3)),
        surfels_at([[0.0, -2.5, 0.0]], (0.0, 0.0, 1.0), 2.0, dtype),
    )
    # 40 layers on the central pixels: the surface set stops after ~13, the volume set after ~26
    n = 40
    means = torch.stack([torch.zeros(n), torch.linspace(-1.0, 1.0, n), torch.zeros(n)], 1)
    yield (
        "stack_40",
        small_camera(8, 8, dtype, eye=CAMERA_EYE),
        surfels_at(means, (0.0, 1.0, 0.0), 0.05, dtype, occupancy=0.5, opacity=0.6),
    )
    yield (
        "grazing",
        small_camera(16, 16, dtype, eye=CAMERA_EYE),
        surfels_at([[0.0, -2.0, 0.0]], (math.sin(math.pi / 2 - 1e-7), -math.cos(math.pi / 2 - 1e-7), 0.0), 0.5, dtype),
    )
    yield (
        "depth_1e4",
        small_camera(16, 16, dtype, eye=CAMERA_EYE),
        surfels_at([[0.0, 1e4, 0.0], [50.0, 1e4, 30.0]], (0.0, 1.0, 0.0), 500.0, dtype),
    )
    yield "empty", small_camera(20, 12, dtype), random_surfels(0, 0, dtype=dtype)


def _hard_cases(dtype):
    torch.manual_seed(0)  # surfels_at draws its features from the global generator
    scenes = list(_hard_scenes(dtype))
    return pytest.mark.parametrize("name,camera,surfels", scenes, ids=[h[0] for h in scenes])


@_hard_cases(torch.float64)
def test_hard_cases_float64(name, camera, surfels):
    parity(surfels, camera, F64_HARD)


def assert_transmittance_in_range(out) -> None:
    """alpha = 1 - T of both sets stays in [0, 1], and the distortion is not negative (as render_and_check)."""
    for name in ("alpha", "volume_alpha"):
        value = getattr(out, name)
        assert value.min() >= 0 and value.max() <= 1 + 1e-6, f"{name} outside [0,1]: transmittance < 0"
    assert (out.distortion >= -1e-6).all()


@_hard_cases(torch.float32)
def test_hard_cases_float32(name, camera, surfels):
    # parity also asserts that every output and gradient is finite
    if name not in ILL_CONDITIONED_FLOAT32:
        _, fast = parity(surfels, camera, F32)
    else:
        _, fast = parity(surfels, camera, F32_ILL)
        camera64 = {n: c for n, c, _ in _hard_scenes(torch.float64)}[name]
        # The scale gradient of a 1e4-scale surfel is ill-conditioned in float32: it is a sum of large
        # cancelling terms of the ray transform's gradient. The float32 reference errs by 0.8-1.2% of
        # its norm there and the triton kernels, which sum in float32 where the cpu kernels sum in
        # float64, by 2.2% (interpreter) to 3.3% (H200): bounded by 5% of the norm, not by the reference.
        as_accurate_as_reference(surfels, camera, camera64, floor=1e-3, floors={"scales": 0.05})
    assert_transmittance_in_range(fast)


@pytest.mark.parametrize("seed,scale,occupancy,opacity,distance,tilt", list(_extreme_mixtures(3)))
def test_extreme_mixtures_float32(seed, scale, occupancy, opacity, distance, tilt):
    """The first draws of the cpu tests' extreme mixtures, on 6 ordinary surfels instead of 12."""
    camera = small_camera(24, 16, torch.float32, eye=CAMERA_EYE)
    base = random_surfels(6, seed, dtype=torch.float32, spread=0.8, n_features=3)
    torch.manual_seed(seed)
    extreme = surfels_at(
        [[0.0, -3.0 + distance, 0.0]], (math.sin(tilt), -math.cos(tilt), 0.0), scale, occupancy=occupancy,
        opacity=opacity,
    )
    merged = Surfels(*[torch.cat([getattr(base, f), getattr(extreme, f)]) for f in SURFEL_FIELDS])
    _, fast = parity(merged, camera, F32)
    assert_transmittance_in_range(fast)


# -- densification signal, backend switch ------------------------------------------------------------


def test_densification_grad_matches_with_a_caller_probe():
    camera = small_camera(20, 16, torch.float32).to(DEVICE)
    surfels = surfels_to(random_surfels(8, 7, dtype=torch.float32, n_features=2), DEVICE)
    grads = {}
    for backend in ("reference", "triton"):
        s = with_grad(surfels)
        probe = torch.zeros(len(s), 2, device=DEVICE, requires_grad=True)
        out = rasterize(s, camera, backend=backend, screen_probe=probe)
        assert out.screen_probe is probe and out.densification_grad() is None
        (out.color.square().sum() + out.normal.sum() + out.depth.mean()).backward()
        grads[backend] = out.densification_grad()
    assert grads["triton"].abs().max() > 0
    assert_mostly_close(
        grads["triton"], grads["reference"], "densification", rtol=1e-3, atol=1e-4 * _scale(grads["reference"])
    )


def test_auto_picks_triton_on_cuda_and_cpu_on_cpu():
    assert default_backend(torch.device("cuda")) == "triton"
    assert default_backend(torch.device("cpu")) == "cpu"


@pytest.mark.skipif(ON_GPU, reason="with a CUDA device the bench runs instead")
def test_gpu_bench_exits_with_a_message_without_cuda(capsys):
    from rtsplat.bench import gpu

    assert gpu.main([]) == 2
    err = capsys.readouterr().err
    assert "needs a CUDA device" in err and "no CUDA device" in err


def test_without_the_interpreter_cpu_tensors_are_refused_and_import_loads_no_triton():
    result = _python(
        """
        import sys
        import torch
        import rtsplat.raster
        print('triton' in sys.modules)
        from raster_scenes import random_surfels, small_camera
        from rtsplat.raster import rasterize
        try:
            rasterize(random_surfels(4, 0, dtype=torch.float32), small_camera(16, 12, torch.float32), backend="triton")
        except ValueError as exc:
            print("refused:", exc)
        """,
        env={"TRITON_INTERPRET": "0"},
    )
    assert result.returncode == 0, result.stderr
    first, second = result.stdout.splitlines()[:2]
    assert first == "False"
    assert second.startswith("refused:") and "TRITON_INTERPRET=1" in second and "backend='cpu'" in second


def test_surfels_with_a_grad_free_parameter():
    # only some inputs require gradients: the backward returns None-free, finite gradients for those
    camera = small_camera(16, 16, torch.float64).to(DEVICE)
    surfels = surfels_to(random_surfels(6, 3, dtype=torch.float64), DEVICE)
    colors = surfels.colors.clone().requires_grad_(True)
    out = rasterize(replace(surfels, colors=colors), camera, backend="triton")
    ref_colors = surfels.colors.clone().requires_grad_(True)
    ref = rasterize(replace(surfels, colors=ref_colors), camera, backend="reference")
    out.color.sum().backward()
    ref.color.sum().backward()
    torch.testing.assert_close(colors.grad, ref_colors.grad, rtol=1e-9, atol=1e-12)

