"""The RT-Splatting composite and its layer algebra (paper section 3.2), as pure tensor functions.

    C = C_spec + beta * (tau * C_trans + (1 - tau) * C_scatter)

Images are [H,W,C]; ``roi`` [H,W,1] is the region-of-interest membership and ``shade`` [H,W,1] the
(boolean) pixels that are deferred-shaded. Outside the shaded region of interest a pixel shows the
plain volume radiance ``C_trans``. The final image splits into three additive layers,

    colour = reflection + transmission + scatter

with reflection the region's ``C_spec``, transmission ``beta * tau * C_trans`` (plus the plain
radiance outside the region) and scatter the rest, ``beta * (1 - tau) * C_scatter``. The model
(:mod:`rtsplat.model.rtmodel`), ``rtsplat render`` and ``rtsplat metrics`` all use these functions.
"""

from __future__ import annotations

import torch
from torch import Tensor


def subsurface_color(c_trans: Tensor, tau: Tensor, c_scatter: Tensor) -> Tensor:
    """``C_sub = tau C_trans + (1 - tau) C_scatter``: the light coming through the surface."""
    return tau * c_trans + (1.0 - tau) * c_scatter


def shaded_color(c_spec: Tensor, beta: Tensor, c_sub: Tensor) -> Tensor:
    """``C_spec + beta C_sub``: the composite of a deferred-shaded pixel."""
    return c_spec + beta * c_sub


def region_blend(inside: Tensor, c_trans: Tensor, roi: Tensor, shade: Tensor) -> Tensor:
    """``inside`` blended with the plain radiance by ROI membership where shaded; ``C_trans`` elsewhere."""
    return torch.where(shade, roi * inside + (1.0 - roi) * c_trans, c_trans)


def reflection_layer(c_spec: Tensor, roi: Tensor, shade: Tensor) -> Tensor:
    """The reflection layer: ``roi C_spec`` where shaded, zero elsewhere."""
    return torch.where(shade, roi * c_spec, torch.zeros_like(c_spec))


def transmission_layer(beta: Tensor, c_direct: Tensor, c_trans: Tensor, roi: Tensor, shade: Tensor) -> Tensor:
    """The transmission layer: ``roi beta c_direct + (1 - roi) C_trans`` where shaded, ``C_trans`` elsewhere.
    ``c_direct`` is ``tau C_trans`` (or ``C_sub`` when the model has no scatter term)."""
    return torch.where(shade, roi * beta * c_direct + (1 - roi) * c_trans, c_trans)


def scatter_layer(color: Tensor, reflection: Tensor, transmission: Tensor) -> Tensor:
    """The scatter layer: what the colour has beyond reflection and transmission."""
    return color - reflection - transmission


def compose_layers(reflection: Tensor, transmission: Tensor, scatter: Tensor) -> Tensor:
    """The colour from its three layers (the inverse of :func:`scatter_layer`)."""
    return reflection + transmission + scatter


def transmission_with_scatter(color: Tensor, reflection: Tensor) -> Tensor:
    """Everything but the reflection (``transmission + scatter``): the transmission layer as the
    synthetic scenes' ground truth defines it."""
    return color - reflection
