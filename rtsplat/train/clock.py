"""Where a run stands in its schedule: by iterations, or by the share of a time budget spent.

The schedule (:class:`rtsplat.train_config.Schedule`) places every stage, density step, resolution step and
evaluation at an iteration of a plan of ``schedule.iterations`` iterations. Without a time budget the run's
iteration *is* its position in that plan. With one (``schedule.seconds``), a step's position is the plan's
iteration at the share of the budget spent before it: ``floor(iterations x spent / seconds) + 1``, never
backwards, at most ``iterations``; the run stops once the budget is spent. So a slow machine runs fewer
iterations of the same plan and a fast one more, each stage taking the same share of the time. A run with a
time budget is not bit-reproducible (its positions follow the clock).

Events that recur every N plan iterations (density control, resets, evaluations, checkpoints) happen at the
step whose position passes a multiple of N (:func:`passed`): once per multiple, whether positions advance by
one per step (an iteration budget, where this is the usual ``iteration % N == 0``), by several (a short time
budget) or by less than one (a long one).
"""

from __future__ import annotations

from dataclasses import dataclass


def passed(previous: int, current: int, every: int, start: int = 1, stop: int | None = None) -> int | None:
    """The largest multiple of ``every`` in ``(previous, current]`` that lies in ``[start, stop)`` (``stop``
    None: no end), or None when there is none (or ``every`` <= 0)."""
    top = current if stop is None else min(current, stop - 1)
    if every <= 0 or top <= previous:
        return None
    multiple = (top // every) * every
    return multiple if multiple > previous and multiple >= start else None


@dataclass
class ScheduleClock:
    """The plan's length (``iterations``), the time budget in seconds of training steps (None: none) and the
    position of the last step taken (0 before the first)."""

    iterations: int
    seconds: float | None = None
    position: int = 0

    def advance(self, spent: float) -> tuple[int, int]:
        """The next step's (previous position, position), ``spent`` being the seconds of the steps so far."""
        previous = self.position
        if self.seconds is None:
            current = previous + 1
        else:
            share = max(spent, 0.0) / self.seconds
            current = max(previous, min(self.iterations, int(self.iterations * share) + 1))
        self.position = current
        return previous, current

    def done(self, iteration: int, spent: float) -> bool:
        """Whether the run is over after ``iteration`` steps that took ``spent`` seconds."""
        if self.seconds is None:
            return iteration >= self.iterations
        return spent >= self.seconds
