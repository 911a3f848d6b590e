"""Density control as a strategy object (2DGS rules with RT-Splatting's occupancy pruning).

* statistics: per surfel, the accumulated norm of the 2DGS densification signal over the views
  where it was visible, the largest screen radius, and whether it was seen since the last reset;
* every ``densify_every`` iterations in [densify_from, densify_until) (default: the first half of the
  run, as 2DGS; the trainer passes the ``densify_from`` that :func:`rtsplat.train.initial.density_start`
  chose for its start): clone small surfels whose mean gradient exceeds the threshold (the clone and its
  original share the original's coverage), split large ones in two (two halves along the longer
  tangent axis, or the 2DGS random split), then prune: occupancy below 0.05 (never opacity: a clear window has
  low opacity) among surfels seen since the last reset (the see-through surface's seeds excepted while the
  volume stage lasts: it does not render them as glass), and, once the first reset has happened (as
  2DGS, whose size pruning starts after its first opacity reset), over-large surfels: before that,
  large surfels are the floor, walls and backdrop that the initial points describe coarsely, and
  deleting them leaves holes that the remaining steps cannot fill;
* before the first densification, with ``early_prune_occupancy`` set, every ``densify_every`` iterations:
  prune alone, the surfels seen so far whose occupancy is below it, the see-through surface's seeds excepted;
* every ``reset_every`` iterations, alternately clamp occupancy then opacity to <= 0.01.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field

import torch
from torch import Tensor

from rtsplat.model.surfels import PARAMETERS, SurfelParameters, logit
from rtsplat.raster import RasterOutput
from rtsplat.raster.projection import quat_to_rotmat
from rtsplat.train.clock import passed
from rtsplat.train.optim import append_rows, keep_rows, reset_rows
from rtsplat.train_config import Densification, Schedule


@dataclass
class DensityEvents:
    cloned: int = 0
    split: int = 0
    pruned: int = 0  # all pruned surfels (split parents are not counted)
    pruned_occupancy: int = 0  # ... of which for their low occupancy
    pruned_size: int = 0  # ... of which for their world or screen size
    reset: str = ""

    def any(self) -> bool:
        return bool(self.cloned or self.split or self.pruned or self.reset)

    def to_dict(self) -> dict[str, int | str]:
        return {k: v for k, v in asdict(self).items() if v}


@dataclass
class DensityControl:
    config: Densification
    schedule: Schedule
    extent: float
    grad_sum: Tensor = field(default_factory=lambda: torch.zeros(0))
    grad_count: Tensor = field(default_factory=lambda: torch.zeros(0))
    max_radius: Tensor = field(default_factory=lambda: torch.zeros(0))
    seen_since_reset: Tensor = field(default_factory=lambda: torch.zeros(0, dtype=torch.bool))
    resets_done: int = 0
    # the see-through surface's seeds, which no pruning removes while the volume stage lasts (early pruning,
    # and density steps up to schedule.volume_until): that stage has no use for them, and their occupancy dips
    # there and recovers once transmission is on. Forgotten at the first density step after the stage.
    spared_early: Tensor = field(default_factory=lambda: torch.zeros(0, dtype=torch.bool))

    def _ensure(self, n: int, device) -> None:
        if self.grad_sum.shape[0] != n:
            self.grad_sum = torch.zeros(n, device=device)
            self.grad_count = torch.zeros(n, device=device)
            self.max_radius = torch.zeros(n, device=device)
            self.seen_since_reset = torch.zeros(n, dtype=torch.bool, device=device)

    @torch.no_grad()
    def observe(self, out: RasterOutput, trainable: Tensor | None = None) -> None:
        """Accumulate statistics after backward()."""
        n = out.visible.shape[0]
        self._ensure(n, out.visible.device)
        visible = out.visible
        self.seen_since_reset |= visible
        # masks as arithmetic, not boolean indexing: no read of the device per iteration
        signal = out.densification_grad()
        if signal is not None:
            norm = signal.norm(dim=-1)
            if trainable is not None:
                norm = norm * trainable
            self.grad_sum += torch.where(visible, norm.to(self.grad_sum.dtype), 0.0)
            self.grad_count += visible.to(self.grad_count.dtype)
        radius = out.radii.amax(-1).to(self.max_radius.dtype)
        self.max_radius = torch.where(visible, torch.maximum(self.max_radius, radius), self.max_radius)

    def state_dict(self) -> dict:
        return {"grad_sum": self.grad_sum, "grad_count": self.grad_count, "max_radius": self.max_radius,
                "seen_since_reset": self.seen_since_reset, "resets_done": self.resets_done,
                "spared_early": self.spared_early}

    def load_state_dict(self, state: dict) -> None:
        for key, value in state.items():
            setattr(self, key, value)

    @torch.no_grad()
    def step(self, iteration: int, surfels: SurfelParameters, optimizer, generator: torch.Generator,
             frozen: Tensor | None = None, previous: int | None = None) -> tuple[DensityEvents, Tensor]:
        """Run the density operations scheduled in ``(previous, iteration]`` of the plan (1-based;
        ``previous`` defaults to ``iteration - 1``; :func:`rtsplat.train.clock.passed`: each at most once
        per step). Returns the events and the new ``frozen`` mask (frozen surfels are never cloned, split or
        pruned)."""
        s = self.schedule
        n = len(surfels)
        device = surfels.means.device
        self._ensure(n, device)
        frozen = torch.zeros(n, dtype=torch.bool, device=device) if frozen is None else frozen
        events = DensityEvents()
        stop = s.densify_stop()
        previous = iteration - 1 if previous is None else previous
        if passed(previous, iteration, s.densify_every, start=s.densify_from, stop=stop) is not None:
            frozen = self._densify_and_prune(surfels, optimizer, generator, frozen, events,
                                             spare_seeds=iteration <= s.volume_until)
        elif self.config.early_prune_occupancy > 0 and passed(
                previous, iteration, s.densify_every, stop=min(s.densify_from, stop)) is not None:
            frozen = self._prune_early(surfels, optimizer, frozen, events)
        if passed(previous, iteration, s.reset_every, stop=stop) is not None:
            self._reset(surfels, optimizer, events)
        return events, frozen

    def _densify_and_prune(self, surfels, optimizer, generator, frozen, events, spare_seeds: bool) -> Tensor:
        """Clone, split, then prune (the module's rules); ``spare_seeds``: the ``spared_early`` rows are not
        pruned, and the mask follows them through this step."""
        c = self.config
        device = surfels.means.device
        seeds = self._seed_rows(len(surfels), device)
        if not spare_seeds:
            seeds.zero_()
        mean_grad = self.grad_sum / self.grad_count.clamp_min(1)
        big = surfels.scales.amax(-1) > c.percent_dense * self.extent
        candidates = (mean_grad >= c.grad_threshold) & ~frozen
        room = max(c.max_surfels - len(surfels), 0)
        clone = candidates & ~big
        split = candidates & big
        if int(clone.sum()) + 2 * int(split.sum()) > room:  # keep the strongest within the budget
            score = torch.where(candidates, mean_grad, torch.full_like(mean_grad, -1.0))
            order = torch.argsort(score, descending=True)
            allowed = torch.zeros_like(candidates)
            allowed[order[: room // 2]] = True
            clone &= allowed
            split &= allowed
        # occupancy pruning judges every surfel, clones and children included, by the occupancy it had
        # before this step (a clone's shared coverage is no reason to prune it)
        low_before = surfels.occupancy.detach() < c.prune_occupancy
        low_rows = [low_before]
        new_rows = {name: [] for name in PARAMETERS}
        tensors = surfels.tensors()
        if clone.any():
            if c.clone_preserves_coverage:
                _share_coverage(surfels, clone)
            for name in PARAMETERS:
                new_rows[name].append(tensors[name].detach()[clone])
            low_rows.append(low_before[clone])
        if split.any():
            idx = torch.nonzero(split).flatten()
            for offset, log_scales in _split_children(surfels, idx, c, generator):
                low_rows.append(low_before[idx])
                for name in PARAMETERS:
                    value = tensors[name].detach()[idx]
                    if name == "means":
                        value = value + offset
                    elif name == "log_scales":
                        value = log_scales
                    new_rows[name].append(value)
        added = {name: torch.cat(v) if v else tensors[name].detach()[:0] for name, v in new_rows.items()}
        n_added = added["means"].shape[0]
        if n_added:
            append_rows(optimizer, surfels, added)
        events.cloned, events.split = int(clone.sum()), int(split.sum())
        no_rows = torch.zeros(n_added, dtype=torch.bool, device=device)
        frozen = torch.cat([frozen, no_rows])
        grown = lambda t, fill: torch.cat([t, torch.full((n_added,), fill, dtype=t.dtype, device=device)])  # noqa: E731
        seen = grown(self.seen_since_reset, False)
        max_radius = grown(self.max_radius, 0)
        remove = torch.cat([split, no_rows])

        low_occupancy = torch.cat(low_rows) & seen
        too_big = torch.zeros_like(seen)
        if self.resets_done > 0:  # 2DGS: size pruning only once the first reset has happened
            too_big = surfels.scales.detach().amax(-1) > c.max_world_scale * self.extent
            if c.max_screen_size > 0:
                too_big |= max_radius > c.max_screen_size
        spared = torch.cat([seeds, no_rows])
        remove |= (low_occupancy | too_big) & ~frozen & ~spared
        keep = ~remove
        if not keep.any():  # never prune the scene away entirely: drop only the split parents
            keep = ~torch.cat([split, no_rows])
        parents = torch.cat([split, no_rows])
        events.pruned_occupancy = int((low_occupancy & ~keep & ~parents).sum())
        events.pruned_size = int((too_big & ~low_occupancy & ~keep & ~parents).sum())
        keep_rows(optimizer, surfels, keep)
        events.pruned = int((~keep).sum()) - events.split
        self.seen_since_reset = seen[keep]
        n_new = int(keep.sum())
        self.grad_sum = torch.zeros(n_new, device=device)
        self.grad_count = torch.zeros(n_new, device=device)
        self.max_radius = torch.zeros(n_new, device=device)
        self.spared_early = spared[keep] if spare_seeds else self.spared_early[:0]
        return frozen[keep]

    def _prune_early(self, surfels, optimizer, frozen, events) -> Tensor:
        """Prune alone, before the first densification: the surfels seen so far whose occupancy is below
        ``early_prune_occupancy`` (at most ``prune_occupancy``), except the ``spared_early`` rows; the
        statistics of the others are kept."""
        c = self.config
        threshold = min(c.early_prune_occupancy, c.prune_occupancy)
        n = len(surfels)
        spared = self._seed_rows(n, surfels.means.device)
        remove = (surfels.occupancy.detach() < threshold) & self.seen_since_reset & ~frozen & ~spared
        n_removed = int(remove.sum())
        if n_removed == 0 or n_removed == n:  # never prune the scene away entirely
            return frozen
        keep = ~remove
        keep_rows(optimizer, surfels, keep)
        events.pruned = events.pruned_occupancy = n_removed
        for name in ("grad_sum", "grad_count", "max_radius", "seen_since_reset"):
            setattr(self, name, getattr(self, name)[keep])
        self.spared_early = spared[keep]
        return frozen[keep]

    def _seed_rows(self, n: int, device) -> Tensor:
        """The ``spared_early`` mask over ``n`` rows (rows past its end are no seeds)."""
        seeds = self.spared_early[:n].to(device)
        return torch.cat([seeds, torch.zeros(n - len(seeds), dtype=torch.bool, device=device)])

    def _reset(self, surfels, optimizer, events) -> None:
        cap = logit(self.config.reset_value)
        name = "occupancy_logit" if self.resets_done % 2 == 0 else "opacity_logit"
        value = getattr(surfels, name).detach().clamp_max(cap)
        reset_rows(optimizer, surfels, name, value)
        self.resets_done += 1
        self.seen_since_reset = torch.zeros(len(surfels), dtype=torch.bool, device=surfels.means.device)
        events.reset = "occupancy" if name == "occupancy_logit" else "opacity"


HALF_OFFSET = 0.6  # children centres at +-0.6 x the longer scale (see Densification.split_mode)
HALF_SCALE = 0.6  # children's longer scale, as a fraction of the parent's


def _split_children(surfels: SurfelParameters, idx: Tensor, c: Densification,
                    generator: torch.Generator) -> list[tuple[Tensor, Tensor]]:
    """(centre offset [M,3], log scales [M,2]) of the two children of each surfel in ``idx``."""
    rot = quat_to_rotmat(surfels.quats.detach()[idx])
    scales = surfels.scales.detach()[idx]
    log_scales = surfels.log_scales.detach()[idx]
    if c.split_mode == "random":
        children = []
        for _ in range(2):
            # drawn from the CPU generator (the run's seed), then moved to the surfels' device
            local = torch.randn(idx.shape[0], 2, generator=generator).to(scales.device) * scales
            offset = (rot[:, :, :2] @ local[:, :, None])[..., 0]
            children.append((offset, log_scales - math.log(c.split_factor)))
        return children
    longer = scales.argmax(-1)
    rows = torch.arange(idx.shape[0], device=scales.device)
    axis = rot[rows, :, longer]  # the tangent direction of the longer scale [M,3]
    offset = HALF_OFFSET * scales[rows, longer][:, None] * axis
    child_scales = log_scales.clone()
    child_scales[rows, longer] += math.log(HALF_SCALE)
    return [(offset, child_scales), (-offset, child_scales)]


def _share_coverage(surfels: SurfelParameters, rows: Tensor) -> None:
    """Give the surfels of ``rows`` the occupancy and opacity with which two coincident copies cover
    what one covered at its centre, in both compositing weight sets: 1 - (1 - o')^2 = o for
    o = occupancy and for o = occupancy x opacity (away from the centre, where the kernel is < 1, the
    pair covers somewhat more). Changes values in place (Adam moments stay)."""
    occupancy = surfels.occupancy.detach()[rows]
    effective = occupancy * surfels.opacity.detach()[rows]
    occupancy_new = 1 - torch.sqrt(1 - occupancy)
    opacity_new = ((1 - torch.sqrt(1 - effective)) / occupancy_new.clamp_min(1e-12)).clamp(1e-6, 1 - 1e-6)
    surfels.occupancy_logit.data[rows] = torch.logit(occupancy_new.clamp(1e-6, 1 - 1e-6))
    surfels.opacity_logit.data[rows] = torch.logit(opacity_new)
