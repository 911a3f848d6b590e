"""The G-buffer's surface values: the numba kernels (SurfaceValues) against the torch reference."""

import math

import pytest
import torch

from rtsplat.model.gbuffer import SurfaceValues, surface_values, surface_values_reference
from rtsplat.raster.numba_runtime import load_numba_module

pytestmark = pytest.mark.skipif(load_numba_module("rtsplat.model.gbuffer_kernels") is None, reason="needs numba")

LAYOUT = {"scatter": slice(0, 3), "tau": slice(3, 4), "roi": slice(4, 5), "opacity": slice(5, 6)}
CLAMPED = frozenset({"roi", "tau", "scatter"})


def _buffers(dtype, seed=0, h=11, w=13):
    """Blended channels [H,W,8] (two unread) and a surface alpha; some ratios fall outside [0, 1]. The channels are
    a slice of a wider image, as the rasterizer's output is."""
    g = torch.Generator().manual_seed(seed)
    alpha = (torch.rand(h, w, 1, generator=g, dtype=torch.float64) * 0.99 + 1e-6).to(dtype)
    image = (torch.rand(h, w, 10, generator=g, dtype=torch.float64) * 1.4 - 0.2).to(dtype)
    image[..., :8] *= alpha
    return image[..., :8].requires_grad_(), alpha.requires_grad_()


def _values_and_gradients(fn, features, alpha, names):
    features.grad = alpha.grad = None
    values = fn(features, alpha, LAYOUT, names, CLAMPED)
    g = torch.Generator().manual_seed(1)
    loss = sum((v * torch.randn(v.shape, generator=g, dtype=torch.float64).to(v.dtype)).sum() for v in values.values())
    loss.backward()
    return values, features.grad, alpha.grad


@pytest.mark.parametrize("names", [("roi",), ("roi", "opacity", "tau", "scatter"), ("scatter", "opacity")])
@pytest.mark.parametrize("dtype, tol", [(torch.float32, 1e-6), (torch.float64, 1e-13)])
def test_kernels_give_the_reference_values_bit_for_bit_and_its_gradients(names, dtype, tol):
    image, alpha = _buffers(dtype)
    features = image.detach().clone().requires_grad_()  # contiguous, and the strided slice itself
    for feats in (image, features):
        mine, my_features, my_alpha = _values_and_gradients(surface_values, feats, alpha, names)
        ref, ref_features, ref_alpha = _values_and_gradients(surface_values_reference, feats, alpha, names)
        assert list(mine) == list(names)
        for name in names:
            assert torch.equal(mine[name], ref[name]), name
        torch.testing.assert_close(my_features, ref_features, rtol=0, atol=0)  # the same division
        torch.testing.assert_close(my_alpha, ref_alpha, rtol=tol, atol=tol)  # the channels' sum: another order
    clamped = (features.detach()[..., :5] / alpha.detach() > 1) | (features.detach()[..., :5] < 0)
    assert clamped.any() and (~clamped).any()


def test_a_nan_stays_in_its_pixel():
    features, alpha = _buffers(torch.float32)
    with torch.no_grad():
        features[2, 3, 4] = math.nan
        alpha[5, 6, 0] = math.nan
    names = ("roi", "opacity")
    mine, my_features, my_alpha = _values_and_gradients(surface_values, features, alpha, names)
    ref, ref_features, ref_alpha = _values_and_gradients(surface_values_reference, features, alpha, names)
    for name in names:
        assert torch.equal(mine[name].isnan(), ref[name].isnan())
        torch.testing.assert_close(mine[name], ref[name], rtol=0, atol=0, equal_nan=True)
    assert torch.equal(my_features.isnan(), ref_features.isnan())
    assert torch.equal(my_alpha.isnan(), ref_alpha.isnan())
    # the NaN alpha's pixel, and the NaN feature's: the clamp stops its gradient, but the divisor's is 0 x NaN
    assert int(my_alpha.isnan().sum()) == 2 and bool(my_alpha[2, 3, 0].isnan()) and bool(my_alpha[5, 6, 0].isnan())


def test_other_float_types_take_the_reference(monkeypatch):
    called = []
    monkeypatch.setattr(SurfaceValues, "apply", lambda *a: called.append(1))
    features, alpha = (t.detach().to(torch.bfloat16) for t in _buffers(torch.float32))
    values = surface_values(features, alpha, LAYOUT, ("roi",), CLAMPED)
    assert not called and values["roi"].dtype == torch.bfloat16
