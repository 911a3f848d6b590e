"""``rtsplat synth``: render a ground-truth benchmark scene with Mitsuba 3."""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from rtsplat.errors import PipelineError
from rtsplat.synth.catalog import SCENE_HELP
from rtsplat.synth.dataset import VIEW_RANGE, SynthConfig


def add_arguments(parser: argparse.ArgumentParser) -> None:
    d = SynthConfig()
    parser.add_argument("--scene", required=True, help=SCENE_HELP)
    parser.add_argument("--out", required=True, type=Path, help="output dataset directory")
    parser.add_argument(
        "--views",
        type=int,
        default=d.views,
        help=f"number of views, {VIEW_RANGE[0]}-{VIEW_RANGE[1]} (default {d.views})",
    )
    parser.add_argument("--width", type=int, default=d.width, help=f"image width (default {d.width})")
    parser.add_argument("--height", type=int, default=d.height, help=f"image height (default {d.height})")
    parser.add_argument("--spp", type=int, default=d.spp, help=f"samples per pixel (default {d.spp})")
    parser.add_argument(
        "--layer-spp",
        type=int,
        default=d.layer_spp,
        help=f"samples per pixel of the layers, 0 = no layers (default {d.layer_spp})",
    )
    parser.add_argument(
        "--layers-every",
        type=int,
        default=d.layers_every,
        help="render the layers only for views 0, K, 2K, ... (default 1 = all); K = 8 gives exactly the test "
        "views of 'rtsplat prepare' (test_every 8) when every view registers",
    )
    parser.add_argument("--seed", type=int, default=d.seed, help=f"random seed (default {d.seed})")
    parser.add_argument("--max-depth", type=int, default=d.max_depth, help=f"path tracer depth (default {d.max_depth})")
    parser.add_argument("--overwrite", action="store_true", help="replace an existing output directory")
    parser.add_argument(
        "--any-views",
        action="store_true",
        help=f"allow view counts outside {VIEW_RANGE[0]}-{VIEW_RANGE[1]} (tests, debugging)",
    )
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")


def run(args: argparse.Namespace) -> int:
    config = SynthConfig(
        scene=args.scene,
        views=args.views,
        width=args.width,
        height=args.height,
        spp=args.spp,
        layer_spp=args.layer_spp,
        layers_every=args.layers_every,
        seed=args.seed,
        max_depth=args.max_depth,
        allow_any_views=args.any_views,
    )
    config.validate()
    if args.out.exists() and not args.overwrite:
        raise PipelineError("the output exists", path=args.out, fix="pass --overwrite to replace it")
    try:
        import mitsuba  # noqa: F401
    except ImportError as exc:
        raise PipelineError(f"Mitsuba 3 is not installed ({exc})", fix="pip install 'mitsuba>=3.5'") from None
    from rtsplat.synth.dataset import render_dataset

    start = time.perf_counter()
    summary = render_dataset(config, args.out, overwrite=args.overwrite, progress=not args.no_progress)
    check = summary.layer_check
    print(
        f"rtsplat synth: {summary.views} views of '{config.scene}' in {args.out} ({time.perf_counter() - start:.1f} s)"
    )
    if check.get("pixels_channels"):
        print(
            f"  see-through pixels: {summary.transparent_pixels}; R + T - full (linear RGB): "
            f"mean {check['mean_residual']:+.5f} ({check['relative_residual']:+.2%} of the "
            f"mean {check['mean_full']:.4f}, {check['residual_z']:+.1f} standard errors), "
            f"per-pixel mean |.| {check['mean_abs_residual']:.4f}"
        )
    return 0
