"""Seconds per video frame of ``rtsplat video``: ``python -m rtsplat.bench.video [--run RUN --data PREPARED]``.

Renders the run along the orbit path at each ``--widths`` (default 200 and 640 pixels; the height keeps
the training cameras' aspect, 150 and 480 for 4:3 cameras) and prints, per size, the seconds per
frame of the whole video (render + H.264 encoding), of rendering and encoding alone, and the CPU
seconds per frame (all threads) with how many cores other processes kept busy meanwhile, as
:func:`rtsplat.video.render_video` measures them (:mod:`rtsplat.usage`). ``--run``/``--data``: a trained
run and its prepared scene, e.g. ``demo/results/dome/runs/rtsplat`` and ``demo/results/dome/prepared``
after ``make demo``.
Without them, a toy scene (:mod:`rtsplat.bench.toy_scene`, 12 views at 100x75) is trained for
``--iterations`` with the demo's model settings first: far fewer surfels than the demo's model, so its
times are a lower bound. One untimed 2-frame video first (compilation, caches); the sizes are then
timed in interleaved rounds and the median is printed. On a machine shared with other jobs the
wall times are noisy; the CPU seconds, and the ratio between the sizes measured in one run, are the
steadier numbers.
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
from pathlib import Path

import torch


def train_toy(root: Path, iterations: int) -> tuple[Path, Path]:
    """A toy scene trained with the demo's model settings: (run folder, prepared scene folder)."""
    from rtsplat.bench.iteration import demo_environment_map
    from rtsplat.bench.toy_scene import train_quietly, write_scene

    scene = write_scene(root / "scene", views=12, width=100, height=75)
    schedule = {"iterations": iterations, "volume_until": iterations // 6, "specular_from": iterations // 3,
                "densify_from": iterations // 4, "densify_every": max(iterations // 12, 1), "reset_every": 0,
                "eval_every": 0, "checkpoint_every": 0, "log_every": 10**9}
    train_quietly(scene, root / "run", schedule, demo_environment_map())
    return root / "run", root / "scene"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--run", type=Path, help="a trained run (default: a toy scene trained first)")
    parser.add_argument("--data", type=Path, help="the prepared scene of --run")
    parser.add_argument("--widths", type=int, nargs="+", default=[200, 640], help="frame widths to time")
    parser.add_argument("--frames", type=int, default=12, help="frames per timed video")
    parser.add_argument("--rounds", type=int, default=2, help="interleaved rounds over the sizes (median)")
    parser.add_argument("--panels", action="store_true", help="time the five-panel frames")
    parser.add_argument("--iterations", type=int, default=120, help="training iterations of the toy model")
    parser.add_argument("--threads", type=int, help="torch threads (default: torch's)")
    parser.add_argument("--device", default="auto", help="auto, cpu, cuda, cuda:N")
    args = parser.parse_args(argv)
    if (args.run is None) != (args.data is None):
        parser.error("give --run and --data together, or neither (toy model)")
    if args.threads:
        torch.set_num_threads(args.threads)

    from rtsplat.video import render_video

    with tempfile.TemporaryDirectory(prefix="rtsplat-bench-video-") as tmp:
        tmp = Path(tmp)
        run, data = (args.run, args.data) if args.run else train_toy(tmp / "toy", args.iterations)
        model = "toy model" if args.run is None else str(run)
        render_video(run, data, tmp / "warmup.mp4", frames=2, width=min(args.widths), panels=args.panels,
                     device=args.device, progress=False)
        results: dict[int, list[dict]] = {w: [] for w in args.widths}
        for round_index in range(args.rounds):
            order = args.widths if round_index % 2 == 0 else list(reversed(args.widths))
            for width in order:
                results[width].append(render_video(run, data, tmp / f"w{width}.mp4", frames=args.frames, width=width,
                                                   panels=args.panels, device=args.device, progress=False))
    first = results[args.widths[0]][0]
    print(f"{model}: {first['surfels']} surfels, {first['device']}, {args.frames} frames per video, "
          f"orbit path, {'five panels' if args.panels else 'image only'}, median of {args.rounds} round(s)")
    print(f"{'size':>10} {'s/frame':>9} {'render s/frame':>15} {'encode s/frame':>15} {'CPU s/frame':>12} "
          f"{'other cores busy':>17}")
    base = None
    for width in args.widths:
        runs = results[width]
        total = statistics.median(r["seconds_per_frame"] for r in runs)
        render = statistics.median(r["render_seconds_per_frame"] for r in runs)
        encode = statistics.median(r["encode_seconds_per_frame"] for r in runs)
        cpu = statistics.median(r["cpu_seconds_per_frame"] for r in runs)
        busy = [r["timing"].get("other_busy_cores") for r in runs]
        busy_text = "/".join("?" if b is None else f"{b:.1f}" for b in busy)
        base = base or total
        print(f"{runs[0]['width']:>5}x{runs[0]['height']:<4} {total:>9.3f} {render:>15.3f} {encode:>15.4f} "
              f"{cpu:>12.3f} {busy_text:>17}   (wall {total / base:.2f}x the first size)")
    return 0


if __name__ == "__main__":
    from rtsplat.errors import run_command

    raise SystemExit(run_command("python -m rtsplat.bench.video", main))
