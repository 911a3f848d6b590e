"""The specular network's bfloat16 pass on a CPU (BFloat16Network and its numba kernels) against the torch
reference (SpecularNetwork.mlp_outputs_reference under autocast) and torch's own bfloat16 ops."""

import numpy as np
import pytest
import torch

from rtsplat.model import specular
from rtsplat.model.specular import BFloat16Network, SpecularNetwork, bucketed_rows
from rtsplat.raster.numba_runtime import load_numba_module

kernels = load_numba_module("rtsplat.model.specular_kernels")
pytestmark = pytest.mark.skipif(kernels is None, reason="numba is not installed")

EVERY_PATTERN = torch.arange(-32768, 32768, dtype=torch.int32).to(torch.int16)  # all 65536 bfloat16 patterns


def features(rows: int, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    generator = torch.Generator().manual_seed(seed)
    env = torch.randn(rows, 20, generator=generator).requires_grad_()
    material = torch.nn.functional.normalize(torch.randn(rows, 4, generator=generator), dim=-1).requires_grad_()
    return env, material


def outputs_and_gradients(net: SpecularNetwork, run, env, material, seed: int = 1) -> list[torch.Tensor]:
    net.zero_grad()
    env.grad = material.grad = None
    out = run(env, material)
    weights = torch.randn(out.shape, generator=torch.Generator().manual_seed(seed))
    (out * weights).sum().backward()
    return [out.detach(), env.grad, material.grad, *(p.grad for p in net.mlp.parameters())]


@pytest.mark.parametrize("rows", [1, 1023, 1500, 6144])
@pytest.mark.parametrize("options", [{}, {"attenuation": "material"}, {"mirror": True, "near_weight": True}])
def test_the_kernel_pass_gives_the_reference_outputs_and_weight_gradients_bit_for_bit(rows, options):
    torch.manual_seed(rows)
    net = SpecularNetwork(20, 4, 64, "bfloat16", **options)
    env, material = features(rows)
    out = net.mlp_outputs(env, material)
    assert type(out.grad_fn).__name__ == "BFloat16NetworkBackward"
    mine = outputs_and_gradients(net, net.mlp_outputs, env, material)
    reference = outputs_and_gradients(net, net.mlp_outputs_reference, env, material)
    assert mine[0].shape == (rows, net.mlp[-1].out_features) and mine[0].dtype == torch.float32
    for name, a, b in zip(["outputs", "w1", "b1", "w2", "b2", "w3", "b3"], mine[:1] + mine[3:],
                          reference[:1] + reference[3:], strict=True):
        assert a.dtype == b.dtype == torch.float32, name
        assert torch.equal(a, b), name
    # the features' gradients: the same sums in float64 instead of float32
    for a, b in zip(mine[1:3], reference[1:3], strict=True):
        torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-7)
        assert torch.isfinite(a).all()


@pytest.mark.parametrize("suffix", ["", "_serial"])
def test_the_input_rows_are_the_outer_product_and_the_features_rounded_as_torch_rounds(suffix):
    env, material = features(700, seed=3)
    env, material = env.detach().clone(), material.detach().clone()
    # ties between two bfloat16 values (both ways), the largest float32, infinities and NaN
    env[0, :6] = torch.tensor([1.0 + 2.0**-8, 1.0 + 3 * 2.0**-8, -(1.0 + 2.0**-8), 3.4e38, float("inf"), float("nan")])
    material[1] = torch.tensor([float("-inf"), 0.0, -0.0, 1e-40])
    rows = bucketed_rows(700)
    x = torch.empty(rows, 100, dtype=torch.bfloat16)
    getattr(kernels, "network_input_kernel" + suffix)(env.numpy(), material.numpy(), rows,
                                                      x.view(torch.int16).numpy().view(np.uint16))
    expected = torch.cat([(env[:, :, None] * material[:, None, :]).flatten(1), env], -1).to(torch.bfloat16)
    nan = expected.isnan()
    assert torch.equal(x[:700].isnan(), nan) and nan.sum() == 5  # a NaN's payload may differ: torch's vector
    assert torch.equal(x[:700].view(torch.int16)[~nan], expected.view(torch.int16)[~nan])  # path keeps it
    assert torch.equal(x[700:].view(torch.int16), torch.zeros(rows - 700, 100, dtype=torch.int16))


