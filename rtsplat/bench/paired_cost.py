"""Two or more methods' training cost measured side by side: ``python -m rtsplat.bench.paired_cost``.

    python -m rtsplat.bench.paired_cost --config benchmarks/family.yaml \
        --prepared family/results/car-0/prepared family/results/shop_window-0/prepared --out /tmp/paired

The speed of the shared development machines drifts by 1.2-1.5x within minutes (docs/benchmarks.md, "Known
limitations"), so the training seconds of runs trained in different minutes do not compare. Here each scene's
runs of the two ``--methods`` (default ``rtsplat,2dgs``, their trainer configs from the pipeline ``--config``, as
the workflow builds them) train at the same time, each ``rtsplat train`` in its own process with one thread,
so both see the same machine. Per scene it prints each run's training CPU seconds (``summary.json``) and the
ratio first / second, the same ratio per part of the schedule (the stages of the training log; the full stage
split where its specular shading runs on 2x2 blocks, ``schedule.specular_coarse_share``) and the final test PSNR
(entire / transparent). A run that ends first is started again as a filler until the last one ends, so that the
measured runs share the machine with the same load from start to end. Then the median ratio over the scenes.
With more than two methods, every other method's ratio to the second is printed too. With ``--equal-time``
every method but the second is then trained again, alone, with every iteration count of its config times 1 / its
ratio (a method's ``budget: F``), and its test PSNR is printed against the second's: that method at the second's
CPU seconds, through the ratio measured side by side rather than a clock that drifts. It runs the
specular gradient through every pixel, as every fixed-count run does; a time-budgeted run (``--seconds-of``) would
run it through a quarter of them (``schedule.specular_gradient_share``) and take more, cheaper, iterations.
``<out>/paired_cost.json`` keeps the numbers (rewritten after every scene; ``complete`` once all are done); the runs
stay in ``<out>/<scene>/<method>``. ``--out`` is a new folder or one this bench wrote, never a folder of the user's.

The parts' CPU seconds come from the log's lines (one every ``schedule.log_every`` iterations): the seconds
between two lines count for the part of the later line's iteration, so a part's boundary is placed to within
``log_every`` iterations.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import subprocess
import sys
import time
from pathlib import Path

from rtsplat.errors import PipelineError, run_command
from rtsplat.io.atomic import write_json_atomic
from rtsplat.io.train_log import LOG_NAME, read_log

TRAIN_COMMAND = ("-c", "import sys; from rtsplat.cli import main; sys.exit(main())", "train")
RESULT_NAME = "paired_cost.json"
ONE_THREAD = {"OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1", "NUMBA_NUM_THREADS": "1"}


def schedule_part(record: dict, schedule) -> str:
    """The part of the schedule a log line belongs to: its stage, and for the full stage whether its training
    renders shade the specular network on blocks (:meth:`rtsplat.train_config.Schedule.specular_downsample_at`)."""
    stage = record.get("stage", "")
    if stage == "full":
        factor = schedule.specular_downsample_at(record["iteration"])
        return f"full, {factor}x{factor} shading" if factor > 1 else "full"
    return stage


def part_seconds(records: list[dict], schedule) -> dict[str, float]:
    """CPU seconds of training per part of the schedule (:func:`schedule_part`), in the order the parts come:
    the seconds between consecutive log lines that carry ``cpu_seconds`` count for the later line's part."""
    parts: dict[str, float] = {}
    previous = None
    for record in records:
        if "cpu_seconds" not in record:
            continue
        if previous is not None and "stage" in record:
            part = schedule_part(record, schedule)
            parts[part] = parts.get(part, 0.0) + record["cpu_seconds"] - previous
        previous = record["cpu_seconds"]
    return parts


