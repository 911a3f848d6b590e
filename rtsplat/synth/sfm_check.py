"""Check a synthetic dataset against structure from motion: registration, reprojection error,
and pose error after a similarity fit to the ground-truth cameras.

Used by the test suite; also handy by hand::

    python -m rtsplat.synth.sfm_check <dataset dir> <work dir> [--max-attempts N]

SfM is the pipeline's own stage (:func:`rtsplat.sfm.run_sfm`, from the images alone, one shared
``SIMPLE_PINHOLE`` camera whose focal length is estimated); the pose errors are
:func:`rtsplat.pose_eval.compare_poses` against the dataset's ``sparse/0``, which the stage computes
whenever a dataset ships a model it does not use.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path


def check_dataset(dataset_dir: str | Path, work_dir: str | Path, num_threads: int = 2, max_attempts: int = 4) -> dict:
    """Run the sfm stage on ``dataset_dir`` into ``work_dir``; registration and pose errors as a dict.

    Keys: ``views``, ``registered``, ``registered_ratio``, ``mean_reprojection_error_px``,
    ``attempts`` (name, registered count per attempt) and the :class:`rtsplat.pose_eval.PoseErrors`
    fields (absent when fewer than 3 views registered). Raises :class:`rtsplat.errors.PipelineError`
    when SfM fails.
    """
    from rtsplat.config import SfmConfig
    from rtsplat.sfm import run_sfm

    cfg = SfmConfig(
        use_dataset_model=False, camera_model="SIMPLE_PINHOLE", num_threads=num_threads, max_attempts=max_attempts
    )
    s = run_sfm(dataset_dir, work_dir, cfg, progress=False, log=lambda line: None)
    return {
        "views": s.total,
        "registered": s.registered,
        "registered_ratio": s.registered / s.total,
        "mean_reprojection_error_px": s.mean_reprojection_error,
        "points3D": s.num_points,
        "attempts": [(a["name"], a["registered"]) for a in s.attempts],
        **(s.pose_errors or {}),
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m rtsplat.synth.sfm_check", description=__doc__.split("\n\n")[0])
    parser.add_argument("dataset", type=Path, help="a dataset written by 'rtsplat synth'")
    parser.add_argument("work", type=Path, help="output folder of the sfm stage (replaced)")
    parser.add_argument("--max-attempts", type=int, default=4, help="sfm.max_attempts (1: no retries)")
    args = parser.parse_args(argv)
    if not (args.dataset / "images").is_dir() or not (args.dataset / "sparse" / "0").is_dir():
        print(f"sfm_check: error: {args.dataset} is not a synth dataset (images/ and sparse/0)", file=sys.stderr)
        return 2
    from rtsplat.errors import run_command

    return run_command("sfm_check", lambda: print(json.dumps(check_dataset(args.dataset, args.work,
                                                                          max_attempts=args.max_attempts), indent=1)))


if __name__ == "__main__":
    sys.exit(main())
