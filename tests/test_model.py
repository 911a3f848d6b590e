"""Model components: environment map, specular network, gating, ablation switches, effects."""

from __future__ import annotations

import dataclasses
import math

import pytest
import torch
from raster_scenes import small_camera

from rtsplat.camera import camera_from_fov
from rtsplat.model import rtmodel, specular
from rtsplat.model.background import BackgroundMap
from rtsplat.model.checkpoint import CheckpointError, read_checkpoint, write_checkpoint
from rtsplat.model.envmap import EnvironmentMap, mip_levels
from rtsplat.model.gating import gate_factor, gate_gradient, specular_complexity
from rtsplat.model.rtmodel import GBUFFER_WIDTHS, STAGES, ActiveEffects, RTModel
from rtsplat.model.settings import Ablations, Gating, ModelSettings
from rtsplat.model.sh import eval_sh, rgb_to_sh_dc
from rtsplat.model.specular import SpecularNetwork, bucketed_rows
from rtsplat.model.surfels import init_from_points
from rtsplat.raster import RasterSettings
from rtsplat.train.effects import decide_effects
from rtsplat.train_config import Effects

SMALL = ModelSettings(env_height=16, env_width=32, env_levels=3, mlp_width=32)


def test_sh_degree_zero_reproduces_the_point_colour():
    rgb = torch.rand(10, 3)
    coeffs = torch.zeros(10, 16, 3)
    coeffs[:, 0] = rgb_to_sh_dc(rgb)
    torch.testing.assert_close(eval_sh(coeffs, torch.nn.functional.normalize(torch.randn(10, 3), dim=-1), 3), rgb)


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_sh_kernels_give_the_torch_references_colours_and_gradients(degree, dtype):
    from rtsplat.model.sh import eval_sh_reference

    generator = torch.Generator().manual_seed(degree)
    n = 400
    coefficients = (torch.randn(n, 16, 3, generator=generator, dtype=dtype) * 0.5).requires_grad_(True)
    directions = torch.nn.functional.normalize(torch.randn(n, 3, generator=generator, dtype=dtype), dim=-1)
    directions.requires_grad_(True)
    grad_colour = torch.randn(n, 3, generator=generator, dtype=dtype)

    fast = eval_sh(coefficients, directions, degree)
    assert type(fast.grad_fn).__name__.startswith("_ShColour")  # the numba kernels, not the reference
    reference = eval_sh_reference(coefficients, directions, degree)
    fast_grads = torch.autograd.grad(fast, [coefficients, directions], grad_colour)
    reference_grads = torch.autograd.grad(reference, [coefficients, directions], grad_colour, allow_unused=True)
    reference_grads = [torch.zeros_like(t) if g is None else g
                       for g, t in zip(reference_grads, (coefficients, directions), strict=True)]

    tolerance = dict(rtol=1e-12, atol=1e-12) if dtype == torch.float64 else dict(rtol=1e-5, atol=2e-6)
    if degree > 0:
        assert 0.01 < float((reference == 0).float().mean()) < 0.5  # some colours are clamped at 0
    torch.testing.assert_close(fast, reference, **tolerance)
    for name, actual, expected in zip(("coefficients", "directions"), fast_grads, reference_grads, strict=True):
        torch.testing.assert_close(actual, expected, **tolerance, msg=lambda m, name=name: f"{name}: {m}")
    k = (degree + 1) ** 2
    assert not fast_grads[0][:, k:].any()  # no gradient for the coefficients beyond the degree


def test_sh_colour_of_the_parts_is_the_colour_of_the_joined_coefficients():
    """The surfels keep the DC and the higher coefficients apart; the kernels read them so, and give the joined
    tensor's colour and gradients bit for bit."""
    from rtsplat.model.sh import eval_sh_parts

    generator = torch.Generator().manual_seed(7)
    dc = torch.randn(300, 1, 3, generator=generator).requires_grad_(True)
    rest = (torch.randn(300, 15, 3, generator=generator) * 0.3).requires_grad_(True)
    directions = torch.nn.functional.normalize(torch.randn(300, 3, generator=generator), dim=-1).requires_grad_(True)
    grad_colour = torch.randn(300, 3, generator=generator)
    parts = eval_sh_parts(dc, rest, directions, 3)
    assert type(parts.grad_fn).__name__.startswith("_ShColour")
    parts_grads = torch.autograd.grad(parts, [dc, rest, directions], grad_colour)
    joined_input = torch.cat([dc, rest], 1)
    joined = eval_sh(joined_input, directions, 3)
    joined_grads = torch.autograd.grad(joined, [joined_input, directions], grad_colour)
    assert torch.equal(parts, joined)
    assert torch.equal(torch.cat(parts_grads[:2], 1), joined_grads[0])
    assert torch.equal(parts_grads[2], joined_grads[1]) and parts_grads[2].abs().max() > 0


def test_environment_map_wraps_around_in_longitude():
    env = EnvironmentMap(channels=2, height=8, width=16, levels=3)
    with torch.no_grad():
        env.features.normal_()
    eps = 1e-4
    # just either side of the seam at phi = +-pi (direction -x)
    a = torch.tensor([[-1.0, eps, 0.0], [-1.0, -eps, 0.0]])
    a = torch.nn.functional.normalize(a, dim=-1)
    out = env(a, torch.zeros(2))
    torch.testing.assert_close(out[0], out[1], atol=1e-2, rtol=0)
    # and across the seam the value is the blend of the first and last columns
    col_first, col_last = env.features[0, :, 4, 0], env.features[0, :, 4, -1]
    mid = env(torch.tensor([[-1.0, 0.0, 0.0]]), torch.zeros(1))[0]
    v = math.acos(0.0) / math.pi * 8 - 0.5  # row coordinate of the equator: between rows 3 and 4
    expected_row4 = 0.5 * (col_first + col_last)
    row3 = 0.5 * (env.features[0, :, 3, 0] + env.features[0, :, 3, -1])
    torch.testing.assert_close(mid, row3 + (v - 3) * (expected_row4 - row3), atol=1e-5, rtol=1e-5)


def test_environment_map_roughness_selects_blurrier_levels():
    env = EnvironmentMap(channels=1, height=16, width=32, levels=3)
    with torch.no_grad():
        env.features.normal_()
    dirs = torch.nn.functional.normalize(torch.randn(500, 3), dim=-1)
    sharp = env(dirs, torch.zeros(500))
    blurry = env(dirs, torch.ones(500))
    assert blurry.std() < 0.6 * sharp.std()


def _env_lookup_by_hand(env: EnvironmentMap, direction, roughness: float) -> torch.Tensor:
    """One sample, spelled out: the two mip levels around roughness x (levels - 1), each bilinear
    with wrapped columns and clamped rows, blended linearly."""
    levels = [t[0] for t in env.pyramid()]
    x, y, z = (float(c) for c in direction)
    u = (math.atan2(y, x) + math.pi) / (2 * math.pi)
    v = math.acos(min(max(z, -1 + 1e-6), 1 - 1e-6)) / math.pi
    level = min(max(roughness, 0.0), 1.0) * (len(levels) - 1)
    lo = min(int(math.floor(level)), len(levels) - 1)
    out = torch.zeros(levels[0].shape[0], dtype=torch.float64)
    for index, weight in ((lo, 1 - (level - lo)), (lo + 1, level - lo)):
        if index >= len(levels) or weight == 0:
            continue
        tex = levels[index].double()
        H, W = tex.shape[1:]
        px, py = u * W - 0.5, v * H - 0.5
        x0, y0 = math.floor(px), math.floor(py)
        for dy, wy in ((0, 1 - (py - y0)), (1, py - y0)):
            for dx, wx in ((0, 1 - (px - x0)), (1, px - x0)):
                row = min(max(y0 + dy, 0), H - 1)
                out += weight * wy * wx * tex[:, row, (x0 + dx) % W]
    return out