def run_summary(run_dir: Path) -> dict:
    """A finished run's training CPU seconds, test PSNR and CPU seconds per part of its schedule."""
    from rtsplat.train_config import TrainConfig

    summary = json.loads((run_dir / "summary.json").read_text())
    config = TrainConfig.from_dict(json.loads((run_dir / "config.json").read_text()))
    records = [record for record, _ in read_log(run_dir / LOG_NAME, lambda _: None)]
    return {"cpu_seconds": summary["train_cpu_seconds"], "iterations": summary["iterations"],
            "test_psnr": summary.get("test_psnr"), "test_psnr_transparent": summary.get("test_psnr_transparent"),
            "parts": part_seconds(records, config.schedule)}


def scene_name(prepared: Path) -> str:
    """The scene a prepared folder belongs to: ``<results>/<scene>/prepared`` -> ``<scene>``, else its own name."""
    return prepared.parent.name if prepared.name == "prepared" else prepared.name


def start_training(prepared: Path, run_dir: Path, log_path: Path, seed: int,
                   config_args: list[str]) -> subprocess.Popen:
    """``rtsplat train`` of ``prepared`` into ``run_dir`` (from scratch, one thread, output to ``log_path``) with
    the trainer config of ``config_args`` (``--config ... --method ...`` or ``--config-json ...``)."""
    command = [sys.executable, *TRAIN_COMMAND, "--data", str(prepared), "--out", str(run_dir), *config_args,
               "--seed", str(seed), "--no-resume", "--quiet"]
    with log_path.open("w") as log:
        return subprocess.Popen(command, stdout=log, stderr=subprocess.STDOUT, env={**os.environ, **ONE_THREAD})


def training_failed(what: str, log_path: Path) -> PipelineError:
    return PipelineError(f"training {what} failed", path=log_path,
                         fix="read the log's last lines; the trainer names the bad input")


def train_side_by_side(prepared: Path, scene: str, methods: list[str], config: Path, out: Path,
                       seed: int) -> dict[str, float]:
    """Start ``rtsplat train`` of every method on ``prepared`` at once (one thread each) and wait for all; returns
    each method's wall seconds. A run that ends while others still train is started again as a filler (in
    ``<out>/<scene>/.filler/``, deleted after; again whenever a filler ends), so that the machine carries the same
    load until the last run ends. A run that fails raises a PipelineError naming its log."""
    scene_dir = out / scene
    scene_dir.mkdir(parents=True, exist_ok=True)

    def start(method: str, run_dir: Path, log_path: Path) -> subprocess.Popen:
        return start_training(prepared, run_dir, log_path, seed,
                              ["--config", str(config), "--scene", scene, "--method", method])

    logs = {method: scene_dir / f"{method}.log" for method in methods}
    procs = {method: start(method, scene_dir / method, logs[method]) for method in methods}
    fillers: dict[str, subprocess.Popen | None] = {}
    walls: dict[str, float] = {}
    begin = time.perf_counter()
    try:
        while len(walls) < len(methods):
            for method, proc in procs.items():
                if method in walls or proc.poll() is None:
                    continue
                walls[method] = time.perf_counter() - begin
                if proc.returncode != 0:
                    raise training_failed(f"{method} on {scene}", logs[method])
                fillers[method] = None
            for method, filler in fillers.items():  # (re)start the fillers while a measured run trains
                if len(walls) < len(methods) and (filler is None or filler.poll() is not None):
                    run_dir = scene_dir / ".filler" / f"{method}-{time.monotonic_ns()}"
                    run_dir.parent.mkdir(exist_ok=True)
                    fillers[method] = start(method, run_dir, run_dir.parent / f"{run_dir.name}.log")
            time.sleep(0.2)
    finally:
        for proc in [*fillers.values(), *procs.values()]:
            if proc is not None and proc.poll() is None:
                proc.terminate()
                proc.wait()
        shutil.rmtree(scene_dir / ".filler", ignore_errors=True)
    return walls


