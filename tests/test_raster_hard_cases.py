"""Numerically hard inputs: every output and every gradient stays finite, and the
transmittance of both weight sets stays in [0, 1] (alpha = 1 - T never leaves [0, 1])."""

from __future__ import annotations

import math

import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from raster_scenes import SURFEL_FIELDS, facing_quat, random_surfels, replace, small_camera, with_grad

from rtsplat.raster import RasterOutput, Surfels, rasterize

IMAGE_OUTPUTS = (
    "features", "normal", "depth", "depth_median", "alpha", "distortion", "color", "volume_alpha",
    "volume_depth",
)


def render_and_check(surfels: Surfels, camera, backend: str = "reference") -> RasterOutput:
    """Render, backpropagate a random mix of every output, and check finiteness and bounds."""
    surfels = with_grad(surfels)
    out = rasterize(surfels, camera, backend=backend)
    g = torch.Generator().manual_seed(0)
    loss = 0.0
    for name in IMAGE_OUTPUTS:
        value = getattr(out, name)
        assert torch.isfinite(value).all(), f"{name} is not finite"
        loss = loss + (value * torch.rand(value.shape, generator=g, dtype=value.dtype)).sum()
    for name in ("alpha", "volume_alpha"):
        value = getattr(out, name)
        assert value.min() >= 0 and value.max() <= 1 + 1e-6, f"{name} outside [0,1]: transmittance < 0"
    assert (out.distortion >= -1e-6).all()
    if loss.requires_grad:
        loss.backward()
        for name in SURFEL_FIELDS:
            grad = getattr(surfels, name).grad
            assert grad is None or torch.isfinite(grad).all(), f"gradient of {name} is not finite"
        probe_grad = out.screen_probe.grad
        assert probe_grad is None or torch.isfinite(probe_grad).all()
    return out


def surfels_at(means, normal, scale, dtype=torch.float32, occupancy=1.0, opacity=1.0) -> Surfels:
    means = torch.as_tensor(means, dtype=dtype).reshape(-1, 3)
    n = means.shape[0]
    return Surfels(
        means=means,
        quats=facing_quat(normal, dtype).expand(n, 4).clone(),
        scales=torch.as_tensor(scale, dtype=dtype).expand(n, 2).clone(),
        occupancy=torch.full((n,), occupancy, dtype=dtype),
        opacity=torch.full((n,), opacity, dtype=dtype),
        features=torch.rand(n, 3, dtype=dtype),
        colors=torch.rand(n, 3, dtype=dtype),
    )


CAMERA_EYE = (0.0, -3.0, 0.0)  # looks along +y at the origin; the eye lies in the plane z = 0


@pytest.mark.parametrize("normal", [(1.0, 0.0, 0.0), (0.0, 0.0, 1.0)])
def test_edge_on_surfels_are_finite_and_still_visible_through_the_low_pass_filter(normal):
    # the surfel's plane contains the eye: rays through it are parallel to the plane; with an odd
    # image size the central pixel row/column lies exactly in that plane
    camera = small_camera(33, 33, torch.float32, eye=CAMERA_EYE)
    out = render_and_check(surfels_at([[0.0, 0.0, 0.0]], normal, 0.5), camera)
    assert out.alpha.max() > 0.1


@pytest.mark.parametrize("scale", [0.0, 1e-30, 1e4])
def test_zero_and_huge_scales(scale):
    camera = small_camera(32, 24, torch.float32)
    surfels = random_surfels(30, 1, dtype=torch.float32)
    surfels = replace(surfels, scales=torch.full_like(surfels.scales, scale))
    out = render_and_check(surfels, camera)
    assert out.alpha.max() > 0  # a zero-size surfel still covers its pixel through the filter


def test_mixed_zero_and_huge_scales_in_one_surfel():
    camera = small_camera(32, 24, torch.float32)
    surfels = random_surfels(20, 2, dtype=torch.float32)
    scales = torch.stack([torch.zeros(20), torch.full((20,), 1e4)], 1)
    render_and_check(replace(surfels, scales=scales), camera)


@pytest.mark.parametrize("occupancy", [0.0, 1.0])
@pytest.mark.parametrize("opacity", [0.0, 1.0])
def test_occupancy_and_opacity_exactly_zero_and_one(occupancy, opacity):
    camera = small_camera(32, 24, torch.float32)
    surfels = random_surfels(40, 3, dtype=torch.float32)
    surfels = replace(
        surfels,
        occupancy=torch.full_like(surfels.occupancy, occupancy),
        opacity=torch.full_like(surfels.opacity, opacity),
    )
    out = render_and_check(surfels, camera)
    if occupancy == 0.0:
        assert out.alpha.max() == 0 and out.volume_alpha.max() == 0
    if opacity == 0.0:
        assert out.volume_alpha.max() == 0
    if occupancy == 1.0 and opacity == 1.0:
        assert out.alpha.max() > 0.9


def test_surfels_behind_the_camera_contribute_nothing():
    camera = small_camera(32, 24, torch.float32, eye=CAMERA_EYE)
    behind = surfels_at([[0.0, -4.0, 0.0], [0.0, -3.1, 0.0], [0.0, -3.0, 0.0]], (0.0, 1.0, 0.0), 1.0)
    out = render_and_check(behind, camera)
    assert out.alpha.max() == 0 and out.volume_alpha.max() == 0
    assert not out.visible.any()
    assert (out.radii == 0).all()


