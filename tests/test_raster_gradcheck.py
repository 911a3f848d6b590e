"""float64 gradcheck of every rasterizer output with respect to every surfel parameter."""

from __future__ import annotations

import pytest
import torch
from raster_scenes import SURFEL_FIELDS, random_surfels, small_camera

from rtsplat.raster import RasterSettings, Surfels, rasterize

OUTPUTS = (
    "features", "normal", "depth", "depth_median", "alpha", "distortion", "color", "volume_alpha",
    "volume_depth",
)


def _inputs(seed: int):
    surfels = random_surfels(6, seed, spread=0.35, scale_range=(0.15, 0.4))
    params = [getattr(surfels, f).clone().requires_grad_(True) for f in SURFEL_FIELDS]
    probe = torch.zeros(len(surfels), 2, dtype=torch.float64, requires_grad=True)
    return params, probe


@pytest.mark.parametrize("output", OUTPUTS)
@pytest.mark.parametrize("seed", [0, 1])
def test_gradcheck_every_output(output, seed):
    camera = small_camera(width=20, height=14)
    settings = RasterSettings(tile_size=8)
    params, probe = _inputs(seed)

    def render(*tensors):
        *fields, screen_probe = tensors
        out = rasterize(Surfels(*fields), camera, settings, backend="reference", screen_probe=screen_probe)
        return getattr(out, output)

    value = render(*params, probe)
    assert value.abs().max() > 0, f"{output} is empty for this scene"
    assert torch.autograd.gradcheck(render, (*params, probe), eps=1e-6, atol=1e-5, rtol=1e-4, fast_mode=True)


def test_gradients_reach_every_parameter():
    camera = small_camera(width=20, height=14)
    params, probe = _inputs(0)
    out = rasterize(Surfels(*params), camera, backend="reference", screen_probe=probe)
    loss = sum(getattr(out, name).sum() for name in OUTPUTS)
    loss.backward()
    for name, p in zip(SURFEL_FIELDS, params, strict=True):
        assert p.grad is not None and p.grad.abs().sum() > 0, f"no gradient reaches {name}"
    signal = out.densification_grad()
    assert signal is not None and signal.shape == (6, 2) and signal.abs().sum() > 0
    # the signal is the pixel-space centre gradient scaled to NDC units, as in 2DGS
    torch.testing.assert_close(signal, probe.grad * torch.tensor([10.0, 7.0], dtype=torch.float64))


@pytest.mark.parametrize("output", ["color", "distortion", "depth"])
def test_gradcheck_full_jacobian_on_a_tiny_image(output):
    """Without fast_mode: every column of the Jacobian, on a 10x8 image."""
    camera = small_camera(width=10, height=8)
    params, probe = _inputs(2)

    def render(*tensors):
        *fields, screen_probe = tensors
        out = rasterize(Surfels(*fields), camera, RasterSettings(tile_size=4), backend="reference",
                        screen_probe=screen_probe)
        return getattr(out, output)

    assert render(*params, probe).abs().max() > 0
    assert torch.autograd.gradcheck(render, (*params, probe), eps=1e-6, atol=1e-5, rtol=1e-4)