@pytest.mark.parametrize("height,width,levels", [(16, 32, 4), (12, 20, 3), (4, 8, 5)])
def test_environment_map_matches_a_per_sample_trilinear_lookup(height, width, levels):
    env = EnvironmentMap(channels=3, height=height, width=width, levels=levels)
    g = torch.Generator().manual_seed(height)
    with torch.no_grad():
        env.features.copy_(torch.randn(env.features.shape, generator=g))
    dirs = torch.nn.functional.normalize(torch.randn(40, 3, generator=g), dim=-1)
    dirs[:4] = torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.0, -1.0], [-1.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
    rough = torch.rand(40, generator=g)
    rough[:6] = torch.tensor([0.0, 1.0, 0.5, 1.0 / (levels - 1), 0.999, 0.0])
    got = env(dirs, rough)
    for k in range(40):
        want = _env_lookup_by_hand(env, dirs[k], float(rough[k]))
        torch.testing.assert_close(got[k].double(), want, rtol=1e-5, atol=1e-5)


def test_single_level_sample_matches_the_by_hand_bilinear_lookup():
    """``sample_level`` (the background map's lookup) is the roughness-0 lookup of that level."""
    env = EnvironmentMap(channels=3, height=12, width=20, levels=2)
    g = torch.Generator().manual_seed(5)
    with torch.no_grad():
        env.features.copy_(torch.randn(env.features.shape, generator=g))
    dirs = torch.nn.functional.normalize(torch.randn(30, 3, generator=g), dim=-1)
    dirs[:3] = torch.tensor([[0.0, 0.0, 1.0], [-1.0, 1e-4, 0.0], [-1.0, -1e-4, 0.0]])
    u, v = EnvironmentMap.direction_to_uv(dirs)
    got = EnvironmentMap.sample_level(env.features, u, v)
    for k in range(30):
        torch.testing.assert_close(got[k].double(), _env_lookup_by_hand(env, dirs[k], 0.0), rtol=1e-5, atol=1e-5)


def test_lookups_without_autograd_give_the_values_of_the_autograd_lookups():
    """The background's single-level samples and the specular network (more rows than one inference slice)
    take other code paths without autograd (rtsplat render, the viewer); their values are the same bits."""
    g = torch.Generator().manual_seed(8)
    level = torch.randn(1, 3, 16, 32, generator=g).requires_grad_()
    dirs = torch.nn.functional.normalize(torch.randn(5000, 3, generator=g), dim=-1)
    u, v = EnvironmentMap.direction_to_uv(dirs)
    with_grad = EnvironmentMap.sample_level(level, u, v)
    assert with_grad.requires_grad
    with torch.inference_mode():
        assert torch.equal(EnvironmentMap.sample_level(level, u, v), with_grad.detach())

    rows = specular.INFERENCE_ROWS + 123
    net = SpecularNetwork(16, 4, 32)
    material = torch.nn.functional.normalize(torch.randn(rows, 4, generator=g), dim=-1)
    inputs = (torch.randn(rows, 16, generator=g), material, torch.rand(rows, 1, generator=g))
    spec, beta = net(*inputs)
    assert spec.requires_grad
    with torch.no_grad():
        spec_ng, beta_ng = net(*inputs)
    assert torch.equal(spec_ng, spec.detach()) and torch.equal(beta_ng, beta.detach())


@pytest.mark.parametrize("channels,dtype", [(1, torch.float32), (4, torch.float32), (16, torch.float32),
                                            (17, torch.float64)])
def test_environment_lookup_without_autograd_gives_the_values_of_the_autograd_lookup(channels, dtype):
    """The trilinear lookup writes its weighed taps one by one without autograd (the specular pass of
    rtsplat render and the viewer): the same bits as the autograd lookup, for any channel count."""
    env = EnvironmentMap(channels=channels, height=16, width=32, levels=4).to(dtype)
    g = torch.Generator().manual_seed(channels)
    with torch.no_grad():
        env.features.copy_(torch.randn(env.features.shape, generator=g, dtype=dtype))
    dirs = torch.nn.functional.normalize(torch.randn(3000, 3, generator=g, dtype=dtype), dim=-1)
    rough = torch.rand(3000, generator=g, dtype=dtype)
    with_grad = env(dirs, rough)
    assert with_grad.requires_grad
    with torch.inference_mode():
        without = env(dirs, rough)
    assert torch.equal(without, with_grad.detach()) and without.abs().max() > 0


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_background_lookup_without_autograd_gives_the_values_of_the_autograd_lookup(dtype):
    """Without autograd (rtsplat render, the viewer) the learned background's levels are sampled by the same
    numba kernel as with it (training): the same bits, at the poles and the longitude seam too, and after a
    fused Adam step changed the levels (which leaves their version counters where they were). The torch
    reference is tests/test_background_lookup.py's."""
    background = BackgroundMap(16, 32, 3).to(dtype)
    g = torch.Generator().manual_seed(5)
    with torch.no_grad():
        for level in background.maps:
            level.copy_(torch.randn(level.shape, generator=g, dtype=dtype))
    dirs = torch.nn.functional.normalize(torch.randn(4000, 3, generator=g, dtype=dtype), dim=-1)
    dirs[:4] = torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.0, -1.0], [-1.0, 0.0, 0.0], [-1.0, -1e-7, 0.0]], dtype=dtype)
    optimizer = torch.optim.Adam(background.parameters(), lr=0.5, fused=True)
    for _ in range(3):
        with_grad = background(dirs)
        assert with_grad.requires_grad
        with torch.inference_mode():
            without = background(dirs)
        assert torch.equal(without, with_grad.detach()) and without.std() > 0.01
        optimizer.zero_grad()
        (with_grad * torch.linspace(-1, 1, with_grad.numel(), dtype=dtype).reshape(with_grad.shape)).sum().backward()
        optimizer.step()


def test_environment_map_without_autograd_reuses_its_texel_table_until_the_map_changes():
    env = EnvironmentMap(channels=4, height=8, width=16, levels=3)
    g = torch.Generator().manual_seed(9)
    dirs = torch.nn.functional.normalize(torch.randn(50, 3, generator=g), dim=-1)
    rough = torch.rand(50, generator=g)
    with torch.no_grad():
        env.features.copy_(torch.randn(env.features.shape, generator=g))
        first = env(dirs, rough)
        table = env._table_cache[1]
        assert torch.equal(env(dirs, rough), first) and env._table_cache[1] is table  # reused
        env.features.mul_(2.0)  # an edit of the map: the next lookup sees it
        assert torch.equal(env(dirs, rough), 2.0 * first)
    assert torch.equal(env(dirs, rough).detach(), 2.0 * first)  # the autograd lookup agrees


def test_environment_map_gradients_match_finite_differences():
    env = EnvironmentMap(channels=2, height=8, width=16, levels=3).double()
    g = torch.Generator().manual_seed(3)
    with torch.no_grad():
        env.features.copy_(torch.randn(env.features.shape, generator=g, dtype=torch.float64))
    dirs = torch.nn.functional.normalize(torch.randn(6, 3, generator=g, dtype=torch.float64), dim=-1)
    rough = 0.1 + 0.8 * torch.rand(6, generator=g, dtype=torch.float64)
    features = env.features

    def lookup(f, d, r):
        with torch.no_grad():
            env.features.data = f
            return env(d, r)

    torch.autograd.gradcheck(lambda d, r: env(torch.nn.functional.normalize(d, dim=-1), r),
                             (dirs.clone().requires_grad_(), rough.clone().requires_grad_()))
    weights = torch.randn(6, 2, generator=g, dtype=torch.float64)
    (env(dirs, rough) * weights).sum().backward()
    eps = 1e-6
    for idx in [(0, 0, 3, 5), (0, 1, 0, 15), (0, 0, 7, 0), (0, 1, 2, 2)]:
        plus, minus = features.detach().clone(), features.detach().clone()
        plus[idx] += eps
        minus[idx] -= eps
        numeric = ((lookup(plus, dirs, rough) - lookup(minus, dirs, rough)) * weights).sum() / (2 * eps)
        assert float(features.grad[idx]) == pytest.approx(float(numeric), abs=1e-7)


@pytest.mark.parametrize("height,width,levels", [(16, 32, 5), (9, 22, 4), (4, 8, 5)])
@pytest.mark.parametrize("channels_last", [True, False])
def test_texel_table_and_its_gradient_are_autograds_through_the_mip_levels(height, width, levels, channels_last):
    """The texel table's own backward (a quarter of each texel's gradient added to the four it averages,
    level by level; a level of odd size through avg_pool2d's backward; the levels repeated below 2x4)
    gives the table and the map's gradient of autograd through the 2x2 averages, for the channels-last
    map the model keeps and for a plain one."""
    env = EnvironmentMap(channels=5, height=height, width=width, levels=levels).double()
    assert env.features.is_contiguous(memory_format=torch.channels_last)
    g = torch.Generator().manual_seed(height + levels)
    with torch.no_grad():
        env.features.copy_(torch.randn(env.features.shape, generator=g, dtype=torch.float64))
    if not channels_last:
        env.features.data = env.features.data.contiguous()
    features = env.features
    expected = torch.cat([level[0].permute(1, 2, 0).reshape(-1, 5) for level in mip_levels(features, levels)])
    table, layout = env.texel_table()
    assert torch.equal(table, expected)
    assert [(h, w) for _, h, w in layout] == [tuple(level.shape[-2:]) for level in mip_levels(features, levels)]
    upstream = torch.randn(table.shape, generator=g, dtype=torch.float64)
    (want,) = torch.autograd.grad(expected, features, upstream)
    (got,) = torch.autograd.grad(table, features, upstream)
    torch.testing.assert_close(got, want, rtol=1e-12, atol=1e-12)
    assert want.abs().min() > 0 or height < 8  # every texel of a large level passed some gradient


def test_specular_network_shapes_and_ranges():
    net = SpecularNetwork(16, 4, 32)
    spec, beta = net(torch.randn(7, 16), torch.nn.functional.normalize(torch.randn(7, 4), dim=-1), torch.rand(7, 1))
    assert spec.shape == (7, 3) and beta.shape == (7, 1)
    assert (spec >= 0).all() and ((beta >= 0) & (beta <= 1)).all()


