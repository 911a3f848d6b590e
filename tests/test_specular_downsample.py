"""The specular shading at a reduced resolution (``RTModel.render(specular_downsample=f)``, the trainer's
``schedule.specular_coarse_share``): the network shades f x f blocks from their mean inputs and every pixel reads
C_spec and beta interpolated from the shaded blocks. The block means and the interpolation are checked against
sums written out here; the shading against the full-resolution shading on smooth inputs; the schedule and the
trainer against the plan."""

from __future__ import annotations

import pytest
import torch
import torch.nn.functional as F
from specular_inputs import recorded_toy_training, small_specular_model

from rtsplat.camera import Camera
from rtsplat.errors import ConfigError
from rtsplat.model.rtmodel import block_mean, image_ray_directions, upsampled_from_blocks
from rtsplat.train_config import SPECULAR_COARSE_FACTOR, TrainConfig


def test_block_means_average_the_pixels_each_block_holds_at_the_edges_too():
    g = torch.Generator().manual_seed(0)
    image = torch.rand(5, 7, 2, generator=g)
    means = block_mean(image, 2)
    assert means.shape == (3, 4, 2)
    for i in range(3):
        for j in range(4):
            block = image[2 * i:2 * i + 2, 2 * j:2 * j + 2].reshape(-1, 2)  # 1, 2 or 4 pixels at the edges
            torch.testing.assert_close(means[i, j], block.mean(0))


