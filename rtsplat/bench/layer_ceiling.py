"""What a reflection-layer PSNR means on a synthetic scene: ``python -m rtsplat.bench.layer_ceiling``.

``rtsplat metrics`` scores the reflection and transmission layers against Mitsuba's inside the
transparent mask. This prints, per prepared scene and over all its views with layers, the scores of the
references of :mod:`rtsplat.layer_references`, computed from the ground truth itself
(no reflection, the truth's mean colour painted flat, the truth blurred, the layers' sum against the image).

Then the image inside the mask: the true transmission alone and plus the reflection's mean colour against
the image. With ``--renders`` (a folder written by ``rtsplat render``), the run's reflection layer is scored
beside the layer references, with its mean and the correlation of its luminance with the truth's (per view,
then the mean), and its final image beside the image references, with the part of its error that follows the
true reflection's detail (``slope``: 1 where the error is that detail left out; ``share``: of the error's
energy; medians over the views).

    python -m rtsplat.bench.layer_ceiling --data demo/prepared/dome --renders demo/renders/dome/rtsplat
"""

from __future__ import annotations

import argparse
from pathlib import Path

from rtsplat.layer_references import ceilings, image_references, read_views, run_image, run_reflection


def _reflection_text(ours: dict) -> str:
    return (f"{ours['psnr']:6.2f}  (mean {ours['mean']:.3f} against {ours['truth mean']:.3f}, luminance correlation "
            f"{ours['correlation']:+.2f})")


def _image_text(ours: dict) -> str:
    return (f"{ours['psnr']:6.2f}  (its error along the reflection's detail: slope {ours['slope']:+.2f}, share "
            f"{ours['share']:.2f})")


# per section: its title, the references from the truth, the run's scores, how they are printed
SECTIONS = (
    ("the reflection layer inside the mask, PSNR dB", ceilings, run_reflection, _reflection_text),
    ("the image inside the mask, PSNR dB", image_references, run_image, _image_text),
)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", type=Path, action="append", required=True,
                        help="a prepared synthetic scene with ground-truth layers (repeatable)")
    parser.add_argument("--renders", type=Path, action="append", default=[],
                        help="a `rtsplat render` folder of a run on the matching --data (repeatable, in order)")
    args = parser.parse_args(argv)
    if args.renders and len(args.renders) != len(args.data):
        parser.error("give one --renders per --data, or none")
    for i, data in enumerate(args.data):
        views = read_views(data)
        renders = args.renders[i] if args.renders else None
        print(f"{data} ({len(views)} views with layers):")
        for title, references, run, describe in SECTIONS:
            print(f"  {title}")
            rows = {name: f"{value:6.2f}" for name, value in references(views).items()}
            if renders:
                rows[f"run {renders}"] = describe(run(views, renders))
            for name, text in rows.items():
                print(f"  {name:32s} {text}")
    return 0


if __name__ == "__main__":
    from rtsplat.errors import run_command

    raise SystemExit(run_command("python -m rtsplat.bench.layer_ceiling", main))
