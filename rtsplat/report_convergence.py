"""The report's convergence section: RT-Splatting and plain 2DGS trained at several budgets on the same scenes
(``benchmarks/convergence.yaml``), to tell what the demo budget leaves on the table.

A scene's budgets are its :func:`rtsplat.report.comparison_pairs` with a budget in their name: the demo pair
(the main method against ``2dgs``: 1x) and every ``<main>_x<N>`` against ``2dgs_x<N>`` (``budget: N``). A
method has converged at the first budget whose next one gained less than :data:`CONVERGED_GAIN` dB of test
PSNR per doubling of the budget, on the entire image and on the transparent region both. The section gives,
per scene, every budget's test PSNR, layers and training time, and the RT-Splatting minus 2DGS gap at the demo
budget beside the gap at convergence (at the larger of the two methods' converged budgets; at the largest
budget, marked so, where either method had not converged by it), and the gap at equal time along the two
finished series: each budget of the main method against 2DGS's finished runs interpolated to the same training
time (:func:`series_at`), which compares finished runs only, where the summary's equal-time gap reads the other
run's log mid-schedule.
"""

from __future__ import annotations

import itertools
import math
import re
from dataclasses import dataclass

from rtsplat.report import (
    BLURRED_REFERENCE,
    FLAT_REFERENCE,
    PLAIN_2DGS,
    Document,
    Roles,
    Run,
    TimeMeasure,
    _difference,
    _fmt,
    _signed,
    comparison_pairs,
    interpolate_between,
    time_measure,
)

CONVERGED_GAIN = 0.1  # dB of test PSNR per doubling of the budget below which a method has converged
REGIONS = ("psnr", "psnr_transparent")  # the test PSNRs a doubling must stop improving, entire and transparent
BUDGET_SUFFIX = re.compile(r"x(\d+(?:\.\d+)?)")  # the budget in a pair's name: rtsplat_x4 against 2dgs_x4


@dataclass(frozen=True)
class Budget:
    """One budget of a scene: its factor on the demo's iteration counts and the two runs trained at it."""

    factor: float
    ours: Run  # the main method (RT-Splatting)
    theirs: Run  # plain 2DGS

    @property
    def label(self) -> str:
        return f"{self.factor:g}x"


def scene_budgets(runs: dict[str, Run], roles: Roles) -> list[Budget]:
    """The scene's budgets at which both methods ran, smallest first (see the module's text)."""
    budgets = []
    for ours, theirs in comparison_pairs(runs, roles):
        suffix = ours[len(roles.main) + 1:]
        match = BUDGET_SUFFIX.fullmatch(suffix)
        if suffix and not match:
            continue  # another kind of pair (_half, _halfstart): not a point of the budget series
        budgets.append(Budget(float(match[1]) if match else 1.0, runs[ours], runs[theirs]))
    return sorted(budgets, key=lambda b: b.factor)


def gain_per_doubling(before: Run, after: Run, doublings: float, key: str) -> float | None:
    """Test PSNR ``key`` gained from ``before`` to ``after`` per doubling of the budget."""
    gain = _difference(after.mean.get(key), before.mean.get(key))
    return None if gain is None else gain / doublings


def gains(budgets: list[Budget], side: str) -> list[dict[str, float | None]]:
    """Per budget, the :data:`REGIONS` gains per doubling of one method (``side``: ``ours`` or ``theirs``) over
    the budget before it (none for the first)."""
    found: list[dict[str, float | None]] = [{}]
    for before, after in itertools.pairwise(budgets):
        doublings = math.log2(after.factor / before.factor)
        found.append({key: gain_per_doubling(getattr(before, side), getattr(after, side), doublings, key)
                      for key in REGIONS})
    return found


def converged_at(budgets: list[Budget], side: str) -> Budget | None:
    """The first budget whose next one gained less than :data:`CONVERGED_GAIN` per doubling in every region both
    runs scored; None when no doubling did (not converged by the largest budget)."""
    for budget, gain in zip(budgets, gains(budgets, side)[1:], strict=False):
        measured = [g for g in gain.values() if g is not None]
        if measured and max(measured) < CONVERGED_GAIN:
            return budget
    return None


