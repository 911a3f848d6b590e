"""The iteration benchmark's methods are valid training configs that keep the demo's settings."""

from __future__ import annotations

import pytest

from rtsplat.bench.iteration import METHODS, demo_options, method_options
from rtsplat.train_config import TrainConfig


@pytest.mark.parametrize("method", sorted(METHODS))
def test_every_method_is_a_valid_config_with_the_demo_map(method):
    cfg = TrainConfig.from_dict(method_options(method))
    # a method's options are merged key by key: one that sets a model, schedule or rate option keeps the demo's
    # map, schedule and rates
    demo = demo_options()
    assert (cfg.model.env_height, cfg.model.env_width, cfg.model.env_levels) == (64, 128, 6)
    assert cfg.schedule.specular_from == demo["schedule"]["specular_from"] == 250
    assert (cfg.lr.sh_dc, cfg.lr.sh_rest) == (demo["lr"]["sh_dc"], demo["lr"]["sh_rest"])
    assert cfg.densify.prune_occupancy == demo["densify"]["prune_occupancy"]
    assert (cfg.schedule.eval_every, cfg.schedule.checkpoint_every) == (0, 0)


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


def test_the_demo_options_are_read_from_demo_config_yaml(tmp_path, monkeypatch):
    """The benchmark times the demo's training as demo/config.yaml sets it (a change there reaches every method),
    less the evaluations, checkpoints and logging it switches off; ``--options`` merge key by key."""
    import yaml

    import rtsplat.bench.iteration as bench

    demo = yaml.safe_load(bench.DEMO_CONFIG.read_text())
    demo["defaults"]["train"]["options"]["lr"]["sh_dc"] = 0.003
    demo["defaults"]["train"]["iterations"] = 500
    changed = tmp_path / "config.yaml"
    changed.write_text(yaml.safe_dump(demo))
    monkeypatch.setattr(bench, "DEMO_CONFIG", changed)
    for method in ("rtsplat", "2dgs", "rtsplat_near_planes"):
        cfg = TrainConfig.from_dict(method_options(method, {"model": {"mlp_width": 64}}))
        assert (cfg.lr.sh_dc, cfg.schedule.iterations, cfg.model.mlp_width, cfg.model.env_height) == (
            0.003, 500, 64, demo["defaults"]["train"]["options"]["model"]["env_height"])
        assert cfg.schedule.eval_every == 0
    # the toy models of the video, viewer and divergence benchmarks take the same map
    options = demo["defaults"]["train"]["options"]["model"]
    options.update(env_height=32, env_width=64, env_levels=5)
    changed.write_text(yaml.safe_dump(demo))
    assert bench.demo_environment_map() == {"env_height": 32, "env_width": 64, "env_levels": 5}


def test_a_missing_demo_config_is_a_clear_error(tmp_path, monkeypatch):
    import rtsplat.bench.iteration as bench
    from rtsplat.errors import PipelineError

    monkeypatch.setattr(bench, "DEMO_CONFIG", tmp_path / "config.yaml")
    with pytest.raises(PipelineError, match="demo/config.yaml"):
        method_options("rtsplat")
