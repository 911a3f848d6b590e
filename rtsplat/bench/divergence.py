"""What the divergence watch costs per training iteration: ``python -m rtsplat.bench.divergence``.

Trains a toy glass scene (``--width`` x ``--height``, the demo's environment map by default) past
the full-model stage, then times, on the same trained state and interleaved over ``--repeats``
rounds: ``--iterations`` training steps as the trainer runs them, the same steps with the watch
replaced by no-ops, and the watch's own work per step in isolation (the gradients' group sums, the
parameters' group sums with the record update, and reading the record back). Prints medians in
milliseconds; ratios are comparable on a loaded machine, absolute times are not.
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from pathlib import Path

import torch

from rtsplat.bench.iteration import demo_environment_map
from rtsplat.bench.toy_scene import write_scene
from rtsplat.train.trainer import Trainer
from rtsplat.train_config import TrainConfig


def _steps(trainer: Trainer, n: int) -> float:
    start = time.perf_counter()
    for _ in range(n):
        trainer.step()
    trainer.watch.check()
    return (time.perf_counter() - start) / n * 1e3


def _watch_alone(trainer: Trainer, n: int) -> float:
    loss = torch.zeros((), device=trainer.device)
    for group in trainer.optimizer.param_groups:
        for p in group["params"]:
            p.grad = torch.zeros_like(p)  # a gradient for every parameter, as after a backward
    start = time.perf_counter()
    for _ in range(n):
        gradients = trainer.watch.gradients(trainer.optimizer)
        trainer.watch.record(trainer.iteration, loss, gradients, trainer.optimizer)
        trainer.watch.check()
    elapsed = (time.perf_counter() - start) / n * 1e3
    trainer.optimizer.zero_grad(set_to_none=True)
    return elapsed


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--width", type=int, default=100)
    parser.add_argument("--height", type=int, default=75)
    parser.add_argument("--env", help="environment map height,width,levels (default: demo/config.yaml's)")
    parser.add_argument("--warmup", type=int, default=60)
    parser.add_argument("--iterations", type=int, default=10)
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args(argv)
    if args.env is None:
        env_map = demo_environment_map()
    else:
        height, width, levels = (int(v) for v in args.env.split(","))
        env_map = {"env_height": height, "env_width": width, "env_levels": levels}
    with tempfile.TemporaryDirectory() as tmp:
        scene = write_scene(Path(tmp) / "scene", views=8, width=args.width, height=args.height)
        cfg = TrainConfig.from_dict({
            "device": "cpu",
            "schedule": {"iterations": 10**6, "volume_until": 10, "specular_from": 20, "densify_from": 30,
                         "densify_until": args.warmup, "densify_every": 15, "reset_every": 0, "log_every": 10**6,
                         "checkpoint_every": 0},
            "model": env_map,
        })
        trainer = Trainer(scene, cfg, Path(tmp) / "run", progress=False, log=lambda m: None)
        for _ in range(args.warmup):
            trainer.step()
        values = sum(p.numel() for g in trainer.optimizer.param_groups for p in g["params"])
        print(f"toy scene {args.width}x{args.height}, {len(trainer.model.surfels)} surfels, "
              f"{len(trainer.optimizer.param_groups)} parameter groups, {values} parameter values, "
              f"{torch.get_num_threads()} threads")
        watch_gradients, watch_record = trainer.watch.gradients, trainer.watch.record
        times: dict[str, list[float]] = {"step, watch on": [], "step, watch off": [], "watch alone": []}
        for _ in range(args.repeats):
            times["step, watch on"].append(_steps(trainer, args.iterations))
            trainer.watch.gradients = lambda optimizer: torch.zeros(0)
            trainer.watch.record = lambda *a: None
            times["step, watch off"].append(_steps(trainer, args.iterations))
            trainer.watch.gradients, trainer.watch.record = watch_gradients, watch_record
            times["watch alone"].append(_watch_alone(trainer, args.iterations))
        for name, values_ms in times.items():
            print(f"{name:>16}: {statistics.median(values_ms):8.3f} ms per iteration (median of {args.repeats})")
        on, off = statistics.median(times["step, watch on"]), statistics.median(times["step, watch off"])
        print(f"watch alone / step: {statistics.median(times['watch alone']) / off:.2%};  "
              f"step on / off: {on / off:.3f}")
    return 0


if __name__ == "__main__":
    from rtsplat.errors import run_command

    raise SystemExit(run_command("python -m rtsplat.bench.divergence", main))
