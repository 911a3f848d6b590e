"""The iteration benchmark's methods are valid training configs that keep the demo's settings."""

from __future__ import annotations

import pytest

from rtsplat.bench.iteration import DEMO_OPTIONS, METHODS, method_options
from rtsplat.train_config import TrainConfig


@pytest.mark.parametrize("method", sorted(METHODS))
def test_every_method_is_a_valid_config_with_the_demo_map(method):
    cfg = TrainConfig.from_dict(method_options(method))
    # a method that sets a model option must keep the demo's map (method_options replaces whole sections)
    assert (cfg.model.env_height, cfg.model.env_width, cfg.model.env_levels) == (128, 256, 7)
    assert cfg.schedule.specular_from == DEMO_OPTIONS["schedule"]["specular_from"]


def test_the_width_method_halves_the_network_and_2dgs_turns_both_effects_off():
    assert TrainConfig.from_dict(method_options("rtsplat_mlp128")).model.mlp_width == 128
    assert TrainConfig.from_dict(method_options("rtsplat")).model.mlp_width == 256
    effects = TrainConfig.from_dict(method_options("2dgs")).effects
    assert (effects.transmission, effects.specular) == ("off", "off")


@pytest.mark.parametrize(("method", "expected"), [("rtsplat_no_specular", ("on", "off")),
                                                  ("rtsplat_no_transmission", ("off", "on"))])
def test_the_one_effect_methods_keep_exactly_one_effect_whatever_the_scene(method, expected):
    effects = TrainConfig.from_dict(method_options(method)).effects
    assert (effects.transmission, effects.specular) == expected


def test_the_demo_options_are_demo_config_yaml_s_training_settings():
    """The benchmark times the demo's training: its options build demo/config.yaml's trainer config, less the
    evaluations, checkpoints and logging it switches off."""
    from pathlib import Path

    from rtsplat.config import load_config, trainer_options

    demo = load_config(Path(__file__).resolve().parent.parent / "demo" / "config.yaml")
    ours = TrainConfig.from_dict(method_options("rtsplat")).to_dict()
    theirs = TrainConfig.from_dict(trainer_options(demo, demo.scenes[0], "rtsplat")).to_dict()
    for tree in (ours, theirs):
        for key in ("eval_every", "checkpoint_every", "log_every"):
            tree["schedule"].pop(key)
    assert ours == theirs
