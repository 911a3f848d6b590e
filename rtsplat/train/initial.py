"""How many surfels training starts with, and from which SfM points.

Each SfM point starts ``densify.initial_copies`` surfels (:func:`rtsplat.model.surfels.scatter_points`)
as long as they fit under a cap that follows the training budget and resolution
(:func:`starting_cap`): a share of ``densify.max_surfels`` (the rest is left to densification), and at
most one surfel per ``densify.initial_pixels_per_surfel`` training pixels. Over the cap the copies
drop first (down to one per point), then the points: a random subset, drawn with the run's seed.
A small scene is never capped, so it starts exactly as without the rule; a real capture's 100k-1M
points start a bounded number of surfels instead of millions.

How dense the start is also places the first density step (:func:`density_start`): most of a dense
start is pruned by that step, so ``schedule.dense_start_densify_from`` can bring it forward; a sparse
start keeps ``schedule.densify_from``, since there the step mostly grows surfels.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import torch
from torch import Tensor

from rtsplat.model.surfels import SurfelParameters, init_from_points, point_cloud_normals, scatter_points
from rtsplat.train.clock import passed
from rtsplat.train_config import Densification, Schedule


@dataclass(frozen=True)
class StartingSurfels:
    """The starting surfels of a run: ``points`` of the ``sfm_points`` SfM points, ``copies`` surfels
    each, under ``cap``; ``reason`` says which rule decided."""

    sfm_points: int
    points: int
    copies: int
    cap: int
    reason: str

    @property
    def surfels(self) -> int:
        return self.points * self.copies

    def to_dict(self) -> dict[str, int | str]:
        return {**asdict(self), "surfels": self.surfels}


def starting_cap(densify: Densification, train_pixels: int) -> int:
    """The most surfels training starts from the SfM points: ``initial_budget_share`` of
    ``max_surfels``, and at most one per ``initial_pixels_per_surfel`` of the ``train_pixels`` (all
    training views at the training resolution; 0 turns this part off). At least 1."""
    cap = densify.initial_budget_share * densify.max_surfels
    if densify.initial_pixels_per_surfel > 0:
        cap = min(cap, train_pixels / densify.initial_pixels_per_surfel)
    return max(1, int(cap))


@dataclass(frozen=True)
class DensityStart:
    """Where density control starts: ``densify_from`` (``schedule.densify_from``, or
    ``schedule.dense_start_densify_from`` for a dense start), the iteration of the first density step
    it gives (the first multiple of ``schedule.densify_every`` from there; None: none before density
    control stops) and why."""

    densify_from: int
    first_step: int | None
    reason: str

    def to_dict(self) -> dict[str, int | str]:
        return asdict(self)


def density_start(schedule: Schedule, densify: Densification, starting: StartingSurfels,
                  view_pixels: float) -> DensityStart:
    """Where density control starts for a run that starts ``starting`` surfels from the SfM points and
    trains on views of ``view_pixels`` pixels (their mean at the training resolution): after
    ``schedule.dense_start_densify_from`` when that is set and the start has at least
    ``densify.dense_start_per_pixel`` surfels per such pixel, else after ``schedule.densify_from``."""
    early = schedule.dense_start_densify_from
    if early is None:
        densify_from, reason = schedule.densify_from, "schedule.densify_from; dense_start_densify_from is null"
    else:
        per_pixel = starting.surfels / max(view_pixels, 1.0)
        dense = per_pixel >= densify.dense_start_per_pixel
        rule = (f"{'a dense' if dense else 'a sparse'} start: {per_pixel:.2f} starting surfels per pixel of a "
                f"training view, {'at least' if dense else 'below'} densify.dense_start_per_pixel "
                f"{densify.dense_start_per_pixel:g}")
        densify_from, reason = ((early, f"schedule.dense_start_densify_from for {rule}") if dense
                                else (schedule.densify_from, f"schedule.densify_from for {rule}"))
    # the first step is where DensityControl's clock (passed) first fires: the one multiple of densify_every in
    # the window of that length from densify_from (from 1: never iteration 0)
    before = max(densify_from, 1) - 1
    first = passed(before, before + schedule.densify_every, schedule.densify_every, start=densify_from,
                   stop=schedule.densify_stop())
    return DensityStart(densify_from, first, reason)


def plan_starting_surfels(sfm_points: int, copies: int, cap: int) -> StartingSurfels:
    """Points and copies per point for ``sfm_points`` points and ``copies`` wanted per point under
    ``cap``: all of them when they fit, else fewer copies (the most that fit, at least one), else
    ``cap`` points with one copy each."""
    if sfm_points * copies <= cap:
        return StartingSurfels(sfm_points, sfm_points, copies, cap,
                               f"{sfm_points} SfM points x {copies} copies are within the cap of {cap}")
    if sfm_points <= cap:
        fewer = cap // sfm_points
        return StartingSurfels(sfm_points, sfm_points, fewer, cap,
                               f"{sfm_points} SfM points x {copies} copies exceed the cap of {cap}: "
                               f"{fewer} copies per point")
    return StartingSurfels(sfm_points, cap, 1, cap,
                           f"{sfm_points} SfM points exceed the cap of {cap}: a random {cap} of them, one surfel each")


def choose_points(plan: StartingSurfels, generator: torch.Generator) -> Tensor | None:
    """Indices (ascending) of the ``plan.points`` SfM points to start from, drawn with ``generator``;
    None when all of them are used (then nothing is drawn, so the generator's later draws are those
    of a run without the cap)."""
    if plan.points >= plan.sfm_points:
        return None
    return torch.randperm(plan.sfm_points, generator=generator)[: plan.points].sort().values


def initial_surfels(points: Tensor, colours: Tensor, plan: StartingSurfels, generator: torch.Generator, *,
                    point_normals: bool, **init: float | int) -> SurfelParameters:
    """The starting surfels of ``plan`` from the SfM ``points`` [N,3] and ``colours`` [N,3] in [0,1]: the
    chosen points (:func:`choose_points`), each followed by its scattered copies
    (:func:`~rtsplat.model.surfels.scatter_points`); with ``point_normals`` they face along the whole
    cloud's normal at their point (a point's copies share it), else randomly. ``init``: the starting
    values of :func:`~rtsplat.model.surfels.init_from_points`."""
    chosen = choose_points(plan, generator)
    kept, kept_colours = (points, colours) if chosen is None else (points[chosen], colours[chosen])
    xyz, rgb = scatter_points(kept, kept_colours, plan.copies, generator=generator)
    normals = (point_cloud_normals(points, queries=None if chosen is None else kept).repeat(plan.copies, 1)
               if point_normals else None)
    return init_from_points(xyz, rgb, generator=generator, normals=normals, **init)
