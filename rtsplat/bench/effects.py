"""What scene-adaptive effects save: ``python -m rtsplat.bench.effects``.

Trains the same scene WITHOUT glass (no transparent pixel in its masks) with each combination of
the two optional branches forced on or off, and prints the time per training iteration of the full
stage (stage 3: every loss term, specular network when on), plus what ``effects: auto`` picks:

* transmission on:  two compositing weight sets, optical opacity, ``tau`` and scatter colour;
* specular on:      environment map lookup and the specular MLP on every shaded pixel.

``auto`` turns transmission off on this scene (the masks are empty) and, because its region of
interest is the estimated one that ``prepare`` writes when the config gives none, specular off too
(plain 2DGS radiance); ``--roi-from-config`` marks the region as user-given, so auto keeps specular.
All configurations run in one process on the same scene, interleaved over ``--repeats`` rounds;
the median time per iteration is reported with its ratio to the everything-on configuration.
Ratios are comparable on a loaded machine, absolute times are not.
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from pathlib import Path

import torch

from rtsplat.bench.toy_scene import write_scene
from rtsplat.scene import PreparedScene

CONFIGS = {
    "transmission on, specular on": {"transmission": "on", "specular": "on"},
    "transmission off, specular on": {"transmission": "off", "specular": "on"},
    "transmission on, specular off": {"transmission": "on", "specular": "off"},
    "transmission off, specular off": {"transmission": "off", "specular": "off"},
    "auto": {"transmission": "auto", "specular": "auto"},
}


def _config(effects: dict, iterations: int, backend: str):
    from rtsplat.train_config import TrainConfig

    return TrainConfig.from_dict({
        "effects": effects,
        "backend": backend,
        # every timed iteration is in the full stage; no densification, resets or checkpoints,
        # so each configuration keeps the same surfels and the comparison is of the branches only
        "schedule": {"iterations": iterations, "volume_until": 0, "specular_from": 0, "densify_from": 10**9,
                     "reset_every": 0, "checkpoint_every": 0, "log_every": 10**9},
    })


def time_per_iteration(scene: PreparedScene, effects: dict, *, warmup: int, iterations: int, backend: str,
                       out: Path) -> tuple[float, dict]:
    from rtsplat.train.trainer import Trainer

    trainer = Trainer(scene, _config(effects, warmup + iterations, backend), out, progress=False, log=lambda m: None)
    for _ in range(warmup):
        trainer.step()
    start = time.perf_counter()
    for _ in range(iterations):
        trainer.step()
    seconds = (time.perf_counter() - start) / iterations
    return seconds, {"transmission": trainer.effects.transmission, "specular": trainer.effects.specular,
                     "surfels": len(trainer.model.surfels)}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m rtsplat.bench.effects", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--width", type=int, default=160)
    parser.add_argument("--height", type=int, default=120)
    parser.add_argument("--views", type=int, default=8)
    parser.add_argument("--side", type=int, default=60, help="the wall has side x side surfels (default 3600)")
    parser.add_argument("--iterations", type=int, default=30, help="timed iterations per configuration and round")
    parser.add_argument("--warmup", type=int, default=5)
    parser.add_argument("--repeats", type=int, default=3, help="interleaved rounds; the median is reported")
    parser.add_argument("--backend", default="auto", help="rasterizer backend (default: auto)")
    parser.add_argument("--roi-from-config", action="store_true",
                        help="mark the region of interest as given in the config (auto then keeps specular on)")
    args = parser.parse_args(argv)

    torch.manual_seed(0)
    with tempfile.TemporaryDirectory(prefix="rtsplat_bench_effects_") as tmp:
        tmp = Path(tmp)
        scene = write_scene(tmp / "scene", views=args.views, width=args.width, height=args.height,
                            with_pane=False, n_side=args.side,
                            roi_source="config" if args.roi_from_config else "estimated")
        times: dict[str, list[float]] = {name: [] for name in CONFIGS}
        info: dict[str, dict] = {}
        for round_ in range(args.repeats):
            for name, effects in CONFIGS.items():
                seconds, info[name] = time_per_iteration(
                    scene, effects, warmup=args.warmup, iterations=args.iterations, backend=args.backend,
                    out=tmp / f"run_{round_}_{len(times[name])}_{name.replace(' ', '_').replace(',', '')}")
                times[name].append(seconds)

    surfels = next(iter(info.values()))["surfels"]
    print(f"scene without glass: {args.width}x{args.height}, {surfels} surfels, backend {args.backend}, "
          f"torch threads {torch.get_num_threads()}; median of {args.repeats} rounds x {args.iterations} iterations")
    full = statistics.median(times["transmission on, specular on"])
    print(f"{'configuration':34s} {'runs':>22s} {'ms/it':>8s} {'vs all on':>10s}")
    for name in CONFIGS:
        med = statistics.median(times[name])
        runs = f"trans={'on' if info[name]['transmission'] else 'off'} spec={'on' if info[name]['specular'] else 'off'}"
        print(f"{name:34s} {runs:>22s} {1000 * med:8.1f} {med / full:10.2f}")
    return 0


if __name__ == "__main__":
    from rtsplat.errors import run_command

    raise SystemExit(run_command("python -m rtsplat.bench.effects", main))