def test_attenuation_from_the_material_ignores_what_the_surface_reflects_and_follows_the_angle():
    torch.manual_seed(0)
    net = SpecularNetwork(16, 4, 32, attenuation="material", mirror=True)
    assert net.mlp[-1].out_features == 4  # C_spec and the mirror weight: no beta column
    material = torch.nn.functional.normalize(torch.randn(6, 4), dim=-1).requires_grad_()
    reflectance, mirror = torch.rand(6, 1), torch.rand(6, 3)
    cos_incidence = torch.linspace(0.05, 1.0, 6)[:, None]
    env_a, env_b = torch.randn(6, 16), 5.0 * torch.randn(6, 16)
    spec_a, beta_a = net(env_a, material, reflectance, mirror, cos_incidence=cos_incidence)
    spec_b, beta_b = net(env_b, material, reflectance, mirror, cos_incidence=cos_incidence)
    assert not torch.allclose(spec_a, spec_b)  # the reflection follows the environment
    torch.testing.assert_close(beta_a, beta_b, rtol=0, atol=0)  # what passes through does not
    assert ((beta_a > 0) & (beta_a < 1)).all()
    _, beta_turned = net(env_a, material, reflectance, mirror, cos_incidence=cos_incidence.flip(0))
    assert not torch.allclose(beta_turned, beta_a)  # but it follows the angle of incidence
    beta_a.sum().backward()
    assert material.grad is not None and torch.isfinite(material.grad).all() and material.grad.abs().sum() > 0
    assert all(p.grad is not None and p.grad.abs().sum() > 0 for p in net.attenuation_head.parameters())
    with pytest.raises(ValueError, match="cos_incidence"):
        net(env_a, material, reflectance, mirror)
    with pytest.raises(ValueError, match="attenuation"):
        SpecularNetwork(16, 4, 32, attenuation="environment")


def test_specular_network_in_bfloat16_follows_float32_and_keeps_float32_outputs_and_gradients():
    torch.manual_seed(0)
    exact = SpecularNetwork(20, 4, 64, "float32")
    low = SpecularNetwork(20, 4, 64, "bfloat16")
    low.load_state_dict(exact.state_dict())
    env = torch.randn(500, 20)
    material = torch.nn.functional.normalize(torch.randn(500, 4), dim=-1)
    reflectance = torch.rand(500, 1)
    outputs, grads = {}, {}
    for name, net in (("exact", exact), ("low", low)):
        spec, beta = net(env, material, reflectance)
        (spec.square().sum() + beta.sum()).backward()
        outputs[name] = torch.cat([spec, beta], -1)
        grads[name] = net.mlp[0].weight.grad
        assert spec.dtype == beta.dtype == net.mlp[0].weight.grad.dtype == torch.float32
        assert torch.isfinite(grads[name]).all()
    assert not torch.equal(outputs["low"], outputs["exact"])  # the products did run in bfloat16
    torch.testing.assert_close(outputs["low"], outputs["exact"], rtol=0.03, atol=0.01)
    cosine = torch.nn.functional.cosine_similarity(grads["low"].flatten(), grads["exact"].flatten(), dim=0)
    assert cosine > 0.99
    assert SpecularNetwork(20, 4, 8, "auto").uses_bfloat16(torch.device("cuda")) is False
    with pytest.raises(ValueError, match="precision"):
        SpecularNetwork(20, 4, 8, "float16")


def test_bucketed_rows_cover_the_rows_with_few_shapes_and_little_padding():
    sizes = range(1, 600_001, 7)
    padded = [bucketed_rows(n) for n in sizes]
    assert all(p >= n for n, p in zip(sizes, padded, strict=True))
    assert all(p - n < 1024 or p <= n * 1.0625 for n, p in zip(sizes, padded, strict=True))
    assert len({bucketed_rows(n) for n in range(1, 7501)}) == 8  # a 100x75 image: eight shapes
    assert len({bucketed_rows(n) for n in range(300_000, 600_001)}) <= 17  # one octave: at most 17
    assert bucketed_rows(0) == 0


def test_specular_network_in_bfloat16_on_the_cpu_runs_on_bucketed_rows_and_drops_the_padding():
    torch.manual_seed(1)
    net = SpecularNetwork(20, 4, 64, "bfloat16")
    shapes = []
    net.mlp[0].register_forward_hook(lambda module, inputs, output: shapes.append(inputs[0].shape[0]))
    env = torch.randn(1500, 20, requires_grad=True)
    material = torch.nn.functional.normalize(torch.randn(1500, 4), dim=-1)
    reflectance = torch.rand(1500, 1)
    assert net.mlp_outputs_reference(env, material).shape == (1500, 4)
    assert shapes == [bucketed_rows(1500)] == [2048]
    spec, beta = net(env, material, reflectance)  # with autograd on a CPU: BFloat16Network, on the same rows
    assert spec.shape == (1500, 3) and beta.shape == (1500, 1)
    (spec.square().sum() + beta.sum()).backward()
    grad_padded = net.mlp[2].weight.grad.clone()
    # the same rows without padding: the padded rows add nothing to the outputs or the weights' gradients
    net.zero_grad()
    with torch.autocast("cpu", dtype=torch.bfloat16):
        outer = (env[:, :, None] * material[:, None, :]).flatten(1)
        out = net.mlp(torch.cat([outer, env], -1)).float()
    torch.testing.assert_close(torch.sigmoid(out[:, 3:4]), beta, rtol=1e-5, atol=1e-6)
    spec_plain = torch.exp((out[:, :3] + math.log(0.5)).clamp_max(8.0)) * reflectance
    torch.testing.assert_close(spec_plain, spec, rtol=1e-5, atol=1e-6)
    (spec_plain.square().sum() + torch.sigmoid(out[:, 3:4]).sum()).backward()
    torch.testing.assert_close(net.mlp[2].weight.grad, grad_padded, rtol=1e-4, atol=1e-5)


@pytest.mark.parametrize("precision", ["float32", "bfloat16", "auto"])
def test_a_model_names_the_dtype_its_specular_network_multiplies_in(precision):
    surfels = init_from_points(torch.rand(20, 3), torch.rand(20, 3), occupancy=0.6)
    settings = dataclasses.replace(SMALL, specular_precision=precision)
    model = RTModel(surfels, effects=ActiveEffects(), settings=settings)
    native = specular.cpu_has_bfloat16_matmul()
    expected = {"float32": "float32", "bfloat16": "bfloat16", "auto": "bfloat16" if native else "float32"}
    assert model.specular_products() == expected[precision]
    plain = RTModel(surfels, effects=ActiveEffects(transmission=False, specular=False), settings=settings)
    assert plain.specular_products() is None


def test_gate_gradient_keeps_the_value_and_scales_the_gradient_exactly():
    x = torch.rand(5, 4, 3, dtype=torch.float64, requires_grad=True)
    g = torch.rand(5, 4, 3, dtype=torch.float64)
    y = gate_gradient(x, g)
    torch.testing.assert_close(y, x, rtol=0, atol=1e-15)
    upstream = torch.rand_like(x)
    y.backward(upstream)
    torch.testing.assert_close(x.grad, g * upstream, rtol=0, atol=1e-15)


@pytest.mark.parametrize("mode", ["variance", "weighted_std"])
def test_gate_is_one_on_flat_specular_and_small_on_busy_specular(mode):
    flat = torch.full((6, 6, 3), 0.7)
    alpha = torch.zeros(6, 6, 1)
    assert torch.allclose(gate_factor(flat, alpha, 4.0, mode), torch.ones(6, 6, 3))
    busy = (torch.arange(36).reshape(6, 6, 1) % 2).float().expand(6, 6, 3) * 3
    assert gate_factor(busy, alpha, 4.0, mode).max() < 0.2
    if mode == "variance":  # plain 3x3 variance at an interior pixel
        window = busy[1:4, 1:4, 0].flatten()
        assert torch.isclose(specular_complexity(busy, alpha, mode)[2, 2, 0], window.var(unbiased=False))


def _model(effects=None, ablations=None, seed=0, settings=SMALL):
    torch.manual_seed(seed)  # the specular network's initialisation
    g = torch.Generator().manual_seed(seed)
    xyz = torch.rand(300, 3, generator=g) * 1.2 - 0.6
    rgb = torch.rand(300, 3, generator=g)
    surfels = init_from_points(xyz, rgb, occupancy=0.6, opacity=0.5, generator=g)
    model = RTModel(surfels, effects=effects or ActiveEffects(), ablations=ablations or Ablations(), settings=settings,
                    roi_center=(0.0, 0.0, 0.0), roi_radius=5.0)
    if model.env is not None:  # drawn in the map's logical order, whatever its memory layout
        with torch.no_grad():
            model.env.features.copy_(torch.randn(model.env.features.shape, generator=g))
    return model


def _render(model, **kw):
    return model.render(small_camera(24, 18, torch.float32), stage="full", backend="reference", **kw)


def test_the_specular_weight_fades_the_full_model_in_from_the_subsurface_stage_image():
    model = _model(seed=1)
    camera = small_camera(24, 18, torch.float32)
    with torch.no_grad():
        before = model.render(camera, stage="subsurface", backend="reference").color
        full = _render(model).color
        assert (full - before).abs().max() > 1e-2  # the specular branch changes the image
        # the subsurface stage rasterizes no specular input, and the torch reference blends the channels in one
        # float32 product whose summation order may follow the channel count: equal to float32 rounding
        torch.testing.assert_close(_render(model, specular_weight=0.0).color, before, rtol=1e-6, atol=1e-6)
        assert torch.equal(_render(model, specular_weight=1.0).color, full)
        # C_spec + beta C_sub is linear in the weight, and so is the region blend around it
        assert torch.allclose(_render(model, specular_weight=0.25).color, 0.75 * before + 0.25 * full, atol=1e-6)
    for weight in (-0.1, 1.5):
        with pytest.raises(ValueError, match="specular_weight"):
            _render(model, specular_weight=weight)