@pytest.mark.parametrize("suffix", ["", "_serial"])
def test_the_relu_kernels_match_torch_on_every_bfloat16_pattern(suffix):
    h = EVERY_PATTERN.clone().reshape(256, 256)
    getattr(kernels, "relu_kernel" + suffix)(h.numpy())
    expected = torch.relu(EVERY_PATTERN.view(torch.bfloat16)).reshape(256, 256)
    mine = h.view(torch.bfloat16)
    assert torch.equal(mine.isnan(), expected.isnan())
    assert torch.equal(mine.nan_to_num(), expected.nan_to_num())
    grad = torch.randn(256, 256).to(torch.bfloat16)
    kept = grad.clone()
    getattr(kernels, "relu_grad_kernel" + suffix)(kept.view(torch.int16).numpy(),
                                                  EVERY_PATTERN.reshape(256, 256).numpy())
    reference = torch.ops.aten.threshold_backward(grad, EVERY_PATTERN.view(torch.bfloat16).reshape(256, 256), 0)
    assert torch.equal(kept.view(torch.int16), reference.view(torch.int16))


def test_the_parallel_and_the_serial_kernels_give_the_same_bits(monkeypatch):
    net = SpecularNetwork(20, 4, 64, "bfloat16")
    env, material = features(3000, seed=7)
    serial = outputs_and_gradients(net, net.mlp_outputs, env, material)
    threads = torch.get_num_threads()
    monkeypatch.setattr(specular, "PARALLEL_ROWS", 1)
    torch.set_num_threads(2)
    try:
        parallel = outputs_and_gradients(net, net.mlp_outputs, env, material)
    finally:
        torch.set_num_threads(threads)
    assert all(torch.equal(a, b) for a, b in zip(serial, parallel, strict=True))
    assert specular._specular_kernels(2, 1).relu_kernel is kernels.relu_kernel
    assert specular._specular_kernels(1, 10**6).relu_kernel is kernels.relu_kernel_serial


def test_a_non_finite_feature_spoils_the_rows_the_reference_spoils_and_no_others():
    net = SpecularNetwork(20, 4, 64, "bfloat16")
    env, material = features(300, seed=5)
    env = env.detach().clone()
    env[7, 2] = float("nan")
    env[99, 0] = float("inf")
    out = net.mlp_outputs(env.requires_grad_(), material)
    reference = net.mlp_outputs_reference(env, material)
    spoiled = ~torch.isfinite(out).all(-1)
    assert torch.equal(spoiled, ~torch.isfinite(reference).all(-1))
    # oneDNN's bfloat16 products read rows in pairs, so a NaN may reach the row beside its own
    rows = spoiled.nonzero().flatten().tolist()
    assert {7, 99} <= set(rows) and all(min(abs(r - 7), abs(r - 99)) <= 1 for r in rows)
    assert torch.equal(out[~spoiled], reference[~spoiled])


def test_the_kernel_pass_runs_only_where_it_applies(monkeypatch):
    calls = []
    monkeypatch.setattr(BFloat16Network, "apply", lambda *args: calls.append(1) or specular.SpecularNetwork
                        .mlp_outputs_reference(net, *args[:2]))
    env, material = features(50)
    net = SpecularNetwork(20, 4, 16, "bfloat16")
    net.mlp_outputs(env, material)
    assert len(calls) == 1
    with torch.no_grad():  # inference: the sliced MLP of the reference
        net.mlp_outputs(env, material)
    SpecularNetwork(20, 4, 16, "float32").mlp_outputs(env, material)
    net.double().mlp_outputs(env.double(), material.double())  # float64: autocast leaves it in float64
    assert len(calls) == 1


def test_an_empty_batch_gives_empty_outputs_and_zero_gradients():
    net = SpecularNetwork(20, 4, 16, "bfloat16")
    env, material = features(0)
    out = net.mlp_outputs(env, material)
    assert out.shape == (0, 4)
    out.sum().backward()
    assert env.grad.shape == (0, 20)
    assert all(torch.equal(p.grad, torch.zeros_like(p)) for p in net.mlp.parameters())
