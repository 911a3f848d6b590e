"""Which colour of the mask files is the see-through surface (``masks.polarity``)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from rtsplat.config import MasksConfig


@dataclass(frozen=True)
class PolarityDecision:
    """Which mask colour is read as see-through (``white`` or ``black``), why, and a warning (empty when
    there is none) for masks that look unusual: under ``masks.polarity: auto`` the masks are kept as given
    whatever they cover, and white covering more than ``masks.max_coverage`` of the photos on average is
    flagged, naming the photos it covers most of and the fix."""

    polarity: str
    reason: str
    warning: str = ""


HIGH_COVERAGE_EXAMPLES = 3  # photos a high-coverage warning names


def decide_polarity(coverage: dict[str, float], cfg: MasksConfig, what: str = "the mask files") -> PolarityDecision:
    """The polarity of mask files of these coverages (by photo stem or name): ``masks.polarity`` when set;
    ``auto`` keeps them as given (white = see-through) and never inverts on coverage, since glass that fills
    the view (a shop window, an aquarium, a windshield from the driver's seat) covers most of each photo just
    as an inverted mask of a small pane does; it warns when white covers more than ``masks.max_coverage`` on
    average. ``what`` names the masks in the messages."""
    mean = float(np.mean(list(coverage.values()))) if coverage else 0.0
    if cfg.polarity == "white":
        return PolarityDecision("white", f"masks.polarity: white: white = see-through (white covers "
                                f"{100 * mean:.1f}% of the photos on average in {what})")
    if cfg.polarity == "black":
        return PolarityDecision("black", f"masks.polarity: black: {what} inverted, black = see-through (black "
                                f"covers {100 * (1 - mean):.1f}% of the photos on average)")
    reason = (f"masks.polarity: auto: white = see-through, kept as given (white covers {100 * mean:.1f}% of the "
              f"photos on average in {what})")
    if mean <= cfg.max_coverage:
        return PolarityDecision("white", reason)
    most = sorted(coverage.items(), key=lambda item: (-item[1], item[0]))[:HIGH_COVERAGE_EXAMPLES]
    examples = ", ".join(f"{name} {100 * value:.0f}%" for name, value in most)
    warning = (f"white covers {100 * mean:.1f}% of the photos on average in {what} (more than masks.max_coverage "
               f"{100 * cfg.max_coverage:g}%; most: {examples}): kept as given, white = see-through. Right for "
               "glass that fills the view (a shop window, an aquarium, a windshield); if white marks what is "
               "not see-through instead, set masks.polarity: black (masks.polarity: white silences this)")
    return PolarityDecision("white", reason, warning)
