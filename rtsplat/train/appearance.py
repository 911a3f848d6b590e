"""Per-view appearance corrections (exposure, white balance), learnt with the model.

The correction of a view is :func:`rtsplat.model.appearance.apply_appearance`'s ``[6]`` (log gain and
offset per channel):

* training views: :class:`AppearanceCorrections`, learnt by Adam from the image loss, with a weak
  prior towards the identity (the model's colours and the views' gains are otherwise free to trade a
  common factor);
* test views: :func:`rtsplat.model.appearance.fit_appearance`, closed form on the render with the
  model fixed, as their poses are fitted.

Whether a scene needs them is decided from the data before training (:func:`appearance_spread`):
the SfM points are seen by many photos; a photo whose colours of those points sit consistently above
or below the points' own colours (their mean over all photos that saw them) was exposed or white-
balanced differently. Where the photos' gains spread by less than :data:`APPEARANCE_SPREAD` the
corrections stay off.
"""

from __future__ import annotations

import torch
from torch import Tensor

from rtsplat.camera import Camera

# effects.appearance auto: the spread of the photos' log gains (median absolute deviation across views,
# largest channel) from which a scene gets per-view corrections. Renders of a fixed camera measure
# 0.00-0.02 (view-dependent reflections and occlusion move single points, not a view's median); a
# 3% exposure step is 0.03 in log gain
APPEARANCE_SPREAD = 0.03
MIN_POINTS_PER_VIEW = 20  # a view with fewer usable point colours gives no gain estimate
DARK = 0.04  # point or pixel colours below this (of 1) are left out: their ratios are mostly noise


class AppearanceCorrections:
    """One learnt correction per training view (log gain, offset per channel), with its own Adam."""

    def __init__(self, count: int, lr: float, device=None):
        self.values = torch.zeros(count, 6, device=device, requires_grad=True)
        self.optimizer = torch.optim.Adam([self.values], lr=lr, eps=1e-15)

    def correction(self, index: int) -> Tensor:
        return self.values[index]

    def prior(self, index: int) -> Tensor:
        """The squared distance of view ``index``'s correction from the identity."""
        return self.values[index].square().sum()

    def step(self) -> None:
        self.optimizer.step()
        self.optimizer.zero_grad(set_to_none=True)

    def detached(self) -> Tensor:
        return self.values.detach().clone()

    def state_dict(self) -> dict:
        return {"values": self.detached(), "optimizer": self.optimizer.state_dict()}

    def load_state_dict(self, state: dict) -> None:
        with torch.no_grad():
            self.values.copy_(state["values"])
        self.optimizer.load_state_dict(state["optimizer"])


@torch.no_grad()
def view_log_gains(
    cameras: list[Camera], images: list[Tensor], masks: list[Tensor | None], xyz: Tensor, rgb: Tensor,
) -> Tensor:
    """[V, 3] each view's log gain against the SfM points' colours: the median over the points it sees
    (in front, inside the image, off the transparent mask, neither colour dark) of ``log(photo / point)``;
    NaN for a view with fewer than :data:`MIN_POINTS_PER_VIEW` such points."""
    out = torch.full((len(cameras), 3), float("nan"))
    for index, (camera, image, mask) in enumerate(zip(cameras, images, masks, strict=True)):
        points = xyz.to(camera.K)
        uv, z = camera.project(points)
        height, width = image.shape[:2]
        u, v = uv[:, 0].floor().long(), uv[:, 1].floor().long()
        inside = (z > 0) & (u >= 0) & (u < width) & (v >= 0) & (v < height) & torch.isfinite(uv).all(-1)
        u, v, colour = u[inside], v[inside], rgb.to(image)[inside.to(rgb.device)]
        seen = image[v, u]
        keep = (seen > DARK).all(-1) & (colour > DARK).all(-1)
        if mask is not None:
            keep &= mask[v, u, 0] < 0.5
        if int(keep.sum()) < MIN_POINTS_PER_VIEW:
            continue
        out[index] = (seen[keep] / colour[keep]).log().median(dim=0).values.float().cpu()
    return out


def appearance_spread(log_gains: Tensor) -> float | None:
    """The spread of the views' log gains: median absolute deviation from their median, per channel,
    the largest channel; None with fewer than 3 views that have a gain."""
    gains = log_gains[torch.isfinite(log_gains).all(-1)]
    if gains.shape[0] < 3:
        return None
    deviation = (gains - gains.median(dim=0).values).abs().median(dim=0).values
    return float(deviation.max())


def decide_appearance(mode: str, spread: float | None) -> tuple[bool, str]:
    """Whether the per-view corrections are learnt: ``on``/``off`` as configured; ``auto`` iff the
    photos' gains spread by at least :data:`APPEARANCE_SPREAD`."""
    measured = "not measurable (too few views see the SfM points)" if spread is None else f"{spread:.3f}"
    if mode != "auto":
        return mode == "on", f"config: {mode}; the photos' exposure spread is {measured}"
    if spread is None:
        return False, f"auto: the photos' exposure spread is {measured}"
    if spread >= APPEARANCE_SPREAD:
        return True, f"auto: the photos' exposure spread is {measured} (>= {APPEARANCE_SPREAD})"
    return False, f"auto: the photos' exposure spread is {measured} (< {APPEARANCE_SPREAD}: one exposure)"
