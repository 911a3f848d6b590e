"""The surfels' Adam groups: each moves at the rate its setting gives."""

from __future__ import annotations

import pytest
import torch

from rtsplat.model.surfels import init_from_points
from rtsplat.train.optim import build_optimizer, learning_rate_key
from rtsplat.train_config import TrainConfig


def _first_step(lr_options: dict) -> dict[str, float]:
    """How far one Adam step moves each surfel parameter (the largest change), from a gradient of ones."""
    g = torch.Generator().manual_seed(0)
    surfels = init_from_points(torch.rand(8, 3, generator=g), torch.rand(8, 3, generator=g), sh_degree=2,
                               generator=g)
    lr = TrainConfig.from_dict({"lr": lr_options}).lr
    optimizer = build_optimizer(torch.nn.Module(), surfels, lr, 1.0)
    before = {name: p.detach().clone() for name, p in surfels.named_parameters()}
    for p in surfels.parameters():
        p.grad = torch.ones_like(p)
    optimizer.step()
    return {name: float((p.detach() - before[name]).abs().max()) for name, p in surfels.named_parameters()}


@pytest.mark.parametrize("sh_rest", [None, 0.003])
def test_the_view_dependent_colour_moves_at_its_own_rate_or_a_twentieth_of_the_dc_rate(sh_rest):
    moved = _first_step({"sh_dc": 0.004, "sh_rest": sh_rest})
    # Adam's first step moves every value by its rate (the gradient's sign times lr, up to eps)
    assert moved["sh_dc"] == pytest.approx(0.004, rel=1e-4)
    assert moved["sh_rest"] == pytest.approx(0.004 / 20 if sh_rest is None else sh_rest, rel=1e-4)


def test_a_divergence_names_the_setting_of_the_view_dependent_colour():
    assert learning_rate_key("sh_rest") == "lr.sh_rest"
    assert learning_rate_key("sh_dc") == "lr.sh_dc"
