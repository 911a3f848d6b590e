"""The environment map's trilinear lookup on the CPU (numba kernels, ``TrilinearLookup``) against its torch
reference (``EnvironmentMap.lookup_reference``): values and the gradients of the map, the directions and the
roughness, at the poles, the longitude seam and the levels' ends too; hard cases stay finite."""

from __future__ import annotations

import pytest
import torch
import torch.nn.functional as F

from rtsplat.model.envmap import EnvironmentMap, MipLookup, TrilinearLookup

pytest.importorskip("numba")


def _map(channels: int, height: int, width: int, levels: int, dtype, seed: int = 0) -> EnvironmentMap:
    env = EnvironmentMap(channels, height, width, levels).to(dtype)
    with torch.no_grad():
        env.features.copy_(torch.randn(env.features.shape, generator=torch.Generator().manual_seed(seed), dtype=dtype))
    return env


def _samples(levels: int, n: int, dtype, seed: int = 1) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    directions = F.normalize(torch.randn(n, 3, generator=g, dtype=dtype), dim=-1)
    directions[:5] = torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.0, -1.0], [-1.0, 0.0, 0.0], [-1.0, -1e-7, 0.0],
                                   [-1.0, 1e-7, 0.0]], dtype=dtype)  # the poles and both sides of the seam
    roughness = torch.rand(n, generator=g, dtype=dtype)
    roughness[:6] = torch.tensor([0.0, 1.0, 0.5, 1.0 / (levels - 1), 0.999, 1.0 - 1.0 / (levels - 1)], dtype=dtype)
    return directions, roughness


def _lookup(env: EnvironmentMap, directions, roughness, by_kernel: bool):
    """Values and the gradients of (features, directions, roughness) of one weighted sum of the lookup."""
    env.features.grad = None
    d = directions.clone().requires_grad_()
    r = roughness.clone().requires_grad_()
    table = env.texel_table()[0]
    u, v = env.direction_to_uv(d)
    level = (r.clamp(0, 1) * (env.levels - 1)).reshape(-1)
    if by_kernel:
        assert TrilinearLookup.applies(table, u, v, level)
        out = TrilinearLookup.apply(table, u, v, level, env.level_layout)
    else:
        out = env.lookup_reference(table, u, v, level)
    weights = torch.linspace(-1, 1, out.numel(), dtype=out.dtype).reshape(out.shape)
    (out * weights).sum().backward()
    return out.detach(), env.features.grad.clone(), d.grad, r.grad


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("channels,height,width,levels", [(3, 16, 32, 5), (16, 9, 22, 4), (1, 4, 8, 5)])
def test_the_kernels_give_the_values_and_gradients_of_the_torch_lookup(dtype, channels, height, width, levels):
    env = _map(channels, height, width, levels, dtype)
    directions, roughness = _samples(levels, 400, dtype)
    fast = _lookup(env, directions, roughness, by_kernel=True)
    reference = _lookup(env, directions, roughness, by_kernel=False)
    tolerance = dict(rtol=1e-5, atol=1e-5) if dtype == torch.float32 else dict(rtol=1e-10, atol=1e-10)
    for name, actual, expected in zip(("values", "features", "directions", "roughness"), fast, reference,
                                      strict=True):
        assert actual.abs().max() > 0, name
        torch.testing.assert_close(actual, expected, **tolerance, msg=lambda m, name=name: f"{name}: {m}")


def test_a_map_forward_on_the_cpu_runs_the_kernels_with_and_without_autograd(monkeypatch):
    env = _map(4, 8, 16, 3, torch.float32)
    directions, roughness = _samples(3, 50, torch.float32)
    calls = []
    for cls in (TrilinearLookup, MipLookup):
        original = cls.forward
        monkeypatch.setattr(cls, "forward", staticmethod(
            lambda *a, cls=cls, original=original: calls.append(cls.__name__) or original(*a)))
    with_grad = env(directions, roughness)
    with torch.no_grad():
        without = env(directions, roughness)
    assert calls == ["MipLookup", "TrilinearLookup"] and torch.equal(with_grad.detach(), without)


def _by_table_and_from_the_map(env, directions, roughness):
    """Values and gradients (features, directions, roughness) of one weighted sum of the lookup, through the texel
    table (MipTable then TrilinearLookup) and straight from the map (MipLookup)."""
    results = []
    for table in (True, False):
        env.features.grad = None
        d = directions.clone().requires_grad_()
        r = roughness.clone().requires_grad_()
        out = env(d, r, env.texel_table()[0] if table else None)
        weights = torch.linspace(-1, 1, out.numel(), dtype=out.dtype).reshape(out.shape)
        (out * weights).sum().backward()
        results.append((out.detach(), env.features.grad.clone(), d.grad, r.grad))
    return results


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("channels,height,width,levels,top", [
    (3, 16, 32, 5, 1.0), (16, 9, 22, 4, 1.0), (1, 4, 8, 5, 1.0),  # odd sizes; levels below 2x4 repeat the last
    (16, 32, 64, 7, 0.15), (4, 8, 16, 3, 0.0),  # only the first levels read (the first alone at roughness 0)
])
@pytest.mark.parametrize("channels_last", [True, False])
def test_the_lookup_from_the_map_is_the_lookup_through_the_table_bit_for_bit(dtype, channels, height, width,
                                                                             levels, top, channels_last):
    env = _map(channels, height, width, levels, dtype)
    if not channels_last:
        env.features = torch.nn.Parameter(env.features.detach().contiguous())
    directions, roughness = _samples(levels, 300, dtype)
    roughness = roughness * top
    by_table, from_map = _by_table_and_from_the_map(env, directions, roughness)
    for name, a, b in zip(("values", "features", "directions", "roughness"), from_map, by_table, strict=True):
        assert torch.equal(a, b), name
    assert from_map[1].abs().sum() > 0


def test_hard_samples_stay_finite_and_a_bad_one_spoils_only_itself():
    """A NaN direction gives NaN for its own sample and no index error; the other samples' values and every
    gradient of the map stay finite, at the last level (roughness 1) and past the ends of the roughness too."""
    env = _map(3, 8, 16, 4, torch.float32)
    directions, roughness = _samples(4, 20, torch.float32)
    directions[7] = float("nan")
    roughness[8:11] = torch.tensor([1.0, -3.0, 7.0])
    d = directions.clone().requires_grad_()
    r = roughness.clone().requires_grad_()
    out = env(d, r)
    assert torch.isnan(out[7]).all()
    others = torch.arange(20) != 7
    assert torch.isfinite(out[others]).all()
    out[others].sum().backward()
    assert torch.isfinite(env.features.grad).all() and env.features.grad.abs().sum() > 0
    assert torch.isfinite(d.grad[others]).all() and torch.isfinite(r.grad[others]).all()
    assert r.grad[9] == 0 and r.grad[10] == 0  # clamped roughness: no gradient, as in torch's clamp


def test_an_empty_lookup_gives_an_empty_result_and_gradient():
    env = _map(3, 8, 16, 4, torch.float32)
    d = torch.zeros(0, 3, requires_grad=True)
    out = env(d, torch.zeros(0))
    assert out.shape == (0, 3)
    out.sum().backward()
    assert d.grad.shape == (0, 3)
