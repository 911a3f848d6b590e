"""Divergence watch: the first iteration whose loss, gradients or parameters are not finite.

Every step the trainer hands the watch the loss, the optimizer's gradients (before the update) and
its parameters (after the update and density control). The watch reduces each parameter group's
tensors to their sums, one small vector per step, and keeps on the training device the iteration
and the vector of the first step where any entry is not finite; recording does not wait for the
device. :meth:`DivergenceWatch.check` reads that record back (one transfer) and returns a
:class:`Divergence`; the trainer reads it before every checkpoint and model write, on every step on
a CPU (where reading waits for nothing) and on logging steps on an accelerator.

A sum is not finite when any of its terms is NaN or infinite, and also when finite terms overflow
float32 (values around 1e31 and beyond in a large tensor); a run whose values grow that large has
diverged too. A sum is one pass over the tensor without a temporary, several times cheaper than
``torch.isfinite(t).all()`` on a CPU.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import torch
from torch import Tensor

from rtsplat.errors import PipelineError
from rtsplat.train.optim import learning_rate_key


class TrainingDiverged(PipelineError):
    """The loss, a gradient or a parameter became NaN or infinite during training."""


def group_sums(optimizer: torch.optim.Optimizer, of: str) -> Tensor:
    """One value per parameter group: the sum of its parameters (``of="data"``) or of their
    gradients (``of="grad"``; 0 for a group without gradients this step)."""
    sums = []
    for group in optimizer.param_groups:
        tensors = [p.grad if of == "grad" else p.detach() for p in group["params"]]
        tensors = [t for t in tensors if t is not None]
        sums.append(torch.stack([t.sum() for t in tensors]).sum() if tensors
                    else torch.zeros((), device=group["params"][0].device))
    return torch.stack(sums)


@dataclass
class Divergence:
    """What went non-finite at the first diverged iteration (parameter group names)."""

    iteration: int
    loss: bool
    gradients: list[str]
    parameters: list[str]

    def what(self) -> str:
        parts = ["the loss"] if self.loss else []
        if self.gradients:
            parts.append("the gradients of " + ", ".join(self.gradients))
        if self.parameters:
            parts.append("the parameters " + ", ".join(self.parameters))
        return "; ".join(parts)

    def likely_cause(self) -> str:
        """Where to look first: the groups whose gradient or update went bad first, else the input."""
        groups = self.gradients or self.parameters
        if self.loss or not groups:
            return ("a learning rate too high for the model (all parameters were finite before this step), or bad "
                    "input data (the prepared images, masks or points)")
        keys = sorted({learning_rate_key(name) for name in groups})
        step = "gradient" if self.gradients else "update"
        names = ", ".join(f"train.{key}" for key in keys)
        return f"the {step} of {', '.join(groups)} blew up: a learning rate too high for it ({names})"

    def fix(self) -> str:
        groups = self.gradients or self.parameters
        if self.loss or not groups:
            return "lower the learning rates (the train.lr section), or check the prepared scene's images and points"
        keys = sorted({learning_rate_key(name) for name in groups})
        return f"lower train.{' and train.'.join(keys)} (e.g. by 10x)"


class DivergenceWatch:
    """The first non-finite iteration, recorded on the device, read by :meth:`check`."""

    def __init__(self, device: torch.device):
        self.first = torch.zeros((), dtype=torch.long, device=device)  # 0: none yet
        self.flags: Tensor | None = None  # at ``first``: which entries were not finite
        self.groups: list[str] = []

    def gradients(self, optimizer: torch.optim.Optimizer) -> Tensor:
        """Call after backward, before the optimizer step; pass the result to :meth:`record`."""
        return group_sums(optimizer, "grad")

    def record(self, iteration: int, loss: Tensor, gradients: Tensor, optimizer: torch.optim.Optimizer) -> None:
        """Note ``iteration`` if its loss, gradients or (current) parameters are not finite."""
        self.groups = [group.get("name", str(i)) for i, group in enumerate(optimizer.param_groups)]
        values = torch.cat([loss.detach().reshape(1).to(gradients.dtype), gradients, group_sums(optimizer, "data")])
        bad = ~torch.isfinite(values)
        if self.flags is None or self.flags.shape != bad.shape:
            self.flags = torch.zeros_like(bad)
        new = (self.first == 0) & bad.any()
        self.first = torch.where(new, torch.full_like(self.first, iteration), self.first)
        self.flags = torch.where(new, bad, self.flags)

    def check(self) -> Divergence | None:
        """The first diverged iteration, if any (waits for the device)."""
        first = int(self.first)
        if first == 0 or self.flags is None:
            return None
        flags = self.flags.tolist()
        n = len(self.groups)
        return Divergence(
            iteration=first, loss=flags[0],
            gradients=[g for g, bad in zip(self.groups, flags[1:1 + n], strict=True) if bad],
            parameters=[g for g, bad in zip(self.groups, flags[1 + n:], strict=True) if bad],
        )


def diverged_error(divergence: Divergence, at: int, checkpoint: Path, checkpoint_iteration: int | None
                   ) -> TrainingDiverged:
    """The error that stops the run: iteration, what, likely cause, and how to go on."""
    seen = "" if at == divergence.iteration else f" (noticed at iteration {at})"
    problem = (f"training diverged at iteration {divergence.iteration}{seen}: {divergence.what()} became NaN or "
               f"infinite. Likely cause: {divergence.likely_cause()}. Nothing of the diverged state was written "
               "(no checkpoint, model.pt or point_cloud.ply)")
    if checkpoint_iteration is not None:
        go_on = (f"then rerun the same `rtsplat train --out ...` with --resume-with-new-config: it resumes from the "
                 f"last good checkpoint {checkpoint} (iteration {checkpoint_iteration})")
    else:
        go_on = ("then rerun `rtsplat train` from the start (no checkpoint was written before the divergence; "
                 "schedule.checkpoint_every sets how often one is)")
    return TrainingDiverged(problem, fix=f"{divergence.fix()}; {go_on}")
