"""The specular pass's per-pixel inputs: the numba kernels (SpecularInputs) against the torch reference."""

import math

import pytest
import torch
import torch.nn.functional as F

from rtsplat.model.specular_inputs import SpecularInputs, specular_inputs, specular_inputs_reference
from rtsplat.raster.numba_runtime import load_numba_module

pytestmark = pytest.mark.skipif(load_numba_module("rtsplat.model.specular_inputs_kernels") is None,
                                reason="needs numba")


def _buffers(h=9, w=7, dtype=torch.float64, seed=0):
    """Rays, normals (unit), blended roughness / material / reflectance and alpha: leaves with gradients. Some
    ratios of a channel to alpha fall below 0 or above 1, where the clamps cut the gradient."""
    g = torch.Generator().manual_seed(seed)

    def rand(*shape):
        return torch.rand(h, w, *shape, generator=g, dtype=torch.float64)

    rays = F.normalize(torch.randn(h, w, 3, generator=g, dtype=torch.float64), dim=-1).to(dtype)
    normal = F.normalize(torch.randn(h, w, 3, generator=g, dtype=torch.float64), dim=-1)
    alpha = rand(1) * 0.9 + 0.1
    leaves = [normal, (rand(1) * 1.4 - 0.2) * alpha, torch.randn(h, w, 4, generator=g, dtype=torch.float64),
              (rand(1) * 1.4 - 0.2) * alpha, alpha]
    return [rays] + [t.to(dtype).requires_grad_() for t in leaves]


def _outputs_and_gradients(fn, buffers, idx, seed=1):
    rays, *leaves = buffers
    for t in leaves:
        t.grad = None
    outputs = fn(rays, *leaves, idx)
    g = torch.Generator().manual_seed(seed)
    loss = sum((o * torch.randn(o.shape, generator=g, dtype=torch.float64).to(o.dtype)).sum() for o in outputs)
    loss.backward()
    return [o.detach() for o in outputs], [t.grad for t in leaves]


@pytest.mark.parametrize("dtype, tol", [(torch.float64, 1e-12), (torch.float32, 2e-5)])
@pytest.mark.parametrize("every_pixel", [False, True])
def test_kernels_give_the_reference_values_and_gradients(dtype, tol, every_pixel):
    buffers = _buffers(dtype=dtype)
    idx = None if every_pixel else torch.tensor([0, 5, 6, 11, 40, 62, 17])
    mine, my_grads = _outputs_and_gradients(specular_inputs, buffers, idx)
    ref, ref_grads = _outputs_and_gradients(specular_inputs_reference, buffers, idx)
    for a, b in zip(mine, ref, strict=True):
        assert a.dtype == b.dtype and a.shape == b.shape
        torch.testing.assert_close(a, b, rtol=tol, atol=tol)
    for a, b in zip(my_grads, ref_grads, strict=True):
        assert a.shape == b.shape
        torch.testing.assert_close(a, b, rtol=tol, atol=tol)
    clamped = ((buffers[2] / buffers[5]).detach() > 1) | ((buffers[2] / buffers[5]).detach() < 0)
    assert clamped.any() and (~clamped).any()  # both sides of the clamp were exercised


def test_pixels_outside_the_rows_get_no_gradient():
    buffers = _buffers()
    idx = torch.tensor([3, 8, 20])
    _, grads = _outputs_and_gradients(specular_inputs, buffers, idx)
    others = torch.ones(63, dtype=torch.bool)
    others[idx] = False
    for grad in grads:
        flat = grad.reshape(63, -1)
        assert torch.equal(flat[others], torch.zeros_like(flat[others]))
        assert flat[idx].abs().sum() > 0


def test_kinks_follow_torch_head_on_grazing_and_a_zero_material():
    """A ray along the normal (|cos| exactly at the clamp's end, 1), one in the surface (cos 0: abs's kink) and a
    zero material feature (its norm below normalize's epsilon): the reference's values and gradients."""
    buffers = _buffers(h=1, w=3)
    rays, normal, _, material, _, _ = buffers
    with torch.no_grad():
        rays[0, 0] = normal[0, 0]
        tangent = torch.linalg.cross(normal[0, 1], torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64))
        rays[0, 1] = F.normalize(tangent, dim=-1)
        material[0, 2] = 0.0
    mine, my_grads = _outputs_and_gradients(specular_inputs, buffers, None)
    ref, ref_grads = _outputs_and_gradients(specular_inputs_reference, buffers, None)
    assert float(mine[1][0]) == pytest.approx(1.0) and abs(float(mine[1][1])) < 1e-15
    for a, b in zip(mine + my_grads, ref + ref_grads, strict=True):
        torch.testing.assert_close(a, b, rtol=1e-12, atol=1e-12)


def test_a_nan_spoils_its_own_pixel_only():
    buffers = _buffers()
    with torch.no_grad():
        buffers[1][2, 3, 0] = math.nan
    outputs, grads = _outputs_and_gradients(specular_inputs, buffers, None)
    bad = 2 * 7 + 3
    for o in outputs[:2]:  # the reflected direction and |cos| read the normal
        rows = o.reshape(63, -1)
        assert torch.isnan(rows[bad]).all() and not torch.isnan(torch.cat([rows[:bad], rows[bad + 1:]])).any()
    normal_grad = grads[0].reshape(63, 3)
    assert torch.isnan(normal_grad[bad]).all()
    assert torch.isfinite(torch.cat([normal_grad[:bad], normal_grad[bad + 1:]])).all()


def test_other_float_types_take_the_reference(monkeypatch):
    called = []
    monkeypatch.setattr(SpecularInputs, "apply", lambda *a: called.append(1))
    buffers = [t.detach().to(torch.bfloat16) for t in _buffers(h=2, w=2)]
    out = specular_inputs(*buffers, None)
    assert not called and out.reflected.dtype == torch.bfloat16