@pytest.mark.parametrize("weight", [0.0, 1e-3, 0.4])
def test_a_faded_specular_branch_passes_finite_gradients_and_none_at_weight_zero(weight):
    model = _model(seed=2)
    _render(model, specular_weight=weight).color.square().sum().backward()
    network = [p.grad for p in model.specular_net.parameters()]
    assert all(g is None or torch.isfinite(g).all() for g in network)
    assert all(torch.isfinite(p.grad).all() for p in model.surfels.parameters() if p.grad is not None)
    reached = any(g is not None and g.abs().max() > 0 for g in network)
    assert reached == (weight > 0)


@pytest.mark.parametrize("backend", ["reference", "cpu"])
def test_frustum_culling_leaves_out_only_surfels_the_rasterizer_skips_and_keeps_the_image(backend):
    from rtsplat.raster.projection import project_surfels

    model = _model(seed=3)
    # close to the cloud, looking past its side: many surfels outside the image, some behind the camera
    camera = camera_from_fov((0.1, -0.9, 0.1), (0.9, 0.0, 0.2), width=32, height=24, fov_x_deg=40.0,
                             dtype=torch.float32)
    settings = RasterSettings()
    kept = model.in_view(camera, settings)
    drawn = project_surfels(model.rasterizer_surfels(camera), camera, settings).valid
    assert int(kept.sum()) < 0.75 * len(kept) and drawn.any()
    assert not (drawn & ~kept).any()  # every surfel the rasterizer draws is kept
    with torch.no_grad():
        full = model.render(camera, raster_settings=settings, backend=backend)
        culled = model.render(camera, raster_settings=settings, backend=backend, frustum_cull=True)
    assert torch.equal(culled.surfel_index, torch.nonzero(kept).flatten()) and full.surfel_index is None
    assert torch.equal(culled.color, full.color) and full.color.abs().sum() > 0
    assert culled.layers.keys() == full.layers.keys()
    for name, image in full.layers.items():
        assert torch.equal(culled.layers[name], image), name


def test_occupancy_ablation_uses_one_opacity_for_both_weight_sets():
    out = _render(_model(ablations=Ablations(occupancy=False))).raster
    assert torch.equal(out.alpha, out.volume_alpha)
    out_on = _render(_model()).raster
    assert (out_on.alpha - out_on.volume_alpha).abs().max() > 0.05


def test_attenuation_ablation_sets_beta_to_one():
    layers = _render(_model(ablations=Ablations(attenuation=False))).layers
    assert torch.equal(layers["beta"], torch.ones_like(layers["beta"]))
    assert (_render(_model()).layers["beta"] - 1).abs().max() > 1e-3


def test_scattering_ablation_removes_tau_and_scatter():
    result = _render(_model(ablations=Ablations(scattering=False)))
    assert "tau" not in result.layers and "scatter" not in result.layers
    L = result.layers
    shaded = L["spec"] + L["beta"] * L["trans"]
    expected = torch.where(L["shade"] > 0, L["roi"] * shaded + (1 - L["roi"]) * L["trans"], L["trans"])
    torch.testing.assert_close(result.color, expected)


def test_composite_equation_with_every_branch_on():
    result = _render(_model())
    L = result.layers
    shaded = L["spec"] + L["beta"] * (L["tau"] * L["trans"] + (1 - L["tau"]) * L["scatter"])
    expected = torch.where(L["shade"] > 0, L["roi"] * shaded + (1 - L["roi"]) * L["trans"], L["trans"])
    torch.testing.assert_close(result.color, expected)
    assert L["shade"].sum() > 10  # the test exercises shaded pixels


def test_shade_coverage_gives_the_uncovered_part_of_a_pixel_the_volume_colour():
    """model.shade_coverage: the shaded colour weighs the surface's coverage of the pixel (its alpha) times the
    normalised region membership, the rest shows C_trans; off: the normalised membership alone. The shaded
    colour itself (C_spec, beta, tau, C_scatter) is the same either way."""
    results = {}
    for on in (False, True):
        model = _model(seed=2)
        model.settings = dataclasses.replace(model.settings, shade_coverage=on)
        result = _render(model)
        result.color.sum().backward()
        results[on] = (result, model.surfels.occupancy_logit.grad.clone())
    (off, _), (on, grad) = results[False], results[True]
    L = off.layers
    alpha = L["alpha"].clamp(0, 1)
    partial = (L["shade"] > 0) & (alpha < 0.9) & (L["roi"] > 0.5)
    assert partial.sum() > 10  # silhouettes and thin cover: the pixels the setting is about
    torch.testing.assert_close(on.layers["roi"], L["roi"] * alpha)
    shaded = L["spec"] + L["beta"] * (L["tau"] * L["trans"] + (1 - L["tau"]) * L["scatter"])
    weight = L["roi"] * alpha
    expected = torch.where(L["shade"] > 0, weight * shaded + (1 - weight) * L["trans"], L["trans"])
    torch.testing.assert_close(on.color, expected)
    for name in ("spec", "beta", "tau", "scatter", "trans"):
        torch.testing.assert_close(on.layers[name], L[name], rtol=0, atol=0)
    gap = (on.color - off.color).abs().amax(-1, keepdim=True)
    assert gap[partial].max() > 1e-3
    assert torch.isfinite(grad).all() and grad.abs().max() > 0


class _EveryShadedPixel(RTModel):
    """Runs the specular network on every shaded pixel, region of interest or not."""

    def _specular(self, camera, normal, g, alpha_safe, shade, every_pixel=None, near=None, rays=None, **kwargs):
        return super()._specular(camera, normal, g, alpha_safe, alpha_safe > self.settings.shade_alpha_threshold,
                                 every_pixel, near, rays, **kwargs)


def test_specular_runs_only_where_the_roi_weighs_and_the_image_and_gradients_do_not_change():
    results = []
    for cls in (RTModel, _EveryShadedPixel):
        model = _model()
        model.__class__ = cls
        with torch.no_grad():  # half of the surfels leave the region of interest
            model.roi_radius.fill_(0.5)
        result = _render(model)
        (result.color * torch.linspace(0.5, 1.5, result.color.numel()).reshape(result.color.shape)).sum().backward()
        grads = [p.grad.clone() for p in model.parameters() if p.grad is not None]
        results.append((result, grads))
    (restricted, g_restricted), (full, g_full) = results
    outside = (full.layers["shade"] > 0) & (full.layers["roi"] == 0)
    assert outside.sum() > 20  # the network sees fewer pixels
    assert restricted.layers["spec"][outside.expand(-1, -1, 3)].abs().max() == 0
    assert full.layers["spec"][outside.expand(-1, -1, 3)].abs().max() > 0
    torch.testing.assert_close(restricted.color, full.color, rtol=0, atol=0)
    for key in ("reflection", "transmission"):
        torch.testing.assert_close(restricted.layers[key], full.layers[key], rtol=0, atol=0)
    assert len(g_restricted) == len(g_full)
    for a, b in zip(g_restricted, g_full, strict=True):  # float32 sums over fewer zero rows: rounding only
        torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-5 * float(b.abs().max()))


def test_see_through_surfaces_alone_get_the_specular_network():
    """model.specular_surfaces='see_through': the network shades only where the blended optical opacity says
    see-through. An opaque pixel (opacity >= 0.8) shows its volume colour alone, a see-through one (<= 0.5) the
    same colour as with 'all', and the network runs on fewer rows.
    Without transmission (no optical opacity) every surface is shaded, as with 'all'."""
    rows = []

    def count_rows(module, inputs, output):
        rows.append(inputs[0].shape[0])

    results = {}
    for surfaces in ("all", "see_through"):
        model = _model(seed=1)
        model.settings = dataclasses.replace(model.settings, specular_surfaces=surfaces)
        with torch.no_grad():  # the left half opaque, the right half clear glass
            left = model.surfels.means[:, 0] < 0
            model.surfels.opacity_logit.copy_(torch.where(left, torch.tensor(6.0), torch.tensor(-4.0)))
        model.specular_net.register_forward_hook(count_rows)
        result = _render(model)
        result.color.sum().backward()
        results[surfaces] = (result, model.surfels.opacity_logit.grad.clone())
    (every, _), (clear, clear_grad) = results["all"], results["see_through"]
    opacity = every.layers["blended_opacity"] / every.layers["alpha"].clamp_min(1e-6)
    shaded = every.layers["shade"] > 0
    opaque, see_through = shaded & (opacity >= 0.8), shaded & (opacity <= 0.5)
    assert opaque.sum() > 20 and see_through.sum() > 20
    assert rows[1] < rows[0]  # the network ran on fewer pixels
    torch.testing.assert_close(clear.color[opaque.expand(-1, -1, 3)], clear.layers["trans"][opaque.expand(-1, -1, 3)],
                               rtol=0, atol=0)
    assert (every.color - every.layers["trans"])[opaque.expand(-1, -1, 3)].abs().max() > 1e-3
    torch.testing.assert_close(clear.color[see_through.expand(-1, -1, 3)], every.color[see_through.expand(-1, -1, 3)])
    assert torch.isfinite(clear_grad).all()
    # no transmission: no optical opacity to read, every surface shaded as with 'all'
    plain = []
    for surfaces in ("all", "see_through"):
        model = _model(effects=ActiveEffects(transmission=False), seed=1)
        model.settings = dataclasses.replace(model.settings, specular_surfaces=surfaces)
        plain.append(_render(model).color.detach())
    torch.testing.assert_close(plain[0], plain[1], rtol=0, atol=0)