def measure_scene(prepared: Path, methods: list[str], config: Path, out: Path, seed: int,
                  equal_time: bool = False) -> dict:
    """The paired runs of one scene (:func:`train_side_by_side`), their summaries and ratios first / second (and,
    in ``ratios``, every method but the second against the second); with ``equal_time`` also each of those methods
    at the second's CPU seconds (:func:`equal_time_run`, budget 1 / its ratio; ``equal_time`` holds the first's,
    ``equal_time_runs`` all of them)."""
    scene = scene_name(prepared)
    walls = train_side_by_side(prepared, scene, methods, config, out, seed)
    runs = {method: run_summary(out / scene / method) for method in methods}
    first, second = (runs[m] for m in methods[:2])
    ratios = {m: runs[m]["cpu_seconds"] / second["cpu_seconds"] for m in methods if m != methods[1]}
    ratio_parts = {part: first["parts"][part] / second["parts"][part] for part in first["parts"]
                   if second["parts"].get(part, 0.0) > 0}
    result = {"scene": scene, "runs": runs, "wall_seconds": walls, "ratio": ratios[methods[0]], "ratios": ratios,
              "ratio_parts": ratio_parts}
    if equal_time:
        result["equal_time_runs"] = {m: equal_time_run(prepared, scene, m, config, out, seed, 1.0 / ratio)
                                     for m, ratio in ratios.items()}
        result["equal_time"] = result["equal_time_runs"][methods[0]]
    return result


def equal_time_run(prepared: Path, scene: str, method: str, config: Path, out: Path, seed: int,
                   factor: float) -> dict:
    """``method`` trained alone with every iteration count of its config times ``factor``
    (:func:`rtsplat.train_config.scale_budget`, a method's ``budget: F``) in ``<out>/<scene>/<method>_equal_time``;
    its :func:`run_summary`. A fixed count, so the result does not depend on the machine's speed while it trains."""
    from rtsplat.config import load_config, trainer_options
    from rtsplat.train_config import TrainConfig, scale_budget

    tree = trainer_options(load_config(config), scene, method)
    tree = scale_budget(TrainConfig.from_dict(tree), factor).validate().to_dict()
    run_dir = out / scene / f"{method}_equal_time"
    log_path = out / scene / f"{method}_equal_time.log"
    if start_training(prepared, run_dir, log_path, seed, ["--config-json", json.dumps(tree)]).wait() != 0:
        raise training_failed(f"{method} at the equal-time budget on {scene}", log_path)
    return {**run_summary(run_dir), "budget": factor}


def format_scene(result: dict, methods: list[str]) -> str:
    runs = result["runs"]

    def psnr(run):
        return f"{run['test_psnr']:.2f} / {run['test_psnr_transparent']:.2f}"

    lines = [f"{result['scene']}: {methods[0]} {runs[methods[0]]['cpu_seconds']:.1f} CPU s, {methods[1]} "
             f"{runs[methods[1]]['cpu_seconds']:.1f}: ratio {result['ratio']:.2f}; "
             f"test PSNR entire / transparent {psnr(runs[methods[0]])} against {psnr(runs[methods[1]])}"]
    for part, ratio in result["ratio_parts"].items():
        lines.append(f"    {part:22s} {runs[methods[0]]['parts'][part]:7.1f} s against "
                     f"{runs[methods[1]]['parts'][part]:7.1f} s: {ratio:.2f}")
    for method in methods[2:]:
        lines.append(f"    {method} {runs[method]['cpu_seconds']:.1f} CPU s: ratio to {methods[1]} "
                     f"{result['ratios'][method]:.2f}; test PSNR {psnr(runs[method])}")
    for method, equal in result.get("equal_time_runs", {}).items():
        gap = [equal[key] - runs[methods[1]][key] for key in ("test_psnr", "test_psnr_transparent")]
        lines.append(f"    at {methods[1]}'s CPU seconds ({method} with budget {equal['budget']:.3f}: "
                     f"{equal['iterations']} iterations): {psnr(equal)}, minus {methods[1]} {gap[0]:+.2f} / "
                     f"{gap[1]:+.2f}")
    return "\n".join(lines)


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(prog="python -m rtsplat.bench.paired_cost", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--config", type=Path, default=Path("config.yaml"),
                        help="pipeline config.yaml whose methods (and scene settings) the runs train with")
    parser.add_argument("--prepared", type=Path, nargs="+", required=True,
                        help="prepared scenes (rtsplat prepare), e.g. family/results/car-0/prepared")
    parser.add_argument("--methods", default="rtsplat,2dgs",
                        help="two or more methods of the config, trained at the same time (default rtsplat,2dgs); "
                        "ratios are first / second")
    parser.add_argument("--out", type=Path, required=True, help="folder for the runs and paired_cost.json")
    parser.add_argument("--seed", type=int, default=0, help="every run's seed (default 0)")
    parser.add_argument("--equal-time", action="store_true",
                        help="then train every method but the second again, alone, with every iteration count "
                        "times the scene's ratio second / that method (budget 1 / ratio): each at the second's CPU "
                        "seconds as measured side by side, a fixed count that the machine's speed cannot change")
    args = parser.parse_args(argv)
    args.methods = [m.strip() for m in args.methods.split(",") if m.strip()]
    return args


