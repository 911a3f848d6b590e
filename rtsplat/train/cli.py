"""``rtsplat train``: train an RT-Splatting model on a prepared scene.

The trainer's config comes, like every stage's, from ``--config-json`` (the trainer tree as JSON:
what the workflow passes, built by :func:`rtsplat.config.train_json`) or ``--config``: a pipeline
``config.yaml`` (with ``--scene`` and ``--method``: that method's trainer tree on that scene, as the
workflow builds it) or a YAML file with a ``train:`` tree (or the trainer keys at top level).
Bad input raises :class:`rtsplat.errors.PipelineError`.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from pathlib import Path

from rtsplat.config import PipelineConfig, add_config_arguments, load_config, trainer_options
from rtsplat.devices import resolve_device
from rtsplat.errors import ConfigError
from rtsplat.io.outputs import check_output_dir, mark_output
from rtsplat.train_config import TrainConfig

PIPELINE_KEYS = frozenset(f.name for f in dataclasses.fields(PipelineConfig))


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
    parser.add_argument("--no-resume", action="store_true", help="ignore an existing checkpoint in --out")
    parser.add_argument("--resume-with-new-config", action="store_true",
                        help="resume from --out's checkpoint even though this config differs from the one it was "
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
        return TrainConfig.from_dict(trainer_options(cfg, args.scene or "__defaults__", method), source=str(path))
    if pipeline_only:
        raise ConfigError(f"{', '.join(pipeline_only)} apply to a pipeline config.yaml, not to a train: tree",
                          path=path, fix="drop them")
    if isinstance(data, dict) and "train" in data:
        data = data["train"] or {}
    return TrainConfig.from_dict(data, source=str(path))


def run(args: argparse.Namespace) -> int:
    from rtsplat.scene import PreparedScene
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
    cfg.validate(source="rtsplat train")
    resolve_device(cfg.device, key="--device" if args.device is not None else "train.device")
    check_output_dir(args.out, "train", inputs=[args.data])
    scene = PreparedScene.load(args.data)
    args.out.mkdir(parents=True, exist_ok=True)
    mark_output(args.out, "train")
    trainer = Trainer(scene, cfg, args.out, progress=not args.quiet, log=lambda msg: print(msg, file=sys.stderr))
    trainer.train(resume=not args.no_resume, new_config=args.resume_with_new_config)
    return 0