def test_see_through_weight_is_one_below_the_first_opacity_zero_above_the_second_and_passes_no_gradient():
    opacity = torch.tensor([0.0, 0.5, 0.65, 0.8, 1.0], requires_grad=True)
    weight = rtmodel.see_through_weight(opacity)
    torch.testing.assert_close(weight, torch.tensor([1.0, 1.0, 0.5, 0.0, 0.0]))
    assert not weight.requires_grad


def _sh_grad(model, gating, weight):
    model.zero_grad(set_to_none=True)
    result = _render(model, gating=gating)
    (result.color * weight(result)).sum().backward()
    return model.surfels.sh_dc.grad.clone(), result


def test_gating_off_leaves_the_transmission_gradient_untouched(monkeypatch):
    """gating off == gating on with g forced to exactly 1."""
    weight = lambda r: torch.ones_like(r.color)  # noqa: E731
    off, _ = _sh_grad(_model(ablations=Ablations(gating=False)), Gating(), weight)
    monkeypatch.setattr(rtmodel, "gate_factor", lambda spec, *a, **k: torch.ones_like(spec))
    forced, result = _sh_grad(_model(), Gating(), weight)
    assert "gate" in result.layers
    torch.testing.assert_close(forced, off, rtol=0, atol=0)


def test_gating_scales_the_transmission_gradient_by_g():
    """Undo g in the loss weights (on the gated path only): gradients must equal the ungated ones."""
    base = _model(seed=3)
    on = _model(seed=3)
    reference = _render(base, gating=Gating()).layers
    g = reference["gate"]
    L = reference
    tau_beta_roi = (L["roi"] * L["beta"] * L["tau"]).detach()
    shade = L["shade"]
    path_on = torch.where(shade > 0, tau_beta_roi * g + (1 - L["roi"].detach()), torch.ones_like(g))
    path_off = torch.where(shade > 0, tau_beta_roi + (1 - L["roi"].detach()), torch.ones_like(g))
    assert (g < 0.99).any(), "the scene has no specular variation to gate"
    grad_off, _ = _sh_grad(_model(seed=3, ablations=Ablations(gating=False)), Gating(), lambda r: path_off / path_off)
    grad_on, _ = _sh_grad(on, Gating(), lambda r: path_off / path_on)
    torch.testing.assert_close(grad_on, grad_off, rtol=1e-4, atol=1e-7)
    # and the forward value does not depend on gating
    torch.testing.assert_close(_render(on, gating=Gating()).color, _render(on, gating=None).color)


class _EveryGBufferChannel(RTModel):
    """Rasterizes every G-buffer channel, whatever its effects and the stage read."""

    def gbuffer_channels(self, stage="full"):
        return tuple(GBUFFER_WIDTHS)


@pytest.mark.parametrize("backend", ["reference", "cpu"])
@pytest.mark.parametrize("stage", STAGES)
@pytest.mark.parametrize("effects, ablations", [
    (ActiveEffects(), Ablations()),
    (ActiveEffects(transmission=False, specular=False), Ablations()),
    (ActiveEffects(specular=False), Ablations()),
    (ActiveEffects(transmission=False), Ablations()),
    (ActiveEffects(), Ablations(occupancy=False, scattering=False)),
])
def test_a_model_rasterizes_only_the_gbuffer_channels_its_effects_and_stage_read_and_gets_the_same_image_and_gradients(
        stage, effects, ablations, backend):
    results = []
    for cls in (RTModel, _EveryGBufferChannel):
        # float32 products: on a CPU with bfloat16 products (precision auto) the network rounds its inputs to
        # bfloat16, and inputs that differ in the last float32 bit (the reference backend's summation order, below)
        # can round to neighbouring bfloat16 values
        model = _model(effects, ablations, settings=dataclasses.replace(SMALL, specular_precision="float32"))
        model.__class__ = cls
        result = model.render(small_camera(24, 18, torch.float32), stage=stage, backend=backend)
        weights = torch.linspace(0.5, 1.5, result.color.numel()).reshape(result.color.shape)
        loss = (result.color * weights).sum() + result.layers["blended_opacity"].sum()
        loss.backward()
        grads = {name: p.grad for name, p in model.named_parameters()}
        results.append((result, grads))
    (subset, g_subset), (every, g_every) = results
    assert subset.raster.features.shape[-1] == sum(GBUFFER_WIDTHS[n] for n in subset.gbuffer)
    assert every.raster.features.shape[-1] == sum(GBUFFER_WIDTHS.values())
    expected = {  # what each model reads in the full stage
        (True, True, True): set(GBUFFER_WIDTHS),
        (False, False, True): set(),  # plain 2DGS
        (True, False, True): {"opacity", "roi", "scatter", "tau"},
        (False, True, True): {"roi", "roughness", "material", "reflectance"},
        (True, True, False): {"roi", "roughness", "material", "reflectance"},  # no occupancy, no scattering
    }[(effects.transmission, effects.specular, ablations.occupancy)]
    if stage == "volume":  # the colour alone, and the mask loss's blended opacity
        expected &= {"opacity"}
    elif stage == "subsurface":  # no specular network, so none of its inputs
        expected -= {"roughness", "material", "reflectance"}
    assert set(subset.gbuffer) == expected
    # the cpu backend composites each channel on its own in float64: the same bits. The torch reference blends all
    # channels in one float32 product, whose summation order the BLAS may choose by the channel count (it does on an
    # AVX2 CPU, not on one with AVX512): the same values to float32 rounding
    exact = backend == "cpu"
    tol = {"rtol": 0, "atol": 0} if exact else {"rtol": 1e-5, "atol": 1e-6}
    torch.testing.assert_close(subset.color, every.color, **tol)
    assert set(subset.layers) == set(every.layers)
    for key in subset.layers:  # with opacity 1 the blended opacity is the alpha, summed in another order
        reordered = key == "blended_opacity" and "opacity" not in subset.gbuffer
        torch.testing.assert_close(subset.layers[key], every.layers[key],
                                   **({"rtol": 1e-6, "atol": 1e-6} if reordered and exact else tol))
    for name, g in g_every.items():  # a parameter the render does not read gets no gradient, not a zero one
        if g_subset[name] is None:
            assert g is None or g.abs().max() == 0, name
        else:
            torch.testing.assert_close(g_subset[name], g, rtol=1e-5, atol=1e-6 * float(g.abs().max()), msg=name)


def test_no_transmission_no_specular_is_plain_2dgs_radiance():
    model = _model(effects=ActiveEffects(transmission=False, specular=False))
    assert model.env is None and model.specular_net is None
    result = _render(model)
    assert torch.equal(result.raster.alpha, result.raster.volume_alpha)
    torch.testing.assert_close(result.color, result.layers["trans"])


def test_effects_auto_decides_from_masks_and_roi():
    effects, why = decide_effects(Effects(), transparent_fraction=0.0, roi_source=None)
    assert effects == ActiveEffects(transmission=False, specular=False)
    assert "no transparent pixel" in why["transmission"]
    # an ROI that prepare estimated does not ask for reflections; one given in the config does
    assert decide_effects(Effects(), 0.0, "estimated")[0] == ActiveEffects(False, False)
    effects, why = decide_effects(Effects(), 0.0, "config")
    assert effects == ActiveEffects(False, True) and "config" in why["specular"]
    effects, why = decide_effects(Effects(), transparent_fraction=0.1, roi_source="estimated")
    # near reflections are off unless asked for
    assert effects == ActiveEffects(True, True, near_reflection=False) and why["near_reflection"] == "config: off"
    # auto asks for them with both branches; the glass's planes decide later
    effects, why = decide_effects(Effects(near_reflection="auto"), transparent_fraction=0.1, roi_source="estimated")
    assert effects == ActiveEffects(True, True, near_reflection=True) and "planes decide" in why["near_reflection"]
    effects, why = decide_effects(Effects(transmission="on", specular="off", near_reflection="auto"), 0.0, "config")
    assert effects == ActiveEffects(True, False) and why["specular"] == "config: off"
    assert "needs transmission and specular" in why["near_reflection"]
    assert not decide_effects(Effects(near_reflection="off"), 0.1, None)[0].near_reflection
    assert not decide_effects(Effects(specular="off", near_reflection="on"), 0.1, None)[0].near_reflection


def test_checkpoint_rebuilds_the_model_without_the_trainer_config(tmp_path):
    model = _model(ablations=Ablations(attenuation=False))
    raster = RasterSettings(tile_size=8)
    write_checkpoint(tmp_path / "m.pt", model, raster, training={"iteration": 7})
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m.pt"]  # no temporary file left behind
    checkpoint = read_checkpoint(tmp_path / "m.pt")
    assert checkpoint.raster == raster and checkpoint.training == {"iteration": 7}
    assert checkpoint.ablations == model.ablations and checkpoint.settings == model.settings
    rebuilt = checkpoint.build_model()
    with torch.no_grad():
        torch.testing.assert_close(_render(rebuilt).color, _render(model).color, rtol=0, atol=0)


