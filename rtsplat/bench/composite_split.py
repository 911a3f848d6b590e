"""Where RT-Splatting's compositing time goes against a baseline's: ``python -m rtsplat.bench.composite_split``.

Times the ``cpu`` rasterizer's compositing (forward and backward, the backend's autograd function, measured by
wrapping it from outside) on the training views of two trained runs of one prepared scene: ``--run`` (an
RT-Splatting run) and ``--baseline`` (e.g. 2DGS, transmission and specular off). The RT-Splatting run is timed
three ways, so that its extra time over the baseline splits into three parts:

* ``channels``: with its G-buffer channels (:meth:`rtsplat.model.rtmodel.RTModel.gbuffer_channels`) against
  without them: what blending the surface attributes costs;
* ``see-through``: without channels, against without channels and with every optical opacity set to 1, so that
  the volume weights end where the surface weights do: what walking on behind the see-through surfaces costs
  (the image is then wrong; only the time is read);
* ``the rest``: that last variant against the baseline: more surfels, and larger ones, at the same walk.

Each view's surfels are built once, outside the clock, from the run's model at its pose-corrected camera, at the
model's SH degree; the loss is a fixed random mix of every output (:func:`rtsplat.bench.raster._loss`). Rounds
are interleaved over the variants, the order alternating; medians over the rounds, ms per view. One thread
(torch and numba), the C heap set as ``rtsplat train`` sets it (:mod:`rtsplat.heap`).
"""

from __future__ import annotations

import argparse
import statistics
from dataclasses import replace
from pathlib import Path

import torch

VARIANTS = ("rtsplat", "no channels", "no channels, opacity 1", "baseline")


def view_surfels(run, views: int, channels: tuple[str, ...] | None, opaque: bool) -> list:
    """(surfels, camera) of the first ``views`` cameras of a loaded run (:func:`rtsplat.render.load_run`), without
    autograd: ``channels`` as :meth:`~rtsplat.model.rtmodel.RTModel.rasterizer_surfels` takes them, every opacity
    set to 1 where ``opaque``."""
    out = []
    with torch.no_grad():
        for camera in run.cameras[:views]:
            surfels = run.model.rasterizer_surfels(camera, channels=channels)
            if opaque:
                surfels = replace(surfels, opacity=torch.ones_like(surfels.opacity))
            out.append((surfels, camera))
    return out


def composite_ms(views: list) -> tuple[float, float]:
    """Mean forward and backward ms per view of the compositing (the ``cpu`` backend's autograd function)."""
    from rtsplat.bench.raster import _loss, with_grad
    from rtsplat.bench.raster_cpu import timed_compositing
    from rtsplat.raster import rasterize

    with timed_compositing({"forward": 0.0, "backward": 0.0}) as spent:
        for surfels, camera in views:
            _loss(rasterize(with_grad(surfels), camera, backend="cpu")).backward()
    return 1000.0 * spent["forward"] / len(views), 1000.0 * spent["backward"] / len(views)


def measure(run_dir: Path, baseline_dir: Path, data: Path, views: int, rounds: int) -> dict:
    """Median forward and backward ms per view of every variant, and the surfel counts."""
    from rtsplat.render import load_run

    run = load_run(run_dir, data, split="train", backend="cpu", device="cpu")
    baseline = load_run(baseline_dir, data, split="train", backend="cpu", device="cpu")
    inputs = {
        "rtsplat": view_surfels(run, views, None, False),
        "no channels": view_surfels(run, views, (), False),
        "no channels, opacity 1": view_surfels(run, views, (), True),
        "baseline": view_surfels(baseline, views, None, False),
    }
    for variant in VARIANTS:  # a warm-up pass each: the kernels loaded, the heap grown
        composite_ms(inputs[variant][:1])
    times: dict[str, list[tuple[float, float]]] = {variant: [] for variant in VARIANTS}
    for index in range(rounds):
        for variant in (VARIANTS if index % 2 == 0 else VARIANTS[::-1]):
            times[variant].append(composite_ms(inputs[variant]))
    medians = {variant: tuple(statistics.median(t[i] for t in values) for i in (0, 1))
               for variant, values in times.items()}
    return {"ms": medians, "surfels": (len(run.model.surfels), len(baseline.model.surfels)),
            "channels": run.model.gbuffer_channels()}


def split_lines(result: dict) -> list[str]:
    """The table and the split of the extra time, as printed."""
    ms = result["ms"]
    total = {variant: sum(ms[variant]) for variant in VARIANTS}
    lines = [f"surfels: run {result['surfels'][0]}, baseline {result['surfels'][1]}; the run's channels: "
             f"{', '.join(result['channels']) or 'none'}",
             f"{'variant':<24}{'forward':>10}{'backward':>10}{'total':>10}  (ms per view)"]
    lines += [f"{variant:<24}{ms[variant][0]:>10.2f}{ms[variant][1]:>10.2f}{total[variant]:>10.2f}"
              for variant in VARIANTS]
    extra = total["rtsplat"] - total["baseline"]
    parts = {"channels": total["rtsplat"] - total["no channels"],
             "see-through": total["no channels"] - total["no channels, opacity 1"],
             "the rest": total["no channels, opacity 1"] - total["baseline"]}
    lines.append(f"the run's compositing: {total['rtsplat'] / total['baseline']:.2f}x the baseline's, "
                 f"{extra:+.2f} ms per view")
    if extra > 0:
        lines.append("of the extra: " + ", ".join(f"{name} {value:+.2f} ms ({100 * value / extra:.0f}%)"
                                                  for name, value in parts.items()))
    return lines


def main(argv: list[str] | None = None) -> int:
    from rtsplat.heap import keep_freed_memory

    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--run", type=Path, required=True, help="the RT-Splatting run directory (its model.pt)")
    parser.add_argument("--baseline", type=Path, required=True, help="the baseline's run directory (e.g. 2dgs)")
    parser.add_argument("--data", type=Path, required=True, help="the prepared scene both were trained on")
    parser.add_argument("--views", type=int, default=8, help="training views timed per round (default 8)")
    parser.add_argument("--rounds", type=int, default=5, help="interleaved rounds (default 5)")
    args = parser.parse_args(argv)
    if min(args.views, args.rounds) < 1:
        parser.error("--views and --rounds must be at least 1")
    keep_freed_memory()
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        result = measure(args.run, args.baseline, args.data, args.views, args.rounds)
    finally:  # the caller's thread count back (the tests call main in their own process)
        torch.set_num_threads(threads)
    print("\n".join(split_lines(result)))
    return 0


if __name__ == "__main__":
    from rtsplat.errors import run_command

    raise SystemExit(run_command("python -m rtsplat.bench.composite_split", main))
