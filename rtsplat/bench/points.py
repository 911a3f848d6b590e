"""Time and peak memory of the per-point steps at real-capture sizes: ``python -m rtsplat.bench.points``.

The clouds are random points on surfaces (:func:`surface_cloud`: three planes of a room corner and two
spheres, with 0.2% noise), of ``--sizes`` points (default 30k, 300k and 1M). The steps:

* ``scale``: :func:`rtsplat.model.surfels.nearest_neighbour_scale` (RMS distance to the 3 nearest);
* ``normals``: :func:`rtsplat.model.surfels.point_cloud_normals` (least-spread axis of the 16 nearest);
* ``init``: :func:`rtsplat.model.surfels.init_from_points` of every point with its normal: one surfel per
  point, no cap (scale, normals and all parameters);
* ``start``: what the trainer starts with (:func:`rtsplat.train.initial.initial_surfels`) under the
  default cap (:func:`rtsplat.train.initial.starting_cap`: half of ``densify.max_surfels``, one per
  training pixel) for ``--train-pixels`` pixels (default: 38 training views of 1008x756) and 4 copies
  per point: 30k points start 90k surfels (3 copies), more than 100k points a random 100k;
* ``densify``: one density-control step (:class:`rtsplat.train.density.DensityControl`, clone, split
  and prune, with the Adam state carried along) on as many surfels, with random statistics under
  which about 10% of them are cloned or split and 5% pruned.

Each (step, size) runs alone in a fresh process with ``--threads`` torch threads (the k-d tree queries
use as many): the time is the step's wall clock (``time.perf_counter``); the memory is the process's
peak resident set during the step (Linux's ``VmHWM`` of ``/proc/self/status``, reset just before the
step by writing 5 to ``/proc/self/clear_refs``, so the building of the inputs does not count) and its
rise over the resident set just before the step (``VmRSS``, which holds the inputs). Resident memory
counts torch's and numpy's allocations alike (``tracemalloc`` sees only the Python allocator's, not
torch's). Building the inputs and importing scipy's k-d tree are not timed. Linux only (``/proc``).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
import time

STEPS = ("scale", "normals", "init", "start", "densify")
DEFAULT_SIZES = (30_000, 300_000, 1_000_000)
DEFAULT_TRAIN_PIXELS = 38 * 1008 * 756  # the glass capture's training views at images_4 size


def surface_cloud(n: int, seed: int = 0):
    """``n`` points [n,3] (float32) on a room corner (floor and two walls, 4 x 4) and two spheres
    (radius 0.5 and 0.8), a fifth of them on each, with Gaussian noise of 0.002 x the extent along
    every axis, and random colours [n,3] in [0,1]."""
    import torch

    g = torch.Generator().manual_seed(seed)
    parts = []
    sizes = [n // 5 + (1 if i < n % 5 else 0) for i in range(5)]
    for axis, count in zip((2, 0, 1), sizes[:3], strict=True):  # floor z=0, walls x=0 and y=0
        p = torch.rand(count, 3, generator=g) * 4.0
        p[:, axis] = 0.0
        parts.append(p)
    for (centre, radius), count in zip((((1.5, 1.5, 0.5), 0.5), ((2.8, 1.0, 0.8), 0.8)), sizes[3:], strict=True):
        direction = torch.nn.functional.normalize(torch.randn(count, 3, generator=g), dim=1)
        parts.append(torch.tensor(centre) + radius * direction)
    xyz = torch.cat(parts)
    xyz += 0.002 * 4.0 * torch.randn(xyz.shape, generator=g)
    return xyz, torch.rand(n, 3, generator=g)


def _memory_status(field: str) -> int:
    """``VmRSS`` or ``VmHWM`` (the peak since the last reset) of this process, in bytes."""
    with open("/proc/self/status") as fh:
        line = next(line for line in fh if line.startswith(field + ":"))
    return int(line.split()[1]) * 1024  # kB


def _reset_peak() -> None:
    with open("/proc/self/clear_refs", "w") as fh:
        fh.write("5")


def _densify_inputs(xyz, rgb):
    """Surfels at the points with random sizes and occupancies, a DensityControl whose statistics
    select about 10% of them, an Adam optimizer with moments for every row."""
    import torch

    from rtsplat.model.sh import num_coefficients, rgb_to_sh_dc
    from rtsplat.model.surfels import PARAMETERS, SurfelParameters, logit
    from rtsplat.train.density import DensityControl
    from rtsplat.train.optim import build_optimizer
    from rtsplat.train_config import Densification, Schedule, TrainConfig

    n = xyz.shape[0]
    g = torch.Generator().manual_seed(1)
    tensors = {
        "means": xyz, "quats": torch.nn.functional.normalize(torch.randn(n, 4, generator=g), dim=1),
        "log_scales": math.log(0.01) + 0.5 * torch.randn(n, 2, generator=g),  # about half above percent_dense
        "occupancy_logit": torch.logit(torch.rand(n, generator=g) * 0.9 + 0.1 / 18),  # ~5% below 0.05
        "opacity_logit": torch.full((n,), logit(0.5)), "sh_dc": rgb_to_sh_dc(rgb)[:, None, :],
        "sh_rest": torch.zeros(n, num_coefficients(3) - 1, 3), "scatter_logit": torch.logit(rgb.clamp(0.02, 0.98)),
        "transmissivity_logit": torch.zeros(n), "roughness_logit": torch.zeros(n),
        "material_raw": 0.1 * torch.randn(n, 4, generator=g), "reflectance_logit": torch.zeros(n),
    }
    surfels = SurfelParameters(tensors)
    config = Densification(max_surfels=4 * n)
    control = DensityControl(config, Schedule(iterations=10, densify_from=1, densify_until=10, densify_every=1),
                             extent=1.0)
    # mean gradients: exponential with mean 1e-4, so that exp(-2) ~ 13.5% reach the 2e-4 threshold
    control.grad_sum = -1e-4 * torch.log(torch.rand(n, generator=g))
    control.grad_count = torch.ones(n)
    control.max_radius = torch.zeros(n)
    control.seen_since_reset = torch.ones(n, dtype=torch.bool)
    control.resets_done = 1  # size pruning on, as after the first reset
    optimizer = build_optimizer(torch.nn.Module(), surfels, TrainConfig().lr, 1.0)
    for name in PARAMETERS:  # one Adam step, so that every row has moments to carry
        getattr(surfels, name).grad = torch.randn(getattr(surfels, name).shape, generator=g)
    optimizer.step()
    optimizer.zero_grad(set_to_none=True)
    return surfels, control, optimizer


def run_step(step: str, n: int, train_pixels: int) -> dict:
    """Build the inputs of ``step`` at ``n`` points, then time it; time and memory as in the module doc."""
    import scipy.spatial  # noqa: F401  (imported on first use by the k-d tree: here, untimed)
    import torch

    from rtsplat.model.surfels import init_from_points, nearest_neighbour_scale, point_cloud_normals
    from rtsplat.train.initial import initial_surfels, plan_starting_surfels, starting_cap
    from rtsplat.train_config import Densification

    xyz, rgb = surface_cloud(n)
    extra: dict = {}
    if step == "scale":
        work = lambda: nearest_neighbour_scale(xyz)  # noqa: E731
    elif step == "normals":
        work = lambda: point_cloud_normals(xyz)  # noqa: E731
    elif step == "init":
        work = lambda: init_from_points(xyz, rgb, normals=point_cloud_normals(xyz),  # noqa: E731
                                        generator=torch.Generator().manual_seed(0))
    elif step == "start":
        plan = plan_starting_surfels(n, Densification().initial_copies, starting_cap(Densification(), train_pixels))
        extra["surfels"] = plan.surfels
        work = lambda: initial_surfels(xyz, rgb, plan, torch.Generator().manual_seed(0),  # noqa: E731
                                       point_normals=True)
    elif step == "densify":
        surfels, control, optimizer = _densify_inputs(xyz, rgb)
        generator = torch.Generator().manual_seed(0)

        def work():
            events, _ = control.step(1, surfels, optimizer, generator)
            extra.update(cloned=events.cloned, split=events.split, pruned=events.pruned, surfels=len(surfels))
    else:
        raise ValueError(f"unknown step {step!r}; one of {', '.join(STEPS)}")
    before = _memory_status("VmRSS")
    _reset_peak()
    start = time.perf_counter()
    work()
    seconds = time.perf_counter() - start
    peak = _memory_status("VmHWM")
    return {"step": step, "points": n, "seconds": seconds, "peak_mb": peak / 2**20,
            "rise_mb": max(peak - before, 0) / 2**20, **extra}


def _in_fresh_process(step: str, n: int, threads: int, train_pixels: int) -> dict:
    command = [sys.executable, "-m", "rtsplat.bench.points", "--one", step, str(n), "--threads", str(threads),
               "--train-pixels", str(train_pixels)]
    done = subprocess.run(command, capture_output=True, text=True, check=False)
    if done.returncode != 0:
        raise RuntimeError(f"{step} at {n} points failed:\n{done.stderr}")
    return json.loads(done.stdout.strip().splitlines()[-1])


def format_table(rows: list[dict]) -> str:
    lines = ["| step | points | seconds | peak RSS in the step (MB) | rise over the inputs (MB) | notes |",
             "|---|---:|---:|---:|---:|---|"]
    for r in rows:
        notes = ", ".join(f"{k} {r[k]}" for k in ("surfels", "cloned", "split", "pruned") if k in r)
        lines.append(f"| {r['step']} | {r['points']:,} | {r['seconds']:.2f} | {r['peak_mb']:.0f} | "
                     f"{r['rise_mb']:.0f} | {notes} |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m rtsplat.bench.points", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sizes", type=int, nargs="+", default=list(DEFAULT_SIZES), help="cloud sizes")
    parser.add_argument("--steps", nargs="+", choices=STEPS, default=list(STEPS), help="steps to run")
    parser.add_argument("--threads", type=int, default=2, help="torch threads (and k-d tree workers); default 2")
    parser.add_argument("--train-pixels", type=int, default=DEFAULT_TRAIN_PIXELS,
                        help="training pixels for the start step's cap (default: 38 views of 1008x756)")
    parser.add_argument("--json", help="also write the rows to this JSON file")
    parser.add_argument("--one", nargs=2, metavar=("STEP", "POINTS"), help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    import torch

    torch.set_num_threads(args.threads)
    if args.one:
        print(json.dumps(run_step(args.one[0], int(args.one[1]), args.train_pixels)))
        return 0
    rows = []
    for n in args.sizes:
        for step in args.steps:
            rows.append(_in_fresh_process(step, n, args.threads, args.train_pixels))
            print(f"{step} at {n:,} points: {rows[-1]['seconds']:.2f} s, peak {rows[-1]['peak_mb']:.0f} MB",
                  file=sys.stderr, flush=True)
    print(f"{args.threads} torch threads, {os.cpu_count()} CPUs")
    print(format_table(rows))
    if args.json:
        from pathlib import Path

        from rtsplat.io.atomic import write_text_atomic

        write_text_atomic(Path(args.json), json.dumps(rows, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    from rtsplat.errors import run_command

    raise SystemExit(run_command("python -m rtsplat.bench.points", main))