def test_checkpoint_reads_version_1_files_and_names_unreadable_ones(tmp_path):
    from dataclasses import asdict

    model = _model()
    v1 = {"version": 1, "iteration": 3, "effects": model.effects.to_dict(),
          "config": {"ablations": asdict(model.ablations), "model": asdict(model.settings), "raster": {}},
          "surfels": {k: v.detach() for k, v in model.surfels.tensors().items()},
          "model": {k: v for k, v in model.state_dict().items() if not k.startswith("surfels.")}}
    torch.save(v1, tmp_path / "v1.pt")
    checkpoint = read_checkpoint(tmp_path / "v1.pt")
    assert checkpoint.training["iteration"] == 3 and checkpoint.raster == RasterSettings()
    with torch.no_grad():
        torch.testing.assert_close(_render(checkpoint.build_model()).color, _render(model).color, rtol=0, atol=0)
    (tmp_path / "bad.pt").write_bytes(b"not a checkpoint")
    with pytest.raises(CheckpointError, match="bad.pt: cannot read checkpoint"):
        read_checkpoint(tmp_path / "bad.pt")


def test_a_lazy_checkpoint_read_gives_the_same_model_and_the_same_errors(tmp_path):
    """``lazy`` (memory-mapped) reads give the model of a whole read, also from a file in torch's old
    serialization format (which cannot be mapped), and name an unreadable file the same way."""
    model = _model()
    write_checkpoint(tmp_path / "m.pt", model, RasterSettings(), training={"iteration": 7})
    state = torch.load(tmp_path / "m.pt", weights_only=False)
    torch.save(state, tmp_path / "old.pt", _use_new_zipfile_serialization=False)
    with torch.no_grad():
        want = _render(read_checkpoint(tmp_path / "m.pt").build_model()).color
        for name in ("m.pt", "old.pt"):
            checkpoint = read_checkpoint(tmp_path / name, lazy=True)
            assert checkpoint.training == {"iteration": 7}
            torch.testing.assert_close(_render(checkpoint.build_model()).color, want, rtol=0, atol=0)
    (tmp_path / "bad.pt").write_bytes(b"not a checkpoint")
    with pytest.raises(CheckpointError, match="bad.pt: cannot read checkpoint"):
        read_checkpoint(tmp_path / "bad.pt", lazy=True)


def test_checkpoint_of_a_model_without_the_extra_specular_inputs_rebuilds_its_network(tmp_path):
    """A model written before the specular network had its extra inputs names neither setting; it is read
    with both off, the shape it was trained with, and renders as before."""
    model = _model_with(specular_view_angle=False, specular_background=False)
    write_checkpoint(tmp_path / "old.pt", model, RasterSettings())
    state = torch.load(tmp_path / "old.pt", weights_only=False)
    for name in ("specular_view_angle", "specular_background"):
        del state["model"]["settings"][name]
    torch.save(state, tmp_path / "old.pt")
    rebuilt = read_checkpoint(tmp_path / "old.pt").build_model()
    assert not rebuilt.settings.specular_view_angle and not rebuilt.settings.specular_background
    assert rebuilt.specular_net.mlp[0].in_features == SMALL.env_channels * 5
    with torch.no_grad():
        torch.testing.assert_close(_render(rebuilt).color, _render(model).color, rtol=0, atol=0)


def test_a_model_written_before_shade_coverage_reads_without_it_and_renders_as_it_was_trained(tmp_path):
    """A file that names no ``shade_coverage`` (written before the setting) is read with it off, the composite
    such a model was trained with; one written now keeps the setting it names."""
    plain = _model_with(shade_coverage=False)
    write_checkpoint(tmp_path / "old.pt", plain, RasterSettings())
    state = torch.load(tmp_path / "old.pt", weights_only=False)
    del state["model"]["settings"]["shade_coverage"]
    torch.save(state, tmp_path / "old.pt")
    old = read_checkpoint(tmp_path / "old.pt").build_model()
    assert old.settings.shade_coverage is False
    current = _model_with(shade_coverage=True)
    write_checkpoint(tmp_path / "new.pt", current, RasterSettings())
    assert read_checkpoint(tmp_path / "new.pt").build_model().settings.shade_coverage is True
    with torch.no_grad():
        torch.testing.assert_close(_render(old).color, _render(plain).color, rtol=0, atol=0)
        assert (_render(current).color - _render(plain).color).abs().max() > 1e-3


def test_a_model_with_beta_from_the_material_round_trips_and_one_written_before_reads_as_network(tmp_path):
    """A model whose beta comes from its attenuation head renders the same after a checkpoint round trip; a
    file that names no ``attenuation_from`` (written before the setting) is read with beta from the network."""
    model = _model_with(attenuation_from="material")
    assert model.specular_net.attenuation_head is not None
    write_checkpoint(tmp_path / "material.pt", model, RasterSettings())
    rebuilt = read_checkpoint(tmp_path / "material.pt").build_model()
    with torch.no_grad():
        expected, again = _render(model), _render(rebuilt)
        torch.testing.assert_close(again.color, expected.color, rtol=0, atol=0)
    beta = expected.layers["beta"][expected.layers["shade"] > 0]
    assert beta.numel() > 10 and float(beta.min()) > 0 and float(beta.max()) < 1
    plain = _model_with(attenuation_from="network")
    write_checkpoint(tmp_path / "old.pt", plain, RasterSettings())
    state = torch.load(tmp_path / "old.pt", weights_only=False)
    del state["model"]["settings"]["attenuation_from"]
    torch.save(state, tmp_path / "old.pt")
    old = read_checkpoint(tmp_path / "old.pt").build_model()
    assert old.settings.attenuation_from == "network" and old.specular_net.attenuation_head is None
    with torch.no_grad():
        torch.testing.assert_close(_render(old).color, _render(plain).color, rtol=0, atol=0)


def _plain_model(background: str, seed: int = 0) -> RTModel:
    g = torch.Generator().manual_seed(seed)
    xyz = torch.rand(40, 3, generator=g) * 0.4 - 0.2  # a small cluster: most pixels see past it
    surfels = init_from_points(xyz, torch.rand(40, 3, generator=g), occupancy=0.6, generator=g)
    settings = ModelSettings(env_height=16, env_width=32, env_levels=3, mlp_width=32, background=background,
                             background_height=16, background_width=32, background_levels=3)
    return RTModel(surfels, effects=ActiveEffects(transmission=False, specular=False), settings=settings)


@pytest.mark.parametrize("mode,value", [("black", 0.0), ("white", 1.0)])
def test_constant_backgrounds_fill_the_transmittance_left(mode, value):
    result = _render(_plain_model(mode))
    out = result.raster
    assert (out.volume_alpha < 1e-3).sum() > 50  # the view sees past the surfels
    torch.testing.assert_close(result.color, out.color + (1 - out.volume_alpha) * value)


