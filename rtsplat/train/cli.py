"""``rtsplat train``: train an RT-Splatting model on a prepared scene.

The trainer's config comes, like every stage's, from ``--config-json`` (the trainer tree as JSON:
what the workflow passes, built by :func:`rtsplat.config.train_json`) or ``--config``: a pipeline
``config.yaml`` (with ``--scene`` and ``--method``: that method's trainer tree on that scene, as the
workflow builds it) or a YAML file with a ``train:`` tree (or the trainer keys at top level).
Bad input raises :class:`rtsplat.errors.PipelineError`.

``--seconds-of RUN`` sets the time budget (``schedule.seconds``) to the training seconds of another finished
run (its ``summary.json``'s ``train_seconds``: the wall seconds of its training steps, what the budget counts):
the run to compare with that one at equal time (a method's ``time_of`` in the pipeline config).

``--checkpoint-dir`` keeps the resumable checkpoint outside ``--out``: a workflow manager that deletes
the output folder of a failed or killed job (Snakemake does) leaves it in place, and the next run
resumes from it. The folder records what it was written for (the ``--data`` files' sizes and
modification times, the trainer config); a checkpoint written for anything else is discarded, with a
message, and training starts at iteration 0. A finished run removes the folder (``--out`` has the
final ``model.pt``).

SIGTERM or SIGUSR1 (a batch system's time limit or preemption warning) stops training at the end of the
current iteration: the checkpoint is written, the process exits with 128 + the signal number (a failure
for a workflow manager, which keeps the checkpoint folder), and the same command resumes from it.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import json
import shutil
import signal
import sys
from collections.abc import Callable, Iterator
from pathlib import Path

from rtsplat.config import PipelineConfig, add_config_arguments, load_config, method_roles, trainer_options
from rtsplat.devices import resolve_device
from rtsplat.errors import ConfigError, PipelineError
from rtsplat.io.atomic import write_errors, write_json_atomic
from rtsplat.io.manifest import scene_manifest
from rtsplat.io.outputs import check_output_dir, mark_output
from rtsplat.train_config import TrainConfig

PIPELINE_KEYS = frozenset(f.name for f in dataclasses.fields(PipelineConfig))
# SIGTERM (a time limit, scancel, Snakemake's own shutdown) and SIGUSR1 (a batch system's warning before
# a time limit, e.g. sbatch --signal=USR1@120) stop training at the next iteration boundary with a checkpoint
STOP_SIGNALS = (signal.SIGTERM, signal.SIGUSR1)
STOPPED_EXIT_BASE = 128  # a stopped run exits with 128 + the signal number, as if the signal had ended it


@contextlib.contextmanager
def stop_on_signals(trainer) -> Iterator[None]:
    """While in the block, :data:`STOP_SIGNALS` set ``trainer.stop_signal`` instead of ending the process
    (the trainer then checkpoints and raises TrainingStopped); the previous handlers come back after it."""

    def request_stop(signal_number: int, frame) -> None:
        trainer.stop_signal = signal_number

    previous = {sig: signal.signal(sig, request_stop) for sig in STOP_SIGNALS}
    try:
        yield
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--data", type=Path, required=True, help="prepared scene directory (rtsplat prepare)")
    parser.add_argument("--out", type=Path, required=True, help="run directory (created; resumable)")
    add_config_arguments(parser)
    parser.add_argument("--method", help="with a pipeline config.yaml: the method whose trainer config is used "
                        "(default: rtsplat, else the first method)")
    parser.add_argument("--iterations", type=int, help="override schedule.iterations")
    parser.add_argument("--backend", help="rasterizer backend (auto, reference, ...)")
    parser.add_argument("--device", help="override device: auto (the GPU when torch sees one), cpu, cuda, cuda:N")
    parser.add_argument("--seed", type=int, help="random seed")
    parser.add_argument("--seconds-of", type=Path, metavar="RUN",
                        help="a time budget: train for as many seconds of training steps as the finished run RUN "
                        "(a run directory with summary.json) took, e.g. the baseline's run on the same scene, for a "
                        "comparison at equal time; replaces schedule.seconds")
    parser.add_argument("--checkpoint-dir", type=Path,
                        help="folder for the resumable checkpoint instead of <out>/checkpoints, e.g. one a workflow "
                        "manager does not delete when the job fails; resumed from when it was written for the "
                        "same --data and config, removed when the run finishes")
    parser.add_argument("--no-resume", action="store_true", help="ignore an existing checkpoint")
    parser.add_argument("--resume-with-new-config", action="store_true",
                        help="resume from the checkpoint even though this config differs from the one it was "
                        "written with (without it that is an error naming the keys; schedule.iterations, the "
                        "log/eval/checkpoint cadence, device and backend may always change)")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")


def trainer_config_from_args(args: argparse.Namespace) -> TrainConfig:
    """The trainer config of ``--config-json`` / ``--config`` (defaults when neither is given)."""
    pipeline_only = [flag for flag, value in (("--scene", args.scene), ("--method", args.method)) if value]
    if args.config_json is not None:
        if pipeline_only:
            raise ConfigError(f"{', '.join(pipeline_only)} apply to a pipeline config.yaml, not to --config-json",
                              fix="drop them, or pass --config config.yaml")
        try:
            data = json.loads(args.config_json)
        except json.JSONDecodeError as exc:
            raise ConfigError(f"--config-json is not valid JSON ({exc})", fix="pass a JSON object") from exc
        return TrainConfig.from_dict(data, source="--config-json")
    if args.config is None:
        if pipeline_only:
            raise ConfigError(f"{', '.join(pipeline_only)} need --config config.yaml", fix="pass --config")
        return TrainConfig()
    import yaml

    path = Path(args.config)
    try:
        data = yaml.safe_load(path.read_text()) or {}
    except (OSError, yaml.YAMLError) as exc:
        raise ConfigError(f"cannot read config ({exc})", path=path, fix="pass a readable YAML file") from exc
    if isinstance(data, dict) and PIPELINE_KEYS & set(data):
        cfg = load_config(path)
        method = args.method or ("rtsplat" if "rtsplat" in cfg.methods else next(iter(cfg.methods)))
        time_of = method_roles(cfg)[method].time_of
        if time_of is not None and args.seconds_of is None:
            raise ConfigError(f"method {method} trains for as long as the run of {time_of} took", path=path,
                              fix=f"pass --seconds-of <the run directory of {time_of} on this scene>")
        return TrainConfig.from_dict(trainer_options(cfg, args.scene or "__defaults__", method), source=str(path))
    if pipeline_only:
        raise ConfigError(f"{', '.join(pipeline_only)} apply to a pipeline config.yaml, not to a train: tree",
                          path=path, fix="drop them")
    if isinstance(data, dict) and "train" in data:
        data = data["train"] or {}
    return TrainConfig.from_dict(data, source=str(path))


def run(args: argparse.Namespace) -> int:
    from rtsplat.scene import PreparedScene
    from rtsplat.train.run import TrainingStopped
    from rtsplat.train.trainer import Trainer

    cfg = trainer_config_from_args(args)
    if args.iterations is not None:
        cfg.schedule.iterations = args.iterations
    if args.backend is not None:
        cfg.backend = args.backend
    if args.device is not None:
        cfg.device = args.device
    if args.seed is not None:
        cfg.seed = args.seed
    if args.seconds_of is not None:
        cfg.schedule.seconds = run_training_seconds(args.seconds_of)
    cfg.validate(source="rtsplat train")
    resolve_device(cfg.device, key="--device" if args.device is not None else "train.device")
    check_output_dir(args.out, "train", inputs=[args.data])
    scene = PreparedScene.load(args.data)

    def log(msg: str) -> None:
        print(msg, file=sys.stderr)

    # the run folder is written in place (it is what a killed run resumes from); a failure to write it or
    # the checkpoint folder names the path (rtsplat.io.atomic.write_errors)
    with write_errors(args.out, args.checkpoint_dir):
        if args.checkpoint_dir is not None:
            claim_checkpoint_dir(args.checkpoint_dir, args.out, args.data, cfg, log)
        args.out.mkdir(parents=True, exist_ok=True)
        mark_output(args.out, "train")
        trainer = Trainer(scene, cfg, args.out, progress=not args.quiet, log=log, checkpoint_dir=args.checkpoint_dir)
        try:
            with stop_on_signals(trainer):
                trainer.train(resume=not args.no_resume, new_config=args.resume_with_new_config)
        except TrainingStopped as stopped:
            log(f"stopped by {signal.Signals(stopped.signal_number).name} at iteration {stopped.iteration} of "
                f"{cfg.schedule.iterations}; checkpoint {stopped.checkpoint}: the same command resumes from it")
            return STOPPED_EXIT_BASE + stopped.signal_number
        if args.checkpoint_dir is not None:
            shutil.rmtree(args.checkpoint_dir)
    return 0


def run_training_seconds(run_dir: Path) -> float:
    """The wall seconds of the training steps of the finished run in ``run_dir`` (its summary's
    ``train_seconds``)."""
    path = run_dir / "summary.json"
    try:
        seconds = json.loads(path.read_text()).get("train_seconds")
    except (OSError, ValueError, AttributeError) as exc:
        raise PipelineError(f"--seconds-of: cannot read the run's summary ({exc})", path=path,
                            fix="pass the directory of a finished run (rtsplat train writes summary.json when it "
                            "finishes)") from exc
    if isinstance(seconds, bool) or not isinstance(seconds, (int, float)) or not seconds > 0:
        raise PipelineError(f"--seconds-of: the summary's train_seconds is {seconds!r}, not a positive number",
                            path=path, fix="pass the directory of a finished run of rtsplat train")
    return float(seconds)


CHECKPOINT_RECORD = "written_for.json"


def claim_checkpoint_dir(folder: Path, out: Path, data: Path, cfg: TrainConfig, log: Callable[[str], None]) -> None:
    """Make ``folder`` the checkpoint folder of a training into ``out`` on ``data`` with ``cfg``: a
    checkpoint there that was written for other ``data`` files (sizes, modification times) or another
    config is removed (and said so); ``folder`` is marked as train output and records what it is for."""
    folder_r, out_r = folder.resolve(), out.resolve()
    if folder_r == out_r or folder_r in out_r.parents or out_r in folder_r.parents:
        raise PipelineError("--checkpoint-dir is, contains or lies inside --out; it is removed when the run "
                            "finishes and is meant to outlive a deleted --out", path=folder,
                            fix="pass a folder beside --out, e.g. <results>/<scene>/checkpoints/<method>")
    check_output_dir(folder, "train", inputs=[data], flag="--checkpoint-dir")
    written_for = json.loads(json.dumps({"data": scene_manifest(data), "config": cfg.to_dict()}, default=str))
    record = folder / CHECKPOINT_RECORD
    if (folder / "last.pt").exists():
        try:
            same = json.loads(record.read_text()) == written_for
        except (OSError, ValueError):
            same = False
        if not same:
            log(f"{folder}: its checkpoint was written for other --data files or another config; "
                "removed, training starts at iteration 0")
            shutil.rmtree(folder)
    folder.mkdir(parents=True, exist_ok=True)
    mark_output(folder, "train")
    write_json_atomic(record, written_for)
