"""The sampled specular gradient (``schedule.specular_gradient_share``): a training render differentiates the
specular network at a random share of the shaded pixels only. The image is the same; the gradient is the full
gradient of the sampled pixels scaled by 1/share (so its expected value is the full gradient); share 1 is the
exact gradient and draws nothing; the default is a quarter under a time budget on the CPU; the trainer passes
the share and its own generator."""

from __future__ import annotations

import pytest
import torch
from specular_inputs import recorded_toy_training, small_specular_model, specular_inputs

from rtsplat.errors import ConfigError
from rtsplat.train_config import TrainConfig

H, W = 24, 30


def _model():
    return small_specular_model()


def _inputs():
    return specular_inputs(H, W)


def _specular_and_gradients(model, share, every_pixel, *, seed=0, pixel_weights=None):
    """C_spec, beta and the gradients of a weighted sum of both into the inputs and the network's parameters,
    with the sample drawn from a generator seeded with ``seed``."""
    camera, normal, alpha, gbuf, shade = _inputs()
    generator = torch.Generator().manual_seed(seed)
    spec, beta = model._specular(camera, normal, gbuf, alpha, shade, every_pixel=every_pixel,
                                 gradient_share=share, generator=generator)
    weights = torch.linspace(0.5, 1.5, H * W * 4).reshape(H, W, 4)
    if pixel_weights is not None:
        weights = weights * pixel_weights
    loss = (torch.cat([spec, beta], -1) * weights).sum()
    leaves = [normal, *gbuf.values(), model.env.features, *model.specular_net.parameters()]
    grads = torch.autograd.grad(loss, leaves, allow_unused=True)
    grads = [torch.zeros_like(leaf) if grad is None else grad for leaf, grad in zip(leaves, grads, strict=True)]
    return spec.detach(), beta.detach(), grads, shade


