"""Mirror planes refined against the images.

The mirror planes of near reflections (:mod:`rtsplat.model.mirror`) are fitted once, to the surface depth
of the see-through pixels, whose noise (a few centimetres, a few degrees on the synthetic cabin) turns a
reflected ray by twice the plane's error. The near reflection itself tells where the plane is: a pane
mirrored a centimetre too far puts what it reflects a centimetre off in every view. :class:`PlaneRefinement`
learns one small motion per plane (a rotation about its centre and a shift along its normal) from the image
loss, with its own Adam:

* each step renders with :meth:`planes` (the model's planes moved by the current motion, zero at the
  start of a step, so the rows equal the model's but carry the gradient);
* :meth:`step` takes an Adam step of the motion, folds it into the plane rows and starts the next step
  from zero again, so the model always holds the current planes (checkpoints, renders and the viewer
  read them as they are) and rotations compose exactly.

Adam steps have about the learning rate's size whatever the gradient's scale: ``lr_rotation`` is in
radians per step, ``lr_shift`` in units of the scene extent per step. The summary reports how far each
plane moved from its fit (:meth:`moved`).
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from rtsplat.model.mirror import move_planes, plane_parts


class PlaneRefinement:
    """A rotation vector [K,3] and a shift [K] per mirror plane, learnt by Adam and folded into the rows."""

    def __init__(self, planes: Tensor, extent: float, lr_rotation: float, lr_shift: float):
        self.fitted = planes.detach().clone()
        self.current = planes.detach().clone()
        self.extent = float(extent)
        count = planes.shape[0]
        self.rotation = torch.zeros(count, 3, dtype=planes.dtype, device=planes.device, requires_grad=True)
        self.shift = torch.zeros(count, dtype=planes.dtype, device=planes.device, requires_grad=True)
        self.optimizer = torch.optim.Adam(
            [{"params": [self.rotation], "lr": lr_rotation}, {"params": [self.shift], "lr": lr_shift}], eps=1e-15)

    def planes(self) -> Tensor:
        """The current plane rows [K,12], differentiable in this step's motion."""
        return move_planes(self.current, self.rotation, self.shift * self.extent)

    def step(self) -> Tensor:
        """One Adam step of the motion (a plane that got no gradient stays), folded into the rows, which it
        returns [K,12]. A step that would make a row non-finite is dropped for that plane."""
        for value in (self.rotation, self.shift):
            if value.grad is not None:
                value.grad = torch.nan_to_num(value.grad, nan=0.0, posinf=0.0, neginf=0.0)
        self.optimizer.step()
        self.optimizer.zero_grad(set_to_none=True)
        with torch.no_grad():
            moved = move_planes(self.current, self.rotation, self.shift * self.extent)
            finite = torch.isfinite(moved).all(-1, keepdim=True)
            self.current = torch.where(finite, moved, self.current)
            self.rotation.zero_()
            self.shift.zero_()
        return self.current

    def moved(self) -> list[dict]:
        """Per plane: the angle (degrees) between its fitted and current normal, and how far its centre
        moved along the fitted normal (scene units)."""
        n0, c0, *_ = plane_parts(self.fitted)
        n1, c1, *_ = plane_parts(self.current)
        cosine = (n0 * n1).sum(-1).clamp(-1.0, 1.0)
        along = ((c1 - c0) * n0).sum(-1)
        return [{"degrees": round(math.degrees(math.acos(float(c))), 3), "shift": round(float(s), 5)}
                for c, s in zip(cosine, along, strict=True)]

    def state_dict(self) -> dict:
        return {"fitted": self.fitted.clone(), "current": self.current.clone(),
                "optimizer": self.optimizer.state_dict()}

    def load_state_dict(self, state: dict) -> None:
        self.fitted = state["fitted"].to(self.current)
        self.current = state["current"].to(self.current)
        self.optimizer.load_state_dict(state["optimizer"])
