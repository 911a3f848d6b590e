"""``rtsplat train``: train an RT-Splatting model on a prepared scene."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import yaml

from rtsplat.errors import PipelineError
from rtsplat.train.config import ConfigError, TrainConfig


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--data", type=Path, required=True, help="prepared scene directory (rtsplat prepare)")
    parser.add_argument("--out", type=Path, required=True, help="run directory (created; resumable)")
    parser.add_argument("--config", type=Path, help="YAML file with the training config (a 'train:' "
                        "section, or the train keys at top level)")
    parser.add_argument("--config-json", help="the training config as a JSON object (what the workflow passes; "
                        "same keys as --config)")
    parser.add_argument("--iterations", type=int, help="override schedule.iterations")
    parser.add_argument("--backend", help="rasterizer backend (auto, reference, ...)")
    parser.add_argument("--seed", type=int, help="random seed")
    parser.add_argument("--no-resume", action="store_true", help="ignore an existing checkpoint in --out")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")


def load_config(path: Path | None) -> TrainConfig:
    data = {}
    if path is not None:
        try:
            data = yaml.safe_load(path.read_text()) or {}
        except (OSError, yaml.YAMLError) as exc:
            raise ConfigError(f"{path}: cannot read config ({exc})") from exc
        if isinstance(data, dict) and "train" in data:
            data = data["train"] or {}
    return TrainConfig.from_dict(data)


def run(args: argparse.Namespace) -> int:
    from rtsplat.scene import PreparedScene
    from rtsplat.train.trainer import CheckpointError, Trainer

    try:
        if args.config_json is not None:
            try:
                data = json.loads(args.config_json)
            except json.JSONDecodeError as exc:
                raise ConfigError(f"--config-json is not valid JSON ({exc})") from exc
            cfg = TrainConfig.from_dict(data if isinstance(data, dict) else {"": data})
        else:
            cfg = load_config(args.config)
        if args.iterations is not None:
            cfg.schedule.iterations = args.iterations
        if args.backend is not None:
            cfg.backend = args.backend
        if args.seed is not None:
            cfg.seed = args.seed
        cfg.validate()
        scene = PreparedScene.load(args.data)
        trainer = Trainer(scene, cfg, args.out, progress=not args.quiet,
                          log=lambda msg: print(msg, file=sys.stderr))
        trainer.train(resume=not args.no_resume)
    except (ConfigError, PipelineError, CheckpointError) as exc:
        print(f"rtsplat train: error: {exc}", file=sys.stderr)
        return 2
    return 0