def test_learned_background_is_indexed_by_the_ray_direction_and_trained_by_the_image_loss():
    model = _plain_model("learned")
    assert model.background_map is not None
    finest = model.background_map.maps[0]
    rows = finest.shape[2]
    with torch.no_grad():  # upper hemisphere (rows of colatitude < 90 degrees, z > 0) red, lower blue
        finest[0, :, : rows // 2] = torch.tensor([4.0, -4.0, -4.0])[:, None, None]
        finest[0, :, rows // 2 :] = torch.tensor([-4.0, -4.0, 4.0])[:, None, None]
    camera = small_camera(24, 18, torch.float32, eye=(0.3, -3.0, 0.0))
    result = model.render(camera, stage="full", backend="reference")
    rays = rtmodel.image_ray_directions(camera)
    empty = result.raster.volume_alpha[..., 0] < 1e-4
    up, down = empty & (rays[..., 2] > 0.1), empty & (rays[..., 2] < -0.1)
    assert up.sum() > 5 and down.sum() > 5
    red, blue = torch.sigmoid(torch.tensor(4.0)), torch.sigmoid(torch.tensor(-4.0))
    torch.testing.assert_close(result.color[up], torch.stack([red, blue, blue]).expand(int(up.sum()), 3), atol=1e-4,
                               rtol=0)
    torch.testing.assert_close(result.color[down], torch.stack([blue, blue, red]).expand(int(down.sum()), 3),
                               atol=1e-4, rtol=0)
    # partly covered pixels see the background through what is left of the transmittance
    out = result.raster
    torch.testing.assert_close(result.color, out.color + (1 - out.volume_alpha) * model.background_radiance(camera))
    result.color.sum().backward()
    for level in model.background_map.maps:
        assert level.grad is not None and level.grad.abs().sum() > 0


def test_a_background_colour_given_to_render_replaces_the_model_background():
    model = _plain_model("random")
    assert model.background_map is None
    colour = torch.tensor([0.2, 0.7, 0.4])
    result = _render(model, background=colour)
    out = result.raster
    torch.testing.assert_close(result.color, out.color + (1 - out.volume_alpha) * colour)


def test_scattered_points_keep_the_originals_and_spread_by_half_the_neighbour_distance():
    from rtsplat.model.surfels import nearest_neighbour_scale, scatter_points

    g = torch.Generator().manual_seed(0)
    grid = torch.stack(torch.meshgrid(torch.arange(20.0), torch.arange(20.0), indexing="ij"), -1).reshape(-1, 2)
    xyz = torch.cat([grid * 0.1, torch.zeros(400, 1)], 1)  # a plane of points 0.1 apart
    xyz[:200] *= 3.0  # half of them 0.3 apart
    rgb = torch.rand(400, 3, generator=g)
    out_xyz, out_rgb = scatter_points(xyz, rgb, 5, generator=g)
    assert out_xyz.shape == (2000, 3) and out_rgb.shape == (2000, 3)
    assert torch.equal(out_xyz[:400], xyz) and torch.equal(out_rgb[400:].reshape(4, 400, 3), rgb.expand(4, 400, 3))
    offsets = (out_xyz[400:].reshape(4, 400, 3) - xyz).reshape(4, 400, 3)
    spread = offsets.pow(2).mean((0, 2)).sqrt()  # per point, over its copies and the axes
    want = 0.5 * nearest_neighbour_scale(xyz)
    for rows in (slice(0, 200), slice(200, 400)):  # tracks the local spacing: 0.3 apart vs 0.1 apart
        ratio = spread[rows].mean() / want[rows].mean()
        assert 0.85 < ratio < 1.15
    same_xyz, same_rgb = scatter_points(xyz, rgb, 1)
    assert same_xyz is xyz and same_rgb is rgb


def test_quats_with_normal_turn_the_surfel_normal_onto_the_given_one():
    from rtsplat.model.surfels import quats_with_normal
    from rtsplat.raster.projection import quat_to_rotmat

    normals = torch.tensor([[0.0, 0, 1], [0, 0, -1], [1, 0, 0], [0.3, -0.4, 0.2], [0, 1e-9, -1]])
    R = quat_to_rotmat(quats_with_normal(normals))
    expected = torch.nn.functional.normalize(normals, dim=-1)
    assert torch.allclose(R[:, :, 2], expected, atol=1e-6)


def _inputs_of_the_specular_network(model, monkeypatch):
    """Render ``model`` and return (its render, the environment features, the reflectance and the mirror
    radiance its specular network got)."""
    seen = []
    forward = SpecularNetwork.forward

    def spy(net, env_features, material, reflectance, mirror=None, near=None, cos_incidence=None):
        seen.append((env_features, reflectance, mirror))
        return forward(net, env_features, material, reflectance, mirror, near, cos_incidence)

    with monkeypatch.context() as patch:
        patch.setattr(SpecularNetwork, "forward", spy)
        result = _render(model)
    assert len(seen) == 1
    return (result, *seen[0])


def _rays_and_normals_of_the_shaded_region(result):
    """View rays and normals [P,3] of the pixels of ``_render``'s image that the specular network shades."""
    L = result.layers
    shaded = ((L["shade"] > 0) & (L["roi"] > 0)).reshape(-1)
    rays = rtmodel.image_ray_directions(small_camera(24, 18, torch.float32)).reshape(-1, 3)[shaded]
    return rays, L["normal"].reshape(-1, 3)[shaded]


def _model_with(**settings):
    torch.manual_seed(0)
    model = _model()
    torch.manual_seed(0)
    return RTModel(model.surfels, effects=ActiveEffects(), settings=dataclasses.replace(SMALL, **settings),
                   roi_center=(0.0, 0.0, 0.0), roi_radius=5.0)


def test_specular_view_angle_is_the_cosine_between_the_view_ray_and_the_shaded_normal(monkeypatch):
    model = _model_with(specular_view_angle=True, specular_background=False)
    assert model.specular_net.mlp[0].in_features == (SMALL.env_channels + 1) * 5
    result, features, _, _ = _inputs_of_the_specular_network(model, monkeypatch)
    rays, n = _rays_and_normals_of_the_shaded_region(result)
    cosine = (rays * n).sum(-1).abs().detach()
    assert len(rays) > 10 and features.shape == (len(rays), SMALL.env_channels + 1)
    torch.testing.assert_close(features[:, -1], cosine, rtol=0, atol=1e-5)
    assert float(cosine.min()) < 0.9 < float(cosine.max())  # a range of angles, not one value


def test_specular_background_sees_the_background_at_the_reflected_direction_without_a_gradient_into_it(
        monkeypatch):
    model = _model_with(specular_view_angle=False, specular_background=True)
    assert model.specular_net.mlp[0].in_features == (SMALL.env_channels + 3) * 5
    before, features, _, _ = _inputs_of_the_specular_network(model, monkeypatch)
    rays, n = _rays_and_normals_of_the_shaded_region(before)
    reflected = torch.nn.functional.normalize(rays - 2 * (rays * n).sum(-1, keepdim=True) * n, dim=-1)
    with torch.no_grad():
        for level in model.background_map.maps:
            level.normal_()
    after, features, _, _ = _inputs_of_the_specular_network(model, monkeypatch)
    # the render's reflected direction equals this one to float32 rounding, which the random map magnifies
    torch.testing.assert_close(features[:, -3:], model.background_map(reflected), rtol=0, atol=1e-4)
    assert (after.layers["spec"] - before.layers["spec"]).abs().max() > 1e-3  # C_spec follows B(w_r)
    after.layers["spec"].sum().backward()
    assert all(level.grad is None for level in model.background_map.maps)
    assert model.specular_net.mlp[0].weight.grad.abs().sum() > 0


def test_specular_mirror_blends_the_background_at_the_reflected_direction_into_c_spec_by_the_fifth_output(
        monkeypatch):
    model = _model_with(specular_view_angle=False, specular_background=False, specular_mirror=True)
    net = model.specular_net
    assert model.uses_mirror and net.mlp[-1].out_features == net.mirror_column + 1  # C_spec, (beta), m
    assert model.specular_net.mlp[0].in_features == SMALL.env_channels * 5  # B(w_r) is not an input here
    with torch.no_grad():
        for level in model.background_map.maps:
            level.normal_()
    head = model.specular_net.mlp[-1]
    spec = {}
    for name, bias in (("mirror", 30.0), ("network", -30.0)):
        with torch.no_grad():
            head.bias[net.mirror_column] = bias
        result, _, reflectance, mirror = _inputs_of_the_specular_network(model, monkeypatch)
        spec[name] = result.layers["spec"][(result.layers["shade"] > 0)[..., 0] & (result.layers["roi"] > 0)[..., 0]]
    rays, n = _rays_and_normals_of_the_shaded_region(result)
    reflected = torch.nn.functional.normalize(rays - 2 * (rays * n).sum(-1, keepdim=True) * n, dim=-1)
    # the render's reflected direction equals this one to float32 rounding, which the random map magnifies
    torch.testing.assert_close(mirror, model.background_map(reflected).detach(), rtol=0, atol=1e-4)
    # m = 1: a mirror of the background, scaled by the reflectance; m = 0: the network's colour alone
    torch.testing.assert_close(spec["mirror"], reflectance * mirror, rtol=1e-5, atol=1e-6)
    plain = _model_with(specular_view_angle=False, specular_background=False, specular_mirror=False)
    with torch.no_grad():
        for mine, theirs in zip(model.specular_net.mlp, plain.specular_net.mlp, strict=True):
            if isinstance(mine, torch.nn.Linear):
                theirs.weight.copy_(mine.weight[:theirs.out_features])
                theirs.bias.copy_(mine.bias[:theirs.out_features])
    alone = _render(plain).layers["spec"]
    torch.testing.assert_close(spec["network"], alone[(result.layers["shade"] > 0)[..., 0]
                                                      & (result.layers["roi"] > 0)[..., 0]], rtol=1e-5, atol=1e-6)
    assert (spec["mirror"] - spec["network"]).abs().max() > 1e-2
    # the mirror reads B without a gradient; the network's blend weight learns from C_spec
    with torch.no_grad():
        head.bias[net.mirror_column] = 0.0
    blended = _render(model)
    blended.layers["spec"].sum().backward()
    assert all(level.grad is None for level in model.background_map.maps)
    assert float(head.bias.grad[net.mirror_column].abs()) > 0 and torch.isfinite(head.bias.grad).all()


def test_schlick_fresnel_runs_from_the_normal_reflectance_head_on_to_one_at_grazing_with_finite_gradients():
    f0 = torch.tensor([0.0, 0.04, 0.5, 1.0], dtype=torch.float64, requires_grad=True)
    cos = torch.linspace(0, 1, 101, dtype=torch.float64, requires_grad=True)
    F = rtmodel.schlick_fresnel(f0[:, None], cos[None, :])
    torch.testing.assert_close(F[:, -1], f0.detach(), rtol=0, atol=1e-12)  # head-on: F0
    torch.testing.assert_close(F[:, 0], torch.ones(4, dtype=torch.float64), rtol=0, atol=1e-12)  # grazing: 1
    assert bool((F.diff(dim=1) <= 1e-12).all())  # never brighter head-on than at a more grazing angle
    assert float(F[1, 50].detach()) < 0.1  # glass (F0 0.04) reflects little at 60 degrees
    F.sum().backward()
    assert torch.isfinite(f0.grad).all() and torch.isfinite(cos.grad).all()


def test_fresnel_reflectance_reaches_the_network_as_schlick_of_the_surfel_reflectance_and_the_view_angle(
        monkeypatch):
    plain, features, reflectance, _ = _inputs_of_the_specular_network(
        _model_with(specular_view_angle=True, specular_background=False, specular_fresnel=False), monkeypatch)
    fresnel, features_f, reflectance_f, _ = _inputs_of_the_specular_network(
        _model_with(specular_view_angle=True, specular_background=False, specular_fresnel=True), monkeypatch)
    cosine = features[:, -1:]  # |cos| of the angle of incidence (the view-angle input)
    torch.testing.assert_close(features_f, features)
    torch.testing.assert_close(reflectance_f, reflectance + (1 - reflectance) * (1 - cosine) ** 5)
    assert float((reflectance_f - reflectance).detach().max()) > 1e-3  # some shaded pixels are seen at an angle
    assert (fresnel.layers["spec"] - plain.layers["spec"]).abs().max() > 1e-4


def _brute_distances(points: torch.Tensor, queries: torch.Tensor) -> torch.Tensor:
    """Exact float64 distances [M,N] from each query to each point (the oracle, no k-d tree, no cdist)."""
    return (queries.double()[:, None, :] - points.double()[None, :, :]).square().sum(-1).sqrt()


def _brute_scale(points: torch.Tensor, k: int = 3) -> torch.Tensor:
    n = points.shape[0]
    if n <= 1:
        return torch.full((n,), 0.01, dtype=torch.float64)
    d2 = _brute_distances(points, points).square()
    d2.fill_diagonal_(math.inf)
    return d2.topk(min(k, n - 1), largest=False).values.mean(-1).clamp_min(1e-7).sqrt()


def _brute_normals(points: torch.Tensor, k: int = 16) -> torch.Tensor:
    nearest = _brute_distances(points, points).topk(min(k, points.shape[0]), largest=False).indices
    neighbours = points.double()[nearest]
    centred = neighbours - neighbours.mean(1, keepdim=True)
    return torch.linalg.eigh(centred.transpose(1, 2) @ centred).eigenvectors[:, :, 0]


def _clouds() -> dict[str, torch.Tensor]:
    """Small clouds in float64: general position, with coincident points, tiny ones, on a line, on a plane."""
    g = torch.Generator().manual_seed(3)
    rand = lambda *shape: torch.rand(*shape, generator=g, dtype=torch.float64)  # noqa: E731
    general = rand(400, 3)
    duplicates = torch.cat([general[:300], general[:60], general[:5], general[:5]])  # pairs and quadruples
    direction = torch.nn.functional.normalize(torch.tensor([0.3, -1.0, 0.4], dtype=torch.float64), dim=0)
    line = torch.tensor([0.1, 0.2, 0.3], dtype=torch.float64) + rand(200, 1) * direction
    uv = rand(300, 2)
    plane = torch.stack([uv[:, 0], uv[:, 1], 0.5 * uv[:, 0] - 0.2 * uv[:, 1] + 1.0], -1)
    return {"general": general, "duplicates": duplicates, "line": line, "plane": plane, "one": rand(1, 3),
            "two": rand(2, 3), "three": rand(3, 3), "five": rand(5, 3), "all_coincident": rand(1, 3).repeat(20, 1)}


@pytest.mark.parametrize("name", list(_clouds()))
def test_neighbour_scales_equal_the_brute_force_ones(name):
    from rtsplat.model.surfels import nearest_neighbour_scale

    points = _clouds()[name]
    for k in (1, 3, 8):
        got = nearest_neighbour_scale(points, k=k)
        assert got.dtype == points.dtype and got.shape == (points.shape[0],) and torch.isfinite(got).all()
        torch.testing.assert_close(got, _brute_scale(points, k), rtol=1e-9, atol=1e-12)
    single = nearest_neighbour_scale(points.float())  # float32 in, float32 out
    assert single.dtype == torch.float32
    torch.testing.assert_close(single.double(), _brute_scale(points.float()), rtol=1e-5, atol=1e-7)


@pytest.mark.parametrize("name", list(_clouds()))
def test_nearest_neighbours_are_the_brute_force_nearest(name):
    from rtsplat.model.surfels import nearest_neighbours

    points = _clouds()[name]
    k = min(6, points.shape[0])
    distances, indices = nearest_neighbours(points, k, chunk=64)
    brute = _brute_distances(points, points)
    expected = brute.topk(k, largest=False).values
    torch.testing.assert_close(torch.from_numpy(distances), expected, rtol=1e-9, atol=1e-12)
    # the indices are k distinct points at those distances (which of equally far points: the tree's choice)
    index = torch.from_numpy(indices)
    torch.testing.assert_close(brute.gather(1, index), expected, rtol=1e-9, atol=1e-12)
    assert all(len(set(row)) == k for row in indices.tolist())
    queries = points[:7] + 0.01
    d_query, _ = nearest_neighbours(points, k, queries)
    torch.testing.assert_close(torch.from_numpy(d_query), _brute_distances(points, queries).topk(k, largest=False)
                               .values, rtol=1e-9, atol=1e-12)


@pytest.mark.parametrize("name", list(_clouds()))
def test_point_cloud_normals_equal_the_brute_force_ones(name):
    from rtsplat.model.surfels import point_cloud_normals

    points = _clouds()[name]
    normals = point_cloud_normals(points, chunk=50)
    assert normals.shape == points.shape and torch.isfinite(normals).all()
    torch.testing.assert_close(normals.norm(dim=1), torch.ones(len(points), dtype=torch.float64))
    if name == "line":  # every direction across the line is least spread: any of them, but across it
        direction = torch.nn.functional.normalize(points[-1] - points[0], dim=0)
        assert float((normals @ direction).abs().max()) < 1e-6
    elif name in ("one", "two"):
        assert normals.tolist() == [[0.0, 0.0, 1.0]] * len(points)
    elif name == "all_coincident":  # no spread at all: any unit vector will do
        pass
    else:  # the same neighbour sets (coincident points tie with identical coordinates) and the same axis
        cosine = (normals * _brute_normals(points)).sum(1).abs()
        assert float(cosine.min()) > 1 - 1e-9
    # normals at some of the points as queries: those of the whole cloud there
    some = point_cloud_normals(points, queries=points[::3])
    assert float((some * normals[::3]).sum(1).abs().min()) > 1 - 1e-9 or name in ("line", "all_coincident")


@pytest.mark.parametrize("specular", [True, False])
def test_view_independent_roi_gives_surfels_inside_the_region_their_degree_0_colour(specular):
    """With the specular branch, a surfel inside the region of interest has the same volume colour from
    every camera and its higher SH coefficients get no gradient; one outside keeps its view-dependent colour.
    Without the specular branch (plain 2DGS) nothing changes."""
    from rtsplat.camera import Camera

    model = _model(effects=ActiveEffects(specular=specular))
    model.settings = dataclasses.replace(model.settings, view_independent_roi=True)
    model.roi_radius.fill_(0.5)
    p = model.surfels
    with torch.no_grad():
        p.sh_rest.normal_(generator=torch.Generator().manual_seed(1))
    inside = (p.means - model.roi_center).norm(dim=-1) <= 0.5
    assert 0 < int(inside.sum()) < len(inside)
    base = small_camera(24, 18, torch.float32)
    turned = torch.eye(4)
    turned[:3, :3] = torch.linalg.matrix_exp(torch.tensor([[0.0, -0.4, 0.0], [0.4, 0.0, 0.0], [0.0, 0.0, 0.0]]))
    other = Camera(K=base.K, world_to_camera=base.world_to_camera @ turned, width=base.width, height=base.height)
    colours = [model.rasterizer_surfels(c).colors for c in (base, other)]
    moved = (colours[0] - colours[1]).abs().amax(-1)
    if specular:
        assert moved[inside].max() == 0 and moved[~inside].max() > 0.05
        colours[0][inside].sum().backward()
        assert p.sh_rest.grad[inside].abs().max() == 0 and p.sh_dc.grad[inside].abs().max() > 0
    else:
        assert moved[inside].max() > 0.05


@pytest.mark.parametrize("downsample", [1, 2])
def test_a_render_reads_the_background_by_kernel_as_by_its_torch_reference(monkeypatch, downsample):
    """The learned background is looked up at the pixels' rays (with autograd) and at the reflected directions
    (without); the kernels that read its levels give the render the image of the torch lookup and its levels'
    gradients, to float32 rounding (the lookups' logits are the same bits: tests/test_background_lookup.py)."""
    pytest.importorskip("numba")
    model = _model_with(specular_view_angle=False, specular_background=True)
    with torch.no_grad():
        for level in model.background_map.maps:
            level.normal_(generator=torch.Generator().manual_seed(5))
    camera = small_camera(24, 18, torch.float32)

    def render_and_gradients():
        model.zero_grad()
        result = model.render(camera, stage="full", backend="reference", specular_downsample=downsample)
        result.color.square().sum().backward()
        return [result.color.detach()] + [level.grad.clone() for level in model.background_map.maps]

    looked_up = []
    by_kernel = type(model.background_map)._logits_by_kernel
    monkeypatch.setattr(type(model.background_map), "_logits_by_kernel",
                        lambda self, u, v: looked_up.append(u.shape[0]) or by_kernel(self, u, v))
    kernel = render_and_gradients()
    assert len(looked_up) == 2  # the pixels' rays, then the reflected directions
    monkeypatch.setattr(type(model.background_map), "_logits_by_kernel", lambda self, u, v: None)
    reference = render_and_gradients()
    torch.testing.assert_close(kernel[0], reference[0], rtol=0, atol=1e-6)
    for a, b in zip(kernel[1:], reference[1:], strict=True):
        torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-6)
    assert kernel[1].abs().sum() > 0
