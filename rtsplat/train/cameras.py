"""Per-view pose corrections.

SfM poses are off by a fraction of a degree (docs/benchmarks.md: 0.1-0.4 degrees on the synthetic
scenes), which at the training resolution is most of a pixel where the scene is far away. Each view
gets a correction ``[6]`` = (rotation vector in radians, translation) applied in the camera's own frame
(:meth:`rtsplat.camera.Camera.corrected`):

* training views: :class:`PoseCorrections`, learnt by Adam together with the model from the image
  loss's gradient (it reaches the pose through the surfels' projection, the pixel rays of the
  background and the view directions);
* test views: :func:`fit_corrections`, a few Adam steps per view on the L1 error of the render with
  the model fixed, so that test PSNR measures the reconstruction and not the test view's own pose
  error (the same protocol for every method).

Corrections are stored scaled: ``correction = values * scale`` with ``scale = (1, 1, 1, e, e, e)``,
``e`` the scene extent, so one learning rate moves rotations in radians and translations in units
of the extent.
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import Tensor

from rtsplat.camera import Camera


def correction_scale(extent: float, device=None) -> Tensor:
    return torch.tensor([1.0, 1.0, 1.0, extent, extent, extent], device=device)


class PoseCorrections:
    """One learnt correction per training view, with its own Adam (rotation and translation groups)."""

    def __init__(self, count: int, extent: float, lr_rotation: float, lr_translation: float, device=None):
        self.scale = correction_scale(extent, device)
        self.rotation = torch.zeros(count, 3, device=device, requires_grad=True)
        self.translation = torch.zeros(count, 3, device=device, requires_grad=True)
        self.optimizer = torch.optim.Adam(
            [{"params": [self.rotation], "lr": lr_rotation}, {"params": [self.translation], "lr": lr_translation}],
            eps=1e-15,
        )

    def correction(self, index: int) -> Tensor:
        return torch.cat([self.rotation[index], self.translation[index]]) * self.scale

    def camera(self, index: int, camera: Camera) -> Camera:
        return camera.corrected(self.correction(index))

    def step(self) -> None:
        self.optimizer.step()
        self.optimizer.zero_grad(set_to_none=True)

    def values(self) -> Tensor:
        """[count, 6] corrections (detached)."""
        return torch.cat([self.rotation, self.translation], 1).detach() * self.scale

    def state_dict(self) -> dict:
        return {"rotation": self.rotation.detach().clone(), "translation": self.translation.detach().clone(),
                "optimizer": self.optimizer.state_dict()}

    def load_state_dict(self, state: dict) -> None:
        with torch.no_grad():
            self.rotation.copy_(state["rotation"])
            self.translation.copy_(state["translation"])
        self.optimizer.load_state_dict(state["optimizer"])


def fit_corrections(
    render_color: Callable[[Camera], Tensor], cameras: list[Camera], images: list[Tensor], start: Tensor,
    extent: float, steps: int, lr: float,
) -> Tensor:
    """Corrections [V, 6] of ``cameras`` that lower the L1 error of ``render_color(camera)`` against
    ``images``, from ``start`` [V, 6]: ``steps`` Adam steps per view, the learning rate decayed
    log-linearly from ``lr`` to ``lr / 10``. Only the corrections get gradients (the model's
    parameters are left untouched, ``.grad`` included). Each view keeps the best correction it saw,
    so a fit never raises a view's error above that at ``start``."""
    scale = correction_scale(extent, start.device)
    out = start.detach().clone()
    if steps <= 0:
        return out
    for index, (camera, image) in enumerate(zip(cameras, images, strict=True)):
        values = (out[index] / scale).clone().requires_grad_(True)
        optimizer = torch.optim.Adam([values], lr=lr, eps=1e-15)
        best, best_error = out[index].clone(), float("inf")
        for step in range(steps + 1):
            error = (render_color(camera.corrected(values * scale)) - image).abs().mean()
            value = float(error.detach())
            if value < best_error:
                best, best_error = (values * scale).detach().clone(), value
            if step == steps:
                break
            (gradient,) = torch.autograd.grad(error, [values])
            values.grad = gradient
            for group in optimizer.param_groups:
                group["lr"] = lr * 0.1 ** (step / max(steps - 1, 1))
            optimizer.step()
        out[index] = best
    return out