def test_interpolation_reproduces_a_linear_field_between_the_block_centres():
    """Bilinear interpolation is exact on a linear function: so the blocks' values sit at their centres."""
    f, h, w = 2, 6, 8
    rows = (torch.arange(h, dtype=torch.float64) * f + (f - 1) / 2)[:, None].expand(h, w)
    cols = (torch.arange(w, dtype=torch.float64) * f + (f - 1) / 2)[None, :].expand(h, w)
    values = torch.stack([3.0 * rows - 2.0 * cols + 1.0, rows], -1)
    out = upsampled_from_blocks(values, torch.ones(h, w, 1, dtype=torch.float64), f, (h * f, w * f))
    y = torch.arange(h * f, dtype=torch.float64)[:, None].expand(h * f, w * f)
    x = torch.arange(w * f, dtype=torch.float64)[None, :].expand(h * f, w * f)
    inner = (slice(f // 2, h * f - f // 2), slice(f // 2, w * f - f // 2))  # between the outermost centres
    torch.testing.assert_close(out[..., 0][inner], (3.0 * y - 2.0 * x + 1.0)[inner])
    torch.testing.assert_close(out[..., 1][inner], y[inner])


def test_blocks_of_weight_zero_neither_dim_nor_tint_their_neighbours():
    g = torch.Generator().manual_seed(1)
    weight = (torch.rand(5, 6, 1, generator=g) > 0.4).to(torch.float64)
    values = torch.where(weight > 0, torch.full((5, 6, 3), 0.3, dtype=torch.float64),
                         torch.full((5, 6, 3), 1e6, dtype=torch.float64))
    out = upsampled_from_blocks(values, weight, 2, (10, 11))
    reads_a_shaded_block = upsampled_from_blocks(weight, torch.ones_like(weight), 2, (10, 11)) > 0
    torch.testing.assert_close(out[reads_a_shaded_block.expand(-1, -1, 3)],
                               torch.full_like(out[reads_a_shaded_block.expand(-1, -1, 3)], 0.3))
    assert (out[~reads_a_shaded_block.expand(-1, -1, 3)] == 0).all()
    # the pixels of a shaded block read it with a weight of at least 9/16
    one_hot = torch.zeros(5, 6, 1, dtype=torch.float64)
    one_hot[2, 3] = 1.0
    spread = upsampled_from_blocks(one_hot, torch.ones_like(one_hot), 2, (10, 11))
    assert spread[4:6, 6:8].min() >= 9 / 16 - 1e-12


def _smooth_inputs(height: int, width: int):
    """Inputs that vary slowly over the image: the normals turn by a few degrees across it, the surface's
    material, roughness and reflectance are the same everywhere; alpha 1 except a corner of uncovered pixels."""
    K = torch.tensor([[40.0, 0, width / 2], [0, 40.0, height / 2], [0, 0, 1]])
    camera = Camera(K, torch.eye(4), width, height)
    y = torch.linspace(-1, 1, height)[:, None, None].expand(height, width, 1)
    x = torch.linspace(-1, 1, width)[None, :, None].expand(height, width, 1)
    # tilted by 45 degrees, so that the reflected rays run near the horizon, far from the map's poles
    normal = F.normalize(torch.cat([0.1 * x, 0.1 * y - 1, -torch.ones_like(x)], -1), dim=-1).requires_grad_()
    alpha = torch.ones(height, width, 1)
    alpha[:4, :5] = 0.0
    # the rasterizer's channels are blended with the surface weights: a surface's value times its alpha
    gbuf = {"roughness": (0.3 * alpha).requires_grad_(),
            "material": (torch.tensor([0.5, -0.2, 0.1, 0.8]) * alpha).requires_grad_(),
            "reflectance": (0.4 * alpha).requires_grad_()}
    return camera, normal, alpha, gbuf, alpha > 0.5


@pytest.mark.parametrize("every_pixel", [False, True])
def test_the_downsampled_shading_follows_the_full_one_on_smooth_inputs_and_passes_finite_gradients(every_pixel):
    with torch.random.fork_rng():
        torch.manual_seed(0)  # the network's initial weights
        model = small_specular_model()
    H, W = 21, 26
    camera, normal, alpha, gbuf, wanted = _smooth_inputs(H, W)
    rays = image_ray_directions(camera)
    full_spec, full_beta = model._specular(camera, normal, gbuf, alpha.clamp_min(1e-6), wanted, rays=rays,
                                           every_pixel=every_pixel)
    spec, beta = model._specular_downsampled(camera, normal, gbuf, alpha, wanted, rays, None, 2, 1.0, None)
    assert (spec[~wanted.expand(-1, -1, 3)] == 0).all() and (beta[~wanted] == 1).all()
    shaded = wanted.expand(-1, -1, 3)
    error = (spec - full_spec)[shaded].abs().max()
    spread = full_spec[shaded].max() - full_spec[shaded].min()
    assert spread > 0.01  # the shading does vary over the image
    assert error < 0.03 * spread  # about 1% here; a one-pixel shift of the blocks would be about 4%
    torch.testing.assert_close(beta[wanted], full_beta[wanted], rtol=0.02, atol=1e-3)
    leaves = [normal, *gbuf.values(), model.env.features, *model.specular_net.parameters()]
    grads = torch.autograd.grad((spec * torch.rand_like(spec)).sum() + beta.sum(), leaves, allow_unused=True)
    assert all(grad is None or torch.isfinite(grad).all() for grad in grads)
    normal_grad = grads[0].abs().sum(-1)
    assert (normal_grad[wanted[..., 0]] > 0).all()  # every shaded pixel's inputs feed its block's shading
    assert grads[5] is not None and grads[5].abs().sum() > 0  # the network's first layer


def test_no_shaded_pixel_and_uncovered_blocks_stay_finite():
    model = small_specular_model()
    camera, normal, alpha, gbuf, _ = _smooth_inputs(9, 11)
    rays = image_ray_directions(camera)
    nothing = torch.zeros(9, 11, 1, dtype=torch.bool)
    spec, beta = model._specular_downsampled(camera, normal, gbuf, torch.zeros_like(alpha), nothing, rays, None,
                                             3, 1.0, None)
    assert (spec == 0).all() and (beta == 1).all()


def test_the_render_checks_the_factor():
    model = small_specular_model()
    camera = Camera(torch.tensor([[20.0, 0, 8], [0, 20.0, 6], [0, 0, 1]]), torch.eye(4), 16, 12)
    with pytest.raises(ValueError, match="specular_downsample"):
        model.render(camera, specular_downsample=0)


def test_the_schedule_shades_the_first_share_of_the_full_stage_coarsely():
    def schedule(**values):
        return TrainConfig.from_dict({"schedule": values}).validate().schedule

    s = schedule(iterations=750, volume_until=125, specular_from=250)
    factors = {it: s.specular_downsample_at(it) for it in (1, 250, 251, 500, 501, 750)}
    assert factors == {1: 1, 250: 1, 251: SPECULAR_COARSE_FACTOR, 500: SPECULAR_COARSE_FACTOR, 501: 1, 750: 1}
    assert {schedule(specular_coarse_share=0.0).specular_downsample_at(it) for it in range(1, 3001, 7)} == {1}
    whole = schedule(iterations=100, specular_from=10, volume_until=5, specular_coarse_share=1.0)
    assert [whole.specular_downsample_at(it) for it in (10, 11, 100)] == [1, 2, 2]
    for bad in (-0.1, 1.5):
        with pytest.raises(ConfigError, match="specular_coarse_share"):
            schedule(specular_coarse_share=bad)


def test_the_trainer_shades_coarsely_where_the_schedule_says_and_trains_finite(tmp_path):
    trainer, renders, summary = recorded_toy_training(tmp_path, 8, {"specular_coarse_share": 0.5})
    calls = [kwargs.get("specular_downsample") for kwargs in renders]
    assert calls[:8] == [1, 1, 2, 2, 2, 1, 1, 1]  # the full stage is iterations 3-8; its first half coarse
    assert torch.isfinite(torch.tensor(summary["test_psnr"]))
    assert all(torch.isfinite(p).all() for p in trainer.model.parameters())