def _seconds(run: Run, measure: TimeMeasure) -> str:
    return _fmt(run.seconds(measure), 0)


def budget_rows(scene: str, budgets: list[Budget], reference: dict[str, float] | None,
                measure: TimeMeasure) -> list[list[str]]:
    """One row per run of the scene's budget series (the main method's, then 2DGS's): test PSNR entire and
    transparent, the gains per doubling, the layers (the reflection also less the flat and the blurred
    references), the training time."""
    rows = []
    for side in ("ours", "theirs"):
        for budget, gain in zip(budgets, gains(budgets, side), strict=True):
            run: Run = getattr(budget, side)
            reflection = run.mean.get("psnr_reflection_layer")
            rows.append([scene, run.method, budget.label, _fmt(run.summary.get("iterations"), 0),
                         _fmt(run.mean.get("psnr")), _fmt(run.mean.get("psnr_transparent")),
                         *(_signed(gain.get(key)) for key in REGIONS), _fmt(reflection),
                         *(_signed(_difference(reflection, (reference or {}).get(name)))
                           for name in (FLAT_REFERENCE, BLURRED_REFERENCE)),
                         _fmt(run.mean.get("psnr_transmission_layer")), _seconds(run, measure)])
    return rows


def series_at(series: list[tuple[float, float | None]], seconds: float | None) -> float | None:
    """A value of a budget series of finished runs, ``(training time, value)`` by increasing time, at ``seconds``:
    linear in log2 of the time between the two runs around it (a doubling of the budget about doubles the time).
    None outside the series' times (no extrapolation), or where a run around it has no value."""
    return None if seconds is None else interpolate_between(series, seconds, log_axis=True)


def equal_time_rows(scene: str, budgets: list[Budget], measure: TimeMeasure) -> list[list[str]]:
    """One row per budget of the main method: its training time, the budget 2DGS's series reaches in that time,
    and RT-Splatting minus 2DGS's finished series there (transparent, entire); "-" beyond 2DGS's series."""
    timed = [(t, b) for b in budgets if (t := b.theirs.seconds(measure)) is not None]  # budgets: by factor
    if any(t0 >= t1 for (t0, _), (t1, _) in itertools.pairwise(timed)):
        timed = []  # a larger 2DGS budget that took no longer (a run beside heavy load): no series to read
    factors = [(t, math.log2(b.factor)) for t, b in timed]
    rows = []
    for budget in budgets:
        seconds = budget.ours.seconds(measure)
        doublings = series_at(factors, seconds)
        gaps = [_difference(budget.ours.mean.get(key),
                            series_at([(t, b.theirs.mean.get(key)) for t, b in timed], seconds))
                for key in ("psnr_transparent", "psnr")]
        rows.append([scene, budget.label, _seconds(budget.ours, measure),
                     "-" if doublings is None else f"{2 ** doublings:.2g}x", *map(_signed, gaps)])
    return rows


def _converged_text(budgets: list[Budget], side: str) -> str:
    budget = converged_at(budgets, side)
    return budget.label if budget else f"not converged by {budgets[-1].label}"


def compared_budget(budgets: list[Budget]) -> tuple[Budget, bool]:
    """The budget the converged gap is read at, and whether both methods converged by it: the larger of the two
    converged budgets, else the largest budget."""
    found = [converged_at(budgets, side) for side in ("ours", "theirs")]
    if None in found:
        return budgets[-1], False
    return max(found, key=lambda b: b.factor), True


def gap_row(scene: str, budget: Budget, label: str, reference: dict[str, float] | None,
            measure: TimeMeasure) -> list[str]:
    """RT-Splatting minus 2DGS at one budget (transparent, entire), the main method's layers beside the
    references, and both runs' training times."""
    ours, theirs = budget.ours, budget.theirs
    return [scene, label, *(_signed(_difference(ours.mean.get(key), theirs.mean.get(key)))
                            for key in ("psnr_transparent", "psnr")),
            _fmt(ours.mean.get("psnr_reflection_layer")), _fmt(ours.mean.get("psnr_transmission_layer")),
            *(_fmt((reference or {}).get(name)) for name in (FLAT_REFERENCE, BLURRED_REFERENCE)),
            _seconds(ours, measure), _seconds(theirs, measure)]


