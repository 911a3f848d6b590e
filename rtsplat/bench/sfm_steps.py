"""What each SfM step costs on a capture: ``python -m rtsplat.bench.sfm_steps <scene> [<scene> ...]``.

Runs ``rtsplat sfm`` (:func:`rtsplat.sfm.run_sfm`, from the images, ``sfm.use_dataset_model`` off)
on each scene folder (``<scene>/images``) once per ``--variant`` (a JSON object of ``sfm`` settings
laid over ``--base``), then prints one line per run: the seconds of every step from the summary's
``step_seconds``, the total, the registered views, the mean reprojection error, the matcher and
refinement decisions and, when the scene has a ``sparse/0``, the pose errors against it. Runs go
to a temporary folder unless ``--out`` keeps them.
"""

from __future__ import annotations

import argparse
import json
import tempfile
from pathlib import Path

from rtsplat.config import SfmConfig
from rtsplat.schema import from_dict
from rtsplat.sfm import run_sfm
from rtsplat.sfm.stats import STEPS


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("scenes", type=Path, nargs="+", help="scene folders with an images/ folder")
    parser.add_argument("--base", default='{"num_threads": 2}', help="sfm settings of every run (JSON)")
    parser.add_argument("--variant", action="append", default=None,
                        help="sfm settings of one run over --base (JSON; repeat for more runs; default: {})")
    parser.add_argument("--out", type=Path, help="keep the runs' outputs here (default: a temporary folder)")
    args = parser.parse_args(argv)
    base = {"use_dataset_model": False, **json.loads(args.base)}
    variants = args.variant or ["{}"]
    with tempfile.TemporaryDirectory(prefix="rtsplat-bench-sfm-") as tmp:
        root = args.out or Path(tmp)
        for scene in args.scenes:
            for k, variant in enumerate(variants):
                settings = {**base, **json.loads(variant)}
                cfg = from_dict(SfmConfig, settings, source="--base/--variant", root="sfm")
                s = run_sfm(scene, root / f"{scene.name}_{k}", cfg, progress=False, log=lambda line: None)
                steps = " ".join(f"{name}={s.step_seconds[name]:.1f}" for name in STEPS if name in s.step_seconds)
                refinement = s.refinement or {}
                decided = ("skipped" if refinement.get("skipped") else
                           ("kept" if refinement.get("kept") else ("not kept" if refinement else "off")))
                before = refinement.get("mean_reprojection_error_before")
                matched = refinement.get("matched_pairs")  # None: the attempt's matches reused
                pairs = f", {matched} pairs matched" if matched is not None else ", the attempt's matches"
                pose = ""
                if s.pose_errors:  # the scene's sparse/0 holds reference cameras
                    pose = (f"; vs sparse/0: rotation {s.pose_errors['rotation_error_deg_mean']:.3f} deg "
                            f"(orientation fit {s.pose_errors['orientation_aligned_rotation_error_deg_mean']:.3f}), "
                            f"centre {100 * s.pose_errors['center_error_relative']:.2f}%")
                print(f"{scene.name} {variant}: {s.seconds:.1f} s [{steps}] {s.registered}/{s.total} registered, "
                      f"{s.mean_reprojection_error:.3f} px, {s.num_points} points, track "
                      f"{s.mean_track_length or 0:.2f}; {s.matcher}: {s.matcher_reason}; refinement {decided}"
                      + (f" (from {before:.3f} px{pairs})" if before else "") + pose,
                      flush=True)


if __name__ == "__main__":
    from rtsplat.errors import run_command

    raise SystemExit(run_command("python -m rtsplat.bench.sfm_steps", main))
