"""``rtsplat fps``: the rendering speed of a trained run, timed in a job of its own.

Loads the run like ``rtsplat render`` (:func:`rtsplat.render.load_run`), renders every test view
``render.fps_rounds`` times after ``render.warmup`` untimed renders, writes nothing but the JSON file
``--out``: ``fps`` (frames / wall seconds) and ``timing``, the wall and CPU seconds of the timed renders,
CPU seconds per frame, the threads used, how busy the other cores of the machine were meanwhile
(``other_busy_cores``, :mod:`rtsplat.usage`) and ``scheduled_alone``, true when ``--scheduled-alone`` says
that the job was scheduled with nothing else of its workflow beside it.

The workflow's ``fps`` rule runs it with ``threads: workflow.cores``: Snakemake keeps the sum of the
threads of the running jobs at or below ``--cores``, so while it runs no other job of the workflow does,
and the FPS does not depend on which jobs happened to run beside it. ``other_busy_cores`` shows what ran
beside it from outside the workflow (other users, another workflow).
"""

from __future__ import annotations

import argparse
from pathlib import Path

from rtsplat.config import add_config_arguments, stage_config_from_args
from rtsplat.devices import resolve_device
from rtsplat.io.atomic import write_json_atomic
from rtsplat.io.outputs import check_output_file, json_with_keys
from rtsplat.render import add_run_arguments, device_name, load_run, time_renders


def measure_fps(run_dir: str | Path, data_dir: str | Path, out: str | Path, *, rounds: int = 3, warmup: int = 2,
                backend: str = "auto", device: str = "auto", scheduled_alone: bool = False) -> dict:
    """Time the test views' renders of ``run_dir`` (see the module docstring); writes and returns ``out``."""
    run = load_run(run_dir, data_dir, backend=backend, device=device)
    info = {**time_renders(run, warmup=warmup, rounds=rounds, scheduled_alone=scheduled_alone),
            "views": len(run.records), "rounds": rounds, "device": device_name(run.device), "backend": backend,
            "width": run.records[0].width, "height": run.records[0].height, "surfels": len(run.model.surfels),
            "run": str(run_dir)}
    write_json_atomic(Path(out), info)
    return info


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_run_arguments(parser, __doc__, "the FPS JSON file (written atomically)")
    parser.add_argument("--rounds", type=int, help="override render.fps_rounds (renders of every test view)")
    parser.add_argument("--warmup", type=int, help="override render.warmup (untimed renders first)")
    parser.add_argument("--backend", default="auto",
                        help="rasterizer backend (auto: triton on a GPU, else cpu; cpu, triton, reference)")
    parser.add_argument("--device", help="override render.device: auto, cpu, cuda, cuda:N")
    parser.add_argument("--scheduled-alone", action="store_true",
                        help="record that the caller runs this job with nothing else beside it (the workflow's "
                        "fps rule does)")
    add_config_arguments(parser)


def run(args: argparse.Namespace) -> int:
    cfg = stage_config_from_args(args, "render", {"warmup": args.warmup, "device": args.device,
                                                  "fps_rounds": args.rounds})
    resolve_device(cfg.device, key="--device" if args.device is not None else "render.device")
    check_output_file(args.out, "fps", lambda path: json_with_keys(path, ("fps", "timing")),
                      inputs=[args.run, args.data])
    info = measure_fps(args.run, args.data, args.out, rounds=cfg.fps_rounds, warmup=cfg.warmup,
                       backend=args.backend, device=cfg.device, scheduled_alone=args.scheduled_alone)
    timing = info["timing"]
    print(f"{info['fps']:.2f} FPS on {info['device']} ({info['frames']} frames, {timing['threads']} threads, "
          f"{timing['cpu_seconds_per_frame']:.3f} CPU s per frame, other processes kept "
          f"{timing['other_busy_cores']} cores busy)")
    return 0