def gap_rows(scene: str, budgets: list[Budget], reference: dict[str, float] | None,
             measure: TimeMeasure) -> list[list[str]]:
    """The scene's gap at the demo budget (when it ran) and at convergence (:func:`compared_budget`)."""
    converged = f"{_converged_text(budgets, 'ours')} / {_converged_text(budgets, 'theirs')}"
    rows = [gap_row(scene, b, "1x (demo)", reference, measure) + [converged] for b in budgets if b.factor == 1.0]
    budget, both = compared_budget(budgets)
    label = f"{budget.label} (converged)" if both else f"{budget.label} (largest; not converged)"
    return rows + [gap_row(scene, budget, label, reference, measure) + [converged]]


def convergence_section(doc: Document, scenes: dict[str, dict[str, Run]], roles: Roles,
                        references: dict[str, dict[str, float] | None]) -> None:
    """The section, over the scenes with at least two budgets; nothing when no scene has them."""
    series = {scene: b for scene, runs in scenes.items() if len(b := scene_budgets(runs, roles)) > 1}
    if not series:
        return
    measure = time_measure({f"{scene}/{r.method}": r for scene, budgets in series.items() for b in budgets
                            for r in (b.ours, b.theirs)})
    main, theirs = roles.main, PLAIN_2DGS
    doc.heading("Convergence: RT-Splatting and plain 2DGS at several budgets")
    doc.paragraph(
        f"The runs of `{main}` and `{theirs}` at several budgets (`<method>_x<N>`: every iteration count of the "
        f"demo's schedule times N; benchmarks/convergence.yaml). A method has converged at the first budget whose "
        f"next one gained less than {CONVERGED_GAIN:g} dB of test PSNR per doubling of the budget, on the entire "
        "image and on the transparent region both. The gap is RT-Splatting minus 2DGS at the demo budget and at "
        "convergence: at the larger of the two methods' converged budgets, or at the largest budget, marked "
        "'not converged', where either method was still climbing. Layers: PSNR of the main method's reflection and "
        "transmission against the ground-truth layers inside the transparent mask, beside what the true reflection "
        "scores painted flat in its mean colour (a reflection without structure) and blurred by 2 pixels; a "
        "reflection that stays near the flat reference at convergence lacks structure by the method, not by the "
        f"budget. Time: {measure.label}.")
    doc.table(["scene", "budget", "dPSNR transp.", "dPSNR", f"{main} reflection", f"{main} transmission",
               "flat reference", "blurred 2 px reference", f"{main} {measure.label}", f"{theirs} {measure.label}",
               f"converged at ({main} / {theirs})"],
              [row for scene, b in series.items() for row in gap_rows(scene, b, references.get(scene), measure)])
    doc.paragraph("Every budget: test PSNR, its gain per doubling over the budget before it, and the layers (the "
                  "reflection also less the flat and the blurred references: positive means more structure than "
                  "that reference has).")
    doc.table(["scene", "run", "budget", "iterations", "PSNR", "PSNR transp.", "gain / doubling",
               "gain / doubling transp.", "reflection", "reflection - flat", "reflection - blurred 2 px",
               "transmission", measure.label],
              [row for scene, b in series.items() for row in budget_rows(scene, b, references.get(scene), measure)])
    doc.paragraph(
        f"At equal time, finished runs only: each budget of `{main}` against `{theirs}`'s finished runs at the same "
        f"training time ({measure.label}), read between the two {theirs} budgets around it, linear in log2 of the time "
        f"('-' where {theirs}'s largest budget took less time). The summary's equal-time gap instead reads the other "
        "run's log mid-schedule, where its learning rates are still high, which favours the shorter schedule.")
    doc.table(["scene", f"{main} budget", f"{main} {measure.label}", f"{theirs} budget in that time",
               "dPSNR transp. at equal time", "dPSNR at equal time"],
              [row for scene, b in series.items() for row in equal_time_rows(scene, b, measure)])
