"""The learned background's lookup on the CPU (numba kernels, ``BackgroundLookup``) against its torch reference
(``BackgroundMap.logits_reference``): the same values bit for bit, with and without autograd, and the gradients of
the levels and the directions, at the poles and the longitude seam too; a non-finite direction spoils only its
own sample."""

from __future__ import annotations

import pytest
import torch
import torch.nn.functional as F

from rtsplat.model.background import BackgroundLookup, BackgroundMap
from rtsplat.model.envmap import EnvironmentMap

pytest.importorskip("numba")


def _background(height: int, width: int, levels: int, dtype, seed: int = 0) -> BackgroundMap:
    background = BackgroundMap(height, width, levels).to(dtype)
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for level in background.maps:
            level.copy_(torch.randn(level.shape, generator=g, dtype=dtype))
    return background


def _directions(n: int, dtype, seed: int = 1) -> torch.Tensor:
    directions = F.normalize(torch.randn(n, 3, generator=torch.Generator().manual_seed(seed), dtype=dtype), dim=-1)
    directions[:5] = torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.0, -1.0], [-1.0, 0.0, 0.0], [-1.0, -1e-7, 0.0],
                                   [-1.0, 1e-7, 0.0]], dtype=dtype)  # the poles and both sides of the seam
    return directions


def _lookup(background: BackgroundMap, directions: torch.Tensor, by_kernel: bool):
    """The logits and the gradients of (every level, the directions) of one weighted sum of them."""
    for level in background.maps:
        level.grad = None
    d = directions.clone().requires_grad_()
    u, v = EnvironmentMap.direction_to_uv(d)
    if by_kernel:
        out = background._logits_by_kernel(u, v)
        assert type(out.grad_fn).__name__ == "BackgroundLookupBackward"
    else:
        out = background.logits_reference(u, v)
    weights = torch.linspace(-1, 1, out.numel(), dtype=out.dtype).reshape(out.shape)
    (out * weights).sum().backward()
    return out.detach(), [level.grad.clone() for level in background.maps], d.grad


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("height,width,levels", [(16, 32, 4), (9, 22, 3), (4, 8, 1)])
def test_the_kernels_give_the_values_and_gradients_of_the_torch_lookup(dtype, height, width, levels):
    background = _background(height, width, levels, dtype)
    directions = _directions(500, dtype)
    values, level_grads, direction_grad = _lookup(background, directions, by_kernel=True)
    ref_values, ref_level_grads, ref_direction_grad = _lookup(background, directions, by_kernel=False)
    assert torch.equal(values, ref_values) and values.std() > 0.1
    with torch.no_grad():
        assert torch.equal(background._logits_by_kernel(*EnvironmentMap.direction_to_uv(directions)), ref_values)
    tolerance = dict(rtol=1e-5, atol=1e-5) if dtype == torch.float32 else dict(rtol=1e-10, atol=1e-10)
    for actual, expected in zip(level_grads, ref_level_grads, strict=True):
        assert expected.abs().max() > 0
        torch.testing.assert_close(actual, expected, **tolerance)
    assert ref_direction_grad.abs().max() > 0
    torch.testing.assert_close(direction_grad, ref_direction_grad, **tolerance)


def test_gradcheck_of_the_lookup_kernel_in_float64():
    background = _background(6, 10, 2, torch.float64)
    directions = _directions(40, torch.float64, seed=3)
    u, v = EnvironmentMap.direction_to_uv(directions[5:])  # away from the poles, where v is clamped
    levels = [level.detach().clone().requires_grad_() for level in background.maps]
    assert torch.autograd.gradcheck(BackgroundLookup.apply, (u.clone().requires_grad_(), v.clone().requires_grad_(),
                                                             *levels))


def test_a_non_finite_direction_spoils_only_its_own_sample():
    background = _background(8, 16, 3, torch.float32)
    directions = _directions(50, torch.float32)
    directions[7] = torch.tensor([float("nan"), 0.0, 1.0])
    directions[9] = torch.tensor([0.0, float("nan"), 0.0])
    values, level_grads, direction_grad = _lookup(background, directions, by_kernel=True)
    bad = torch.zeros(50, dtype=torch.bool)
    bad[[7, 9]] = True
    assert values[bad].isnan().all() and values[~bad].isfinite().all()
    assert all(g.isfinite().all() for g in level_grads)
    assert direction_grad[~bad].isfinite().all()


def test_an_empty_lookup_gives_empty_logits_and_gradients():
    background = _background(8, 16, 2, torch.float32)
    values, level_grads, direction_grad = _lookup(background, torch.zeros(0, 3), by_kernel=True)
    assert values.shape == (0, 3) and direction_grad.shape == (0, 3)
    assert all((g == 0).all() for g in level_grads)


def test_without_a_sample_gradient_the_levels_get_theirs_as_with_one():
    """Directions without autograd (fixed cameras): the lookup keeps no derivatives of the samples, and the levels'
    gradients are those of the torch lookup."""
    background = _background(16, 32, 3, torch.float32)
    u, v = EnvironmentMap.direction_to_uv(_directions(300, torch.float32))
    grads = []
    for by_kernel in (True, False):
        background.zero_grad()
        out = background._logits_by_kernel(u, v) if by_kernel else background.logits_reference(u, v)
        (out * torch.linspace(-1, 1, out.numel()).reshape(out.shape)).sum().backward()
        grads.append([level.grad.clone() for level in background.maps])
    assert not u.requires_grad
    for actual, expected in zip(*grads, strict=True):
        assert expected.abs().max() > 0
        torch.testing.assert_close(actual, expected, rtol=1e-5, atol=1e-5)
