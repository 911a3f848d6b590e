"""``rtsplat sfm``: camera poses and sparse points with pycolmap.

* :mod:`rtsplat.sfm.stage`: the orchestrator :func:`run_sfm` and the CLI (``add_arguments``, ``run``);
* :mod:`rtsplat.sfm.matching`: the matcher chosen from the capture, the features and matches;
* :mod:`rtsplat.sfm.attempts`: one attempt (extraction, matching, mapping) and the ladder of retries;
* :mod:`rtsplat.sfm.refine`: the refinement of the chosen model and when it is skipped;
* :mod:`rtsplat.sfm.stats`: the model statistics and the per-step seconds every part reports.

pycolmap is imported inside the functions that use it, so importing the package stays cheap.
"""

from rtsplat.sfm.stage import SfmSummary, add_arguments, run, run_sfm

__all__ = ["SfmSummary", "add_arguments", "run", "run_sfm"]