def check_inputs(args: argparse.Namespace) -> None:
    """Every method in the config and every prepared folder a prepared scene, before anything trains."""
    from rtsplat.config import load_config
    from rtsplat.errors import ConfigError

    if len(args.methods) < 2 or len(set(args.methods)) != len(args.methods):
        raise ConfigError(f"--methods names {args.methods}: give two or more different methods",
                          fix="e.g. --methods rtsplat,2dgs")
    cfg = load_config(args.config)
    unknown = [m for m in args.methods if m not in cfg.methods]
    if unknown:
        raise ConfigError(f"methods not in the config: {', '.join(unknown)}", path=args.config,
                          fix=f"use methods listed under 'methods' ({', '.join(cfg.methods)})")
    for prepared in args.prepared:
        if not (prepared / "scene.json").is_file():
            raise PipelineError("not a prepared scene (no scene.json)", path=prepared,
                                fix="run `rtsplat prepare` (or the workflow's prepare rule) for it first")
    check_out_folder(args.out, [args.config, *args.prepared])


def _is_own_result(path: Path) -> bool:
    try:
        return "median_ratio" in json.loads(path.read_text())
    except (OSError, ValueError, TypeError):
        return False


def check_out_folder(out: Path, inputs: list[Path]) -> None:
    """``--out`` may be a new or empty folder, or one this bench wrote (its ``paired_cost.json`` says so), and no
    input, nor inside one, a dataset or a stage's output (:func:`rtsplat.io.outputs.check_output_file`): never a
    folder of the user's. The runs inside are ``rtsplat train``'s, which checks its own ``--out``."""
    from rtsplat.io.outputs import check_output_file

    result = out / RESULT_NAME
    if out.is_dir() and any(out.iterdir()) and not _is_own_result(result):
        raise PipelineError(f"the output folder exists, is not empty and holds no {RESULT_NAME} of this bench; it "
                            "is left as it is", path=out, fix="pass a new folder for --out, or delete that folder "
                            "yourself if you no longer need it")
    check_output_file(result, "bench.paired_cost", _is_own_result, inputs=inputs, flag="--out",
                      command="python -m rtsplat.bench.paired_cost")


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)

    def work() -> int:
        check_inputs(args)
        results: list[dict] = []

        def write(complete: bool) -> None:  # after every scene, so an interrupted run keeps the scenes it did
            median = statistics.median(r["ratio"] for r in results) if results else None
            write_json_atomic(args.out / RESULT_NAME, {"methods": args.methods, "seed": args.seed, "complete":
                                                       complete, "median_ratio": median, "scenes": results})

        args.out.mkdir(parents=True, exist_ok=True)
        write(False)
        for prepared in args.prepared:
            results.append(measure_scene(prepared, args.methods, args.config, args.out, args.seed, args.equal_time))
            print(format_scene(results[-1], args.methods), flush=True)
            write(False)
        write(True)
        for method in results[0]["ratios"]:  # --prepared names at least one scene
            print(f"median ratio {method} / {args.methods[1]} of the training CPU seconds over "
                  f"{len(results)} scene(s): {statistics.median(r['ratios'][method] for r in results):.2f}")
        return 0

    return run_command("paired_cost", work)


if __name__ == "__main__":
    sys.exit(main())
