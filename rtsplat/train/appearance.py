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
balanced differently. ``rtsplat prepare`` measures each photo's log gain at the keypoints SfM tied to
3D points (``scene.json``'s ``exposure``: only where the photo really saw the point); for a prepared
scene without it the points are projected into the training images (:func:`view_log_gains`), which
also reads points hidden from a view and is noisier. Where the photos' gains spread by less than
:data:`APPEARANCE_SPREAD` (:data:`PROJECTED_SPREAD` for projected points) the corrections stay off.
"""

from __future__ import annotations

import torch
from torch import Tensor

from rtsplat.camera import Camera
from rtsplat.model.appearance import observed_log_gain

# effects.appearance auto: the spread of the photos' log gains (half the interquartile range across views,
# largest channel) from which a scene gets per-view corrections. From SfM's observations the synthetic
# scenes (one exposure) measure 0.000, two real phone captures 0.025 (22 of instant-ngp's fox photos) and
# 0.035 (22 of TranspNeRF's glass photos); the projected points, noisier, measure 0.019 on the
# one-exposure cabin, 0.019 on the fox and 0.049 on the glass, 0.006-0.018 on the trainer tests' toy scenes
APPEARANCE_SPREAD = 0.015
PROJECTED_SPREAD = 0.03  # the same for gains read from the projected points (a scene prepared without them)
MAX_POINTS = 100_000  # a larger cloud is read at every k-th point: a view's median needs far fewer


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
    NaN for a view with too few such points (:func:`rtsplat.model.appearance.observed_log_gain`). At most
    :data:`MAX_POINTS` points are read (every k-th of a larger cloud)."""
    out = torch.full((len(cameras), 3), float("nan"))
    stride = max(1, -(-xyz.shape[0] // MAX_POINTS))
    xyz, rgb = xyz[::stride], rgb[::stride]
    for index, (camera, image, mask) in enumerate(zip(cameras, images, masks, strict=True)):
        points = xyz.to(camera.K)
        uv, z = camera.project(points)
        height, width = image.shape[:2]
        u, v = uv[:, 0].floor().long(), uv[:, 1].floor().long()
        inside = (z > 0) & (u >= 0) & (u < width) & (v >= 0) & (v < height) & torch.isfinite(uv).all(-1)
        u, v, colour = u[inside], v[inside], rgb.to(image)[inside.to(rgb.device)]
        if mask is not None:
            clear = mask[v, u, 0] < 0.5
            u, v, colour = u[clear], v[clear], colour[clear]
        gain = observed_log_gain(image[v, u], colour)
        if gain is not None:
            out[index] = gain.float().cpu()
    return out


def scene_log_gains(exposure: dict[str, list[float] | None], names: list[str]) -> Tensor | None:
    """[V, 3] the prepared scene's measured log gains of the views ``names`` (NaN where it has none), or None
    when it measured none of them (a scene prepared without the measurement)."""
    if not any(name in exposure for name in names):
        return None
    nan = [float("nan")] * 3
    return torch.tensor([exposure.get(name) or nan for name in names], dtype=torch.float32)


def appearance_spread(log_gains: Tensor) -> float | None:
    """The spread of the views' log gains: half their interquartile range, per channel, the largest
    channel (for normally spread gains about their standard deviation's 0.67; two exposure levels, each
    in a quarter of the views or more, count in full; a few views with a wrong estimate do not); None
    with fewer than 3 views that have a gain."""
    gains = log_gains[torch.isfinite(log_gains).all(-1)]
    if gains.shape[0] < 3:
        return None
    quartiles = torch.quantile(gains.double(), torch.tensor([0.25, 0.75], dtype=torch.float64), dim=0)
    return float(((quartiles[1] - quartiles[0]) / 2).max())


def decide_appearance(mode: str, spread: float | None, source: str = "SfM observations",
                      threshold: float = APPEARANCE_SPREAD) -> tuple[bool, str]:
    """Whether the per-view corrections are learnt: ``on``/``off`` as configured; ``auto`` iff the
    photos' gains spread by at least ``threshold`` (:data:`APPEARANCE_SPREAD` for gains from SfM's
    observations, :data:`PROJECTED_SPREAD` for projected points). ``source`` names how they were read."""
    measured = ("not measurable (too few views see the SfM points)" if spread is None
                else f"{spread:.3f} (from {source})")
    if mode != "auto":
        return mode == "on", f"config: {mode}; the photos' exposure spread is {measured}"
    if spread is None:
        return False, f"auto: the photos' exposure spread is {measured}"
    if spread >= threshold:
        return True, f"auto: the photos' exposure spread is {measured} (>= {threshold})"
    return False, f"auto: the photos' exposure spread is {measured} (< {threshold}: one exposure)"
