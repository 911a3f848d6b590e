"""The ``rtsplat`` command: one subcommand per pipeline stage.

Each stage lives in its own module that exposes two functions:

* ``add_arguments(parser: argparse.ArgumentParser) -> None``
* ``run(args: argparse.Namespace) -> int``  (the exit status)

The CLI only parses arguments, sets the C heap to keep what it frees (:mod:`rtsplat.heap`) and calls
``run``; the work is done by the stage's function API.
Stage modules are imported lazily, so ``rtsplat --help`` stays fast and a stage's heavy
dependencies (pycolmap, mitsuba, onnxruntime, ...) are loaded only when that stage runs.

Exit statuses, the same for every stage:

* 0: done;
* 1: bad input. A stage's ``run`` raises :class:`rtsplat.errors.PipelineError` (or a subclass such
  as :class:`~rtsplat.errors.ConfigError`) and never catches it; :func:`main` prints it once as
  ``rtsplat <stage>: error: <message>`` on stderr (:func:`rtsplat.errors.run_command`, which the
  ``python -m rtsplat.*`` commands use too);
* 2: a command-line usage error (argparse's own status);
* 3: the stage is not implemented;
* 130: interrupted (ctrl-C); stages write their outputs atomically, so nothing partial is left.
"""

from __future__ import annotations

import argparse
import importlib
import sys
from dataclasses import dataclass

from rtsplat.errors import BAD_INPUT_EXIT, INTERRUPTED_EXIT, run_command  # noqa: F401 (the exit statuses)
from rtsplat.heap import keep_freed_memory

NOT_IMPLEMENTED_EXIT = 3


@dataclass(frozen=True)
class Stage:
    name: str
    module: str  # module exposing add_arguments() and run()
    help: str


STAGES: tuple[Stage, ...] = (
    Stage("frames", "rtsplat.frames", "take a scene's photos from its video (the sharpest frame of each stretch)"),
    Stage("sfm", "rtsplat.sfm", "structure from motion with pycolmap (skipped when sparse/0 exists)"),
    Stage("masks", "rtsplat.masks", "ingest or segment (ONNX) the transparent-surface masks"),
    Stage("prepare", "rtsplat.prepare", "downsample, region of interest, train/test split"),
    Stage("train", "rtsplat.train.cli", "train an RT-Splatting model on a prepared scene"),
    Stage("render", "rtsplat.render", "render test views, decomposed layers and measure FPS"),
    Stage("video", "rtsplat.video", "render a trained run along a camera path into an MP4 (H.264)"),
    Stage("fps", "rtsplat.fps", "time the test views' renders in a job of their own (FPS)"),
    Stage("view", "rtsplat.viewer", "look at a trained run in the browser: layers, scene edits, views"),
    Stage("metrics", "rtsplat.metrics", "PSNR/SSIM/LPIPS on the entire image and transparent region"),
    Stage("report", "rtsplat.report", "benchmark report (HTML + Markdown)"),
    Stage("synth", "rtsplat.synth.cli", "render a ground-truth benchmark scene with Mitsuba 3"),
    Stage("demo", "rtsplat.demo", "rasterizer demo: render a small random surfel scene to PNG"),
)


def _load(stage: Stage):
    """Import a stage module; None when that module does not exist yet."""
    try:
        return importlib.import_module(stage.module)
    except ModuleNotFoundError as exc:
        # Only "this stage's module is missing" means not implemented; a missing dependency
        # inside an existing module is a real error and must surface.
        missing = exc.name or ""
        if stage.module == missing or stage.module.startswith(missing + "."):
            return None
        raise


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="rtsplat",
        description="RT-Splatting reconstruction pipeline. Every stage is also a Snakemake rule; "
        "run 'rtsplat <stage> --help' for a stage's options.",
    )
    from rtsplat import __version__

    parser.add_argument("--version", action="version", version=f"rtsplat {__version__}")
    sub = parser.add_subparsers(dest="stage", metavar="<stage>")
    for stage in STAGES:
        sub.add_parser(stage.name, help=stage.help, description=stage.help, add_help=False)
    return parser


def stage_parser(stage: Stage, module) -> argparse.ArgumentParser:
    """The argument parser of one stage (``module``: the stage's loaded module)."""
    parser = argparse.ArgumentParser(prog=f"rtsplat {stage.name}", description=stage.help)
    module.add_arguments(parser)
    return parser


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    parser = build_parser()
    if not argv or argv[0] not in {s.name for s in STAGES}:
        args = parser.parse_args(argv)  # handles --help/--version and unknown stages
        parser.print_help()
        return 2
    stage = next(s for s in STAGES if s.name == argv[0])
    module = _load(stage)
    if module is None:
        print(
            f"rtsplat {stage.name}: this stage is not implemented yet ({stage.help}).",
            file=sys.stderr,
        )
        return NOT_IMPLEMENTED_EXIT
    args = stage_parser(stage, module).parse_args(argv[1:])
    keep_freed_memory()  # a stage's large torch buffers reuse their pages from one step to the next
    return run_command(f"rtsplat {stage.name}", lambda: module.run(args))


if __name__ == "__main__":
    sys.exit(main())
