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

The measurement is only as good as the observations it rests on: a view whose photo is mostly glass has
few keypoints outside it, and a median over few noisy colours scatters from view to view by itself. Each
view's gain comes with its standard error (:class:`rtsplat.model.appearance.GainEstimate`), from which
:func:`exposure_spread` computes the spread that the errors alone would give (``noise``); the decision
(:func:`decide_appearance`) counts only the spread beyond that noise, stays off when the noise alone
reaches the threshold ("too few reliable observations"), and says how confident it is.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

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
NORMAL_HALF_IQR = 0.6745  # half the interquartile range of a unit normal: the spread of gains that differ by noise


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


@dataclass(frozen=True)
class ViewGains:
    """Views' measured log gains ``[V, 3]`` (NaN where a view has none), how many observations each used
    ``[V]`` and the gains' standard errors ``[V]`` (NaN where none); ``points`` and ``errors`` are None for a
    scene prepared before they were recorded."""

    log_gains: Tensor
    points: Tensor | None = None
    errors: Tensor | None = None


@torch.no_grad()
def view_log_gains(
    cameras: list[Camera], images: list[Tensor], masks: list[Tensor | None], xyz: Tensor, rgb: Tensor,
) -> ViewGains:
    """Each view's log gain against the SfM points' colours: the median over the points it sees (in front,
    inside the image, off the transparent mask, neither colour dark) of ``log(photo / point)``, with the
    number of such points and the gain's standard error; NaN for a view with too few such points
    (:func:`rtsplat.model.appearance.observed_log_gain`). At most :data:`MAX_POINTS` points are read (every
    k-th of a larger cloud)."""
    out = torch.full((len(cameras), 3), float("nan"))
    points = torch.zeros(len(cameras), dtype=torch.long)
    errors = torch.full((len(cameras),), float("nan"))
    stride = max(1, -(-xyz.shape[0] // MAX_POINTS))
    xyz, rgb = xyz[::stride], rgb[::stride]
    for index, (camera, image, mask) in enumerate(zip(cameras, images, masks, strict=True)):
        projected = xyz.to(camera.K)
        uv, z = camera.project(projected)
        height, width = image.shape[:2]
        u, v = uv[:, 0].floor().long(), uv[:, 1].floor().long()
        inside = (z > 0) & (u >= 0) & (u < width) & (v >= 0) & (v < height) & torch.isfinite(uv).all(-1)
        u, v, colour = u[inside], v[inside], rgb.to(image)[inside.to(rgb.device)]
        if mask is not None:
            clear = mask[v, u, 0] < 0.5
            u, v, colour = u[clear], v[clear], colour[clear]
        estimate = observed_log_gain(image[v, u], colour)
        points[index] = estimate.points
        if estimate.log_gain is not None:
            out[index] = estimate.log_gain.float().cpu()
            errors[index] = estimate.error
    return ViewGains(out, points, errors)


def scene_log_gains(exposure: dict[str, list[float] | None], names: list[str],
                    points: dict[str, int] | None = None, errors: dict[str, float | None] | None = None,
                    ) -> ViewGains | None:
    """The prepared scene's measured log gains of the views ``names`` (NaN where it has none), with their
    observation counts and standard errors where the scene recorded them (``exposure_points``,
    ``exposure_error``), or None when it measured none of the views (a scene prepared without the
    measurement)."""
    if not any(name in exposure for name in names):
        return None
    nan = [float("nan")] * 3
    gains = torch.tensor([exposure.get(name) or nan for name in names], dtype=torch.float32)
    recorded = bool(points) and bool(errors) and all(name in points for name in names)
    if not recorded:
        return ViewGains(gains)
    error = [errors.get(name) for name in names]
    return ViewGains(gains, torch.tensor([int(points[name]) for name in names], dtype=torch.long),
                     torch.tensor([float("nan") if e is None else float(e) for e in error], dtype=torch.float32))


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


@dataclass(frozen=True)
class ExposureSpread:
    """What :func:`exposure_spread` measured: the views' ``spread`` (:func:`appearance_spread`, None with fewer
    than 3 views that have a gain), how many ``views`` have a gain, the median number of ``observations`` per
    view (all views, those without a gain too) and the ``noise``: the spread the gains' standard errors alone
    would give (half the interquartile range of normal errors of the views' median standard error);
    ``observations`` and ``noise`` are None where the scene did not record the counts and errors."""

    spread: float | None
    views: int
    observations: int | None = None
    noise: float | None = None

    @property
    def beyond_noise(self) -> float | None:
        """The spread that the noise does not explain: ``sqrt(spread^2 - noise^2)`` (independent spreads add
        in squares), 0 when the noise explains it all; the spread itself where the noise is unknown."""
        if self.spread is None or self.noise is None:
            return self.spread
        return math.sqrt(max(self.spread ** 2 - self.noise ** 2, 0.0))


def exposure_spread(gains: ViewGains) -> ExposureSpread:
    """The spread of the views' gains with how reliable it is (:class:`ExposureSpread`)."""
    valid = torch.isfinite(gains.log_gains).all(-1)
    views = int(valid.sum())
    observations = noise = None
    if gains.points is not None and len(gains.points):
        observations = round(float(torch.quantile(gains.points.double(), 0.5)))
    if gains.errors is not None and views:
        errors = gains.errors[valid]
        if torch.isfinite(errors).all():
            noise = NORMAL_HALF_IQR * float(errors.double().median())
    return ExposureSpread(appearance_spread(gains.log_gains), views, observations, noise)


@dataclass(frozen=True)
class AppearanceDecision:
    """Whether the per-view corrections are learnt, why, and how confident the data make that decision:
    ``high`` (the spread beyond the noise lies at least one noise away from the threshold), ``low`` (closer,
    or too few reliable observations to measure it), ``unknown`` (the noise was not recorded)."""

    on: bool
    reason: str
    confidence: str


def decide_appearance(mode: str, measured: ExposureSpread, source: str = "SfM observations",
                      threshold: float = APPEARANCE_SPREAD) -> AppearanceDecision:
    """``on``/``off`` as configured; ``auto``: on iff the photos' gains spread by at least ``threshold``
    (:data:`APPEARANCE_SPREAD` for gains from SfM's observations, :data:`PROJECTED_SPREAD` for projected
    points) beyond what their measurement noise explains (:attr:`ExposureSpread.beyond_noise`); off with "too
    few reliable observations" where fewer than 3 views have a gain or the noise alone reaches the threshold
    (a photo mostly of glass has few keypoints outside it). ``source`` names how the gains were read."""
    spread, noise = measured.spread, measured.noise
    per_view = "" if measured.observations is None else f"{measured.observations} per view"
    counted = f" ({per_view})" if per_view else ""
    unreliable = spread is None or (noise is not None and noise >= threshold)
    if unreliable:
        what = (f"too few reliable observations{counted} to measure the exposure spread: "
                + (f"{measured.views} view(s) have a gain, 3 are needed" if spread is None else
                   f"the views' gains are uncertain enough to spread by {noise:.3f} by themselves (>= "
                   f"{threshold}), measured {spread:.3f} (from {source})"))
        confidence = "low"
    else:
        beyond = measured.beyond_noise
        if noise is None:
            what = (f"the photos' exposure spread is {spread:.3f} (from {source}; its noise was not recorded: "
                    "rerun rtsplat prepare to measure it)")
            confidence = "unknown"
        else:
            what = (f"the photos' exposure spread is {spread:.3f} (from {source}, {per_view}), {beyond:.3f} beyond "
                    f"the {noise:.3f} its measurement noise explains")
            confidence = "high" if abs(beyond - threshold) >= noise else "low"
    if mode != "auto":
        return AppearanceDecision(mode == "on", f"config: {mode}; {what}", confidence)
    if unreliable:
        return AppearanceDecision(False, f"auto: {what}", confidence)
    if measured.beyond_noise >= threshold:
        return AppearanceDecision(True, f"auto: {what} (>= {threshold})", confidence)
    return AppearanceDecision(False, f"auto: {what} (< {threshold}: one exposure)", confidence)
