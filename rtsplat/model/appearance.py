"""Per-view appearance: the exposure and white balance a camera applied to one photo.

Phones and compact cameras pick exposure and white balance shot by shot, so the same surface has a
different colour in every photo. A per-view correction ``[6]`` = (log gain per channel, offset per
channel) maps the model's rendered colour to that photo's colour:

    photo ~ rendered * exp(log_gain) + offset

It is applied to the final image only (the model's layers stay in the scene's own colours), is the
identity at zero, and is finite for any finite input. The trainer learns one per training view and
fits one per test view (:func:`fit_appearance`), as it does for the views' poses; ``rtsplat render``
applies the stored ones.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

LOG_GAIN_LIMIT = 2.0  # exp(+-2): a 7x exposure change either way, beyond what a capture's auto-exposure does
MIN_POINTS_PER_VIEW = 20  # a view with fewer usable point colours gives no gain estimate
DARK = 0.04  # point or pixel colours below this (of 1) are left out: their ratios are mostly noise


def _gain(correction: Tensor) -> Tensor:
    """The per-channel gain of ``correction``, its log clamped to +-:data:`LOG_GAIN_LIMIT` so that a wild
    value cannot overflow."""
    return correction[:3].clamp(-LOG_GAIN_LIMIT, LOG_GAIN_LIMIT).exp()


def apply_appearance(color: Tensor, correction: Tensor) -> Tensor:
    """``color`` [..., 3] seen through ``correction`` [6] (log gain per channel, offset per channel)."""
    return color * _gain(correction) + correction[3:]


def remove_appearance(photo: Tensor, correction: Tensor) -> Tensor:
    """The inverse of :func:`apply_appearance`: ``photo`` brought back to the model's colours."""
    return (photo - correction[3:]) / _gain(correction)


def fit_appearance(rendered: Tensor, photo: Tensor, prior: float = 1e-2) -> Tensor:
    """The correction [6] that maps ``rendered`` [H, W, 3] closest to ``photo`` (least squares per
    channel, ``photo ~ gain * rendered + offset``), with a ridge of weight ``prior`` (relative to the
    pixel count) pulling gain to 1 and offset to 0, so that a flat render cannot take any gain.
    Closed form: the render does not depend on the correction, so no optimisation is needed."""
    x = rendered.detach().reshape(-1, 3).double()
    y = photo.detach().reshape(-1, 3).double()
    n = float(x.shape[0])
    lam = prior * n
    sx, sy, sxx, sxy = x.sum(0), y.sum(0), (x * x).sum(0), (x * y).sum(0)  # per channel
    # normal equations of (gain, offset) per channel, the ridge on (gain - 1) and offset
    a = torch.stack([torch.stack([sxx + lam, sx], -1), torch.stack([sx, torch.full_like(sx, n + lam)], -1)], -2)
    b = torch.stack([sxy + lam, sy], -1)
    gain = torch.linalg.solve(a, b)[:, 0].clamp(math.exp(-LOG_GAIN_LIMIT), math.exp(LOG_GAIN_LIMIT))
    offset = (sy - gain * sx) / (n + lam)  # the best offset for the (clamped) gain
    return torch.cat([gain.log(), offset]).to(rendered.dtype)


MEDIAN_ERROR = 1.2533  # the standard error of a median of normal samples, in units of sigma / sqrt(n)
MAD_SIGMA = 1.4826  # sigma of normal samples per unit of their median absolute deviation


@dataclass(frozen=True)
class GainEstimate:
    """A photo's log gain per channel measured at ``points`` point colours, and ``error``: the standard error
    of that measurement (the largest channel's), from how much the points' log ratios scatter (view-dependent
    colour, misplaced keypoints): ``MEDIAN_ERROR * MAD_SIGMA * MAD / sqrt(points)``. ``log_gain`` is None
    with fewer than :data:`MIN_POINTS_PER_VIEW` points (``error`` is then None too)."""

    log_gain: Tensor | None
    points: int
    error: float | None = None


def observed_log_gain(seen: Tensor, reference: Tensor) -> GainEstimate:
    """A photo's log gain per channel [3] from colours it shows of known points: the median over the
    points of ``log(seen / reference)`` (both [n, 3] in [0, 1]), leaving out points where either colour
    is darker than :data:`DARK`, with its standard error (:class:`GainEstimate`); no gain with fewer than
    :data:`MIN_POINTS_PER_VIEW` such points."""
    keep = (seen > DARK).all(-1) & (reference > DARK).all(-1)
    points = int(keep.sum())
    if points < MIN_POINTS_PER_VIEW:
        return GainEstimate(None, points)
    ratios = (seen[keep] / reference[keep]).log()
    gain = ratios.median(dim=0).values
    deviation = (ratios - gain).abs().median(dim=0).values
    error = float(MEDIAN_ERROR * MAD_SIGMA * deviation.max()) / math.sqrt(points)
    return GainEstimate(gain, points, error)