def test_surfel_straddling_the_near_plane_is_clipped_per_pixel():
    # a large floor-like surfel under the camera, centre 0.5 ahead, reaching behind the eye
    camera = small_camera(32, 24, torch.float32, eye=(0.0, -3.0, 0.3))
    floor = surfels_at([[0.0, -2.5, 0.0]], (0.0, 0.0, 1.0), 2.0)
    out = render_and_check(floor, camera)
    assert out.alpha.max() > 0.5
    seen = out.alpha[..., 0] > 0
    assert (out.depth[..., 0][seen] >= 0.2 - 1e-5).all()  # nothing composited before the near plane


def test_ten_thousand_surfels_stacked_on_one_pixel():
    camera = small_camera(16, 16, torch.float32, eye=CAMERA_EYE)
    n = 10_000
    y = torch.linspace(-1.0, 1.0, n)
    means = torch.stack([torch.zeros(n), y, torch.zeros(n)], 1)
    stack = surfels_at(means, (0.0, 1.0, 0.0), 0.02, occupancy=0.5, opacity=0.3)
    out = render_and_check(stack, camera)
    centre = out.alpha[8, 8, 0]
    assert centre > 0.99  # the surface set saturates, early termination kicks in


def test_depths_of_ten_thousand():
    camera = small_camera(32, 24, torch.float32, eye=CAMERA_EYE)
    far = surfels_at([[0.0, 1e4, 0.0], [50.0, 1e4, 30.0]], (0.0, 1.0, 0.0), 500.0)
    out = render_and_check(far, camera)
    assert out.alpha.max() > 0.5
    assert abs(float(out.depth.detach()[12, 16, 0]) - (1e4 + 3.0)) < 1.0


def test_empty_scene():
    camera = small_camera(20, 12, torch.float32)
    empty = random_surfels(0, 0, dtype=torch.float32)
    out = render_and_check(empty, camera)
    assert out.color.shape == (12, 20, 3) and out.alpha.abs().max() == 0
    assert out.features.shape == (12, 20, 2)


EXTREME_SCALES = [0.0, 1e-6, 0.05, 0.5, 1e4]
EXTREME_PROBS = [0.0, 1e-6, 0.5, 1.0 - 1e-6, 1.0]


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    seed=st.integers(0, 10_000),
    scale=st.sampled_from(EXTREME_SCALES),
    occupancy=st.sampled_from(EXTREME_PROBS),
    opacity=st.sampled_from(EXTREME_PROBS),
    distance=st.sampled_from([-1.0, 0.0, 0.19, 0.2, 0.21, 3.0, 1e4]),
    tilt=st.sampled_from([0.0, math.pi / 2, math.pi / 2 - 1e-7, 1.0]),
)
def test_property_extreme_mixtures_stay_finite(seed, scale, occupancy, opacity, distance, tilt):
    """Random scenes mixing extreme values with ordinary surfels: finite everywhere, T in [0,1]."""
    camera = small_camera(24, 16, torch.float32, eye=CAMERA_EYE)
    base = random_surfels(12, seed, dtype=torch.float32, spread=0.8, n_features=3)
    # one extreme surfel on the optical axis at `distance` in front of the eye, tilted by `tilt`
    extreme = surfels_at([[0.0, -3.0 + distance, 0.0]], (math.sin(tilt), -math.cos(tilt), 0.0), scale,
                         occupancy=occupancy, opacity=opacity)
    merged = Surfels(*[torch.cat([getattr(base, f), getattr(extreme, f)]) for f in SURFEL_FIELDS])
    render_and_check(merged, camera)


NOTHING_VISIBLE = {
    # name: (surfel centres, normal, scale) for the camera at CAMERA_EYE looking along +y
    "all behind the camera": ([[0.0, -4.0, 0.0], [0.5, -3.5, 0.2]], (0.0, 1.0, 0.0), 1.0),
    "at the camera centre": ([[0.0, -3.0, 0.0]], (0.0, 1.0, 0.0), 0.5),
    "inside the near plane": ([[0.0, -2.9, 0.0], [0.05, -2.85, 0.0]], (0.0, 1.0, 0.0), 0.01),
    "camera inside the surfel": ([[0.0, -3.0, 0.0]], (0.0, 0.0, 1.0), 2.0),
}


@pytest.mark.parametrize("case", sorted(NOTHING_VISIBLE))
def test_nothing_visible_gives_zeros_that_backpropagate(case):
    """Every surfel culled: both backends return zero images whose backward pass runs and gives zero
    gradients (the training loss stays differentiable on such a view)."""
    means, normal, scale = NOTHING_VISIBLE[case]
    camera = small_camera(32, 24, torch.float32, eye=CAMERA_EYE)
    base = surfels_at(means, normal, scale)
    grads = {}
    for backend in ("reference", "cpu"):
        surfels = with_grad(base)
        out = rasterize(surfels, camera, backend=backend)
        assert not out.visible.any()
        for name in IMAGE_OUTPUTS:
            assert getattr(out, name).abs().max() == 0, f"{backend}: {name} is not zero"
        loss = sum(getattr(out, name).sum() for name in IMAGE_OUTPUTS)
        loss.backward()  # must not raise
        grads[backend] = {name: getattr(surfels, name).grad for name in SURFEL_FIELDS}
        for name, grad in grads[backend].items():
            assert grad is None or (grad == 0).all(), f"{backend}: gradient of {name} is not zero"
    for name in SURFEL_FIELDS:  # the same (zero) gradients from both
        ref, cpu = grads["reference"][name], grads["cpu"][name]
        assert ref is not None and ref.shape == getattr(base, name).shape
        assert cpu is None or torch.equal(ref.abs(), cpu.abs())