@pytest.mark.parametrize("every_pixel", [False, True])
def test_a_sampled_gradient_leaves_the_image_unchanged_and_is_the_sampled_pixels_full_gradient_over_the_share(
        every_pixel):
    model = _model()
    share = 0.25
    spec1, beta1, full, shade = _specular_and_gradients(model, 1.0, every_pixel)
    spec, beta, sampled, _ = _specular_and_gradients(model, share, every_pixel)
    torch.testing.assert_close(spec, spec1, rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(beta, beta1, rtol=1e-5, atol=1e-6)
    # the pixels that passed a gradient: those whose normal got one
    tracked = sampled[0].abs().sum(-1, keepdim=True) > 0
    assert not (tracked & ~shade).any()
    n_shaded, n_tracked = int(shade.sum()), int(tracked.sum())
    assert 0.15 * n_shaded < n_tracked < 0.35 * n_shaded  # about a quarter of 430 shaded pixels
    # the full gradient of a loss that weighs only the tracked pixels, times 1/share: the same gradient
    _, _, restricted, _ = _specular_and_gradients(model, 1.0, every_pixel, pixel_weights=tracked.float())
    for got, expected in zip(sampled, restricted, strict=True):
        assert torch.isfinite(got).all()
        torch.testing.assert_close(got, expected / share, rtol=1e-4, atol=1e-6)


def test_the_sample_follows_the_generator_and_its_mean_approaches_the_full_gradient():
    model = _model()
    _, _, full, _ = _specular_and_gradients(model, 1.0, False)
    draws = [_specular_and_gradients(model, 0.5, False, seed=seed)[2] for seed in range(40)]
    again = _specular_and_gradients(model, 0.5, False, seed=0)[2]
    for a, b in zip(draws[0], again, strict=True):
        assert torch.equal(a, b)
    assert not torch.equal(draws[0][0], draws[1][0])
    normal_full = full[0]
    one = (draws[0][0] - normal_full).norm() / normal_full.norm()
    mean = (torch.stack([d[0] for d in draws]).mean(0) - normal_full).norm() / normal_full.norm()
    # a single draw of half the pixels is off by about 1 (relative); the mean of 40 by about 1/sqrt(40)
    assert one > 0.5 and mean < 0.3 and mean < one / 3


def test_share_one_and_no_autograd_draw_nothing_and_give_the_exact_gradient():
    model = _model()
    camera, normal, alpha, gbuf, shade = _inputs()
    generator = torch.Generator().manual_seed(0)
    state = generator.get_state()
    exact = model._specular(camera, normal, gbuf, alpha, shade)
    same = model._specular(camera, normal, gbuf, alpha, shade, gradient_share=1.0, generator=generator)
    with torch.no_grad():
        model._specular(camera, normal, gbuf, alpha, shade, gradient_share=0.3, generator=generator)
    assert torch.equal(generator.get_state(), state)
    for a, b in zip(exact, same, strict=True):
        assert torch.equal(a, b)
    with pytest.raises(ValueError, match="gradient_share"):
        model._specular(camera, normal, gbuf, alpha, shade, gradient_share=0.0)


def test_the_default_share_is_a_quarter_under_a_time_budget_where_sampling_saves_time_and_every_pixel_else():
    def share(saves=True, **schedule):
        schedule = TrainConfig.from_dict({"schedule": schedule}).validate().schedule
        return schedule.resolved_specular_gradient_share(saves)

    assert share() == 1.0
    assert share(seconds=60) == 0.25
    # a GPU evaluates every pixel anyway, and a CPU with AMX tiles runs the network's backward cheaply: no saving
    assert share(saves=False, seconds=60) == 1.0
    assert share(specular_gradient_share=0.5) == 0.5
    assert share(saves=False, specular_gradient_share=0.5) == 0.5
    assert share(seconds=60, specular_gradient_share=1.0) == 1.0
    for bad in (0.0, 1.5):
        with pytest.raises(ConfigError, match="specular_gradient_share"):
            share(specular_gradient_share=bad)


def test_the_trainer_renders_with_the_share_and_its_own_generator_and_reports_it(tmp_path):
    trainer, renders, summary = recorded_toy_training(tmp_path, 9, {"specular_gradient_share": 0.25})
    calls = [(kwargs.get("specular_gradient_share"), kwargs.get("generator")) for kwargs in renders]
    assert [share for share, _ in calls[:9]] == [0.25] * 9
    assert all(generator is trainer.rng for _, generator in calls[:9])
    assert torch.isfinite(torch.tensor(summary["test_psnr"]))
    assert all(torch.isfinite(p).all() for p in trainer.model.parameters())
    assert summary["specular_gradient_share"] == 0.25


def test_a_sampled_render_reads_one_texel_table_and_leaves_none_that_goes_stale(monkeypatch):
    """Both sets of pixels read one mip pyramid of the environment map; and none is kept: after the
    optimizer's fused step (which changes the map without moving its version counter) a lookup without
    autograd, as an evaluation makes, reads the new map."""
    model = _model()
    built = []
    texel_table = type(model.env).texel_table
    monkeypatch.setattr(type(model.env), "texel_table",
                        lambda self, levels=None: built.append(levels) or texel_table(self, levels))
    _, _, grads, _ = _specular_and_gradients(model, 0.25, False)
    env_gradient = grads[4]  # the leaves: the normal, three G-buffer channels, the map, the network's
    assert len(built) == 1 and env_gradient.abs().sum() > 0
    optimizer = torch.optim.Adam([model.env.features], lr=0.5, fused=True)
    model.env.features.grad = env_gradient
    optimizer.step()
    g = torch.Generator().manual_seed(1)
    directions = torch.nn.functional.normalize(torch.randn(200, 3, generator=g), dim=-1)
    roughness = torch.rand(200, generator=g)
    with torch.no_grad():
        evaluated = model.env(directions, roughness)
    assert torch.equal(evaluated, model.env(directions, roughness).detach())  # with autograd: a table built anew
