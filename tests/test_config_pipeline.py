"""The pipeline config: dataclasses, generated schema, readable errors, per-scene overrides."""

from __future__ import annotations

import json
import math
import re
from pathlib import Path

import numpy as np
import pytest
import yaml

from rtsplat.config import (
    SCHEMA_PATH,
    ConfigError,
    discover_scenes,
    json_schema,
    json_schema_text,
    load_config,
    load_config_dict,
    scene_config,
    section_from_dict,
    section_json,
    train_json,
    validate_config,
)
from rtsplat.train_config import TrainConfig

ROOT = Path(__file__).resolve().parent.parent
DEMO = yaml.safe_load((ROOT / "demo" / "config.yaml").read_text())
DEMO_ITERATIONS = DEMO["defaults"]["train"]["iterations"]
DEMO_EVAL_EVERY = DEMO["defaults"]["train"]["options"]["schedule"]["eval_every"]


def test_schema_file_is_generated_from_the_dataclasses():
    assert SCHEMA_PATH.read_text() == json_schema_text(), (
        "workflow/schemas/config.schema.json is stale: run `python -m rtsplat.config --write-schema`"
    )


def test_repository_config_is_valid_and_matches_defaults():
    cfg = load_config(ROOT / "config.yaml")
    assert cfg.defaults.prepare.downsample == 4 and cfg.defaults.prepare.test_every == 8
    assert "rtsplat" in cfg.methods and "2dgs" in cfg.methods
    # every key in config.yaml exists in the schema (it validated) and the schema has every field
    props = json_schema()["properties"]["defaults"]["properties"]
    assert set(props) == {"frames", "sfm", "masks", "prepare", "train", "render", "video", "metrics"}


def test_the_real_capture_benchmark_builds_every_method_on_both_captures():
    """benchmarks/real.yaml is a config of its own (not layered over the demo): both captures, every method,
    the demo's schedule at 1x and 4x, appearance off only where asked."""
    from rtsplat.config import trainer_options

    cfg = load_config(ROOT / "benchmarks" / "real.yaml")
    assert cfg.scenes == ["glass", "fox"] and cfg.defaults.prepare.resolution == 480
    trees = {(scene, m): trainer_options(cfg, scene, m) for scene in cfg.scenes for m in cfg.methods}
    for scene in cfg.scenes:
        assert trees[(scene, "rtsplat_x4")]["schedule"]["iterations"] == 4 * trees[(scene, "rtsplat")]["schedule"][
            "iterations"]
        assert TrainConfig.from_dict(trees[(scene, "rtsplat_no_appearance")]).effects.appearance == "off"
        assert TrainConfig.from_dict(trees[(scene, "rtsplat")]).effects.appearance == "auto"


def test_the_real_glass_is_marked_with_the_outlines_of_the_test_capture():
    """benchmarks/real.yaml marks 3-5 photos of the glass (its masks propagated, RT-Splatting's glass trained on
    real photos) with polygons in pixels of the 1008x756 photos named as README's fetch leaves them
    (frame_000NN.jpeg): the outlines drawn on tests/data/glass's 336x252 copies of the same photos, times 3."""
    from rtsplat.config import scene_config
    from rtsplat.masks.propagation import polygon_mask

    cfg = load_config(ROOT / "benchmarks" / "real.yaml")
    marks = scene_config(cfg, "glass").masks.marks
    outlines = json.loads((ROOT / "tests" / "data" / "glass" / "outlines.json").read_text())
    assert 3 <= len(marks) <= 5 and not scene_config(cfg, "fox").masks.marks
    for name, mark in marks.items():
        assert re.fullmatch(r"frame_000\d\d\.jpeg", name) and mark["polygon"]
        drawn = polygon_mask(np.asarray(mark["polygon"]) / 3.0, 336, 252)
        outline = polygon_mask(np.asarray(outlines[name.replace(".jpeg", ".jpg")], float), 336, 252)
        assert (drawn & outline).sum() >= 0.97 * (drawn | outline).sum(), name
        assert (np.asarray(mark["polygon"]).max(0) <= [1008, 756]).all()


def test_the_budget_curves_over_the_demo_pair_both_methods_at_every_budget():
    """benchmarks/budgets.yaml over demo/config.yaml: RT-Splatting and 2DGS at the same budgets, a quarter to four
    times the demo's iterations, and both with the half-size start."""
    from rtsplat.config import deep_merge, trainer_options

    data = deep_merge(yaml.safe_load((ROOT / "demo" / "config.yaml").read_text()),
                      yaml.safe_load((ROOT / "benchmarks" / "budgets.yaml").read_text()))
    cfg = load_config_dict(data, source="budgets.yaml")
    trees = {m: trainer_options(cfg, "dome", m) for m in cfg.methods}
    demo = trees["rtsplat"]["schedule"]["iterations"]
    for suffix, factor in (("quarter", 0.25), ("half", 0.5), ("x2", 2), ("x4", 4)):
        ours, theirs = trees[f"rtsplat_{suffix}"], trees[f"2dgs_{suffix}"]
        assert ours["schedule"]["iterations"] == theirs["schedule"]["iterations"] == round(factor * demo)
        assert theirs["effects"]["transmission"] == "off" and ours["effects"]["transmission"] == "auto"
    for method in ("rtsplat_halfstart", "2dgs_halfstart"):
        schedule = trees[method]["schedule"]
        assert (schedule["coarse_downsample"], schedule["full_resolution_from"], schedule["iterations"]) == (
            2, trees["rtsplat"]["schedule"]["densify_from"], demo)


def test_the_convergence_benchmark_pairs_both_methods_at_every_budget_on_one_tuning_scene_per_kind():
    """benchmarks/convergence.yaml, a config of its own: seed 0 of every kind of the family (tuning scenes, never
    seen or held out), RT-Splatting and 2DGS at 0.5, 1, 2, 4 and 8 times the demo's iterations, training seed 0,
    which the report's convergence section reads as one curve per method."""
    from rtsplat.config import roles_json, trainer_options
    from rtsplat.report import Roles, Run
    from rtsplat.report_convergence import scene_budgets
    from rtsplat.synth.family import KINDS, parse_name

    cfg = load_config(ROOT / "benchmarks" / "convergence.yaml")
    members = [parse_name(scene) for scene in cfg.scenes]
    assert sorted(m.kind for m in members) == sorted(KINDS) and {m.split for m in members} == {"tuning"}
    for scene in cfg.scenes:
        for budget in (0.5, 1, 2, 4, 8):
            ours, theirs = (TrainConfig.from_dict(trainer_options(cfg, scene, m if budget == 1 else f"{m}_x{budget:g}"))
                            for m in ("rtsplat", "2dgs"))
            assert ours.schedule.iterations == theirs.schedule.iterations == DEMO_ITERATIONS * budget
            assert ours.schedule.eval_every == round(DEMO_EVAL_EVERY * budget) and ours.seed == theirs.seed == 0
            assert (ours.effects.transmission, theirs.effects.transmission, theirs.effects.specular) == (
                "auto", "off", "off")
    roles = Roles.from_dict(json.loads(roles_json(cfg, quote=False)))
    budgets = scene_budgets({m: Run(cfg.scenes[0], m) for m in cfg.methods}, roles)
    assert [(b.factor, b.ours.method, b.theirs.method) for b in budgets] == [
        (0.5, "rtsplat_x0.5", "2dgs_x0.5"), (1.0, "rtsplat", "2dgs"), (2.0, "rtsplat_x2", "2dgs_x2"),
        (4.0, "rtsplat_x4", "2dgs_x4"), (8.0, "rtsplat_x8", "2dgs_x8")]


@pytest.mark.parametrize("name", ["family", "family_page", "family_quick", "heldout", "heldout_time", "convergence",
                                  "real"])
def test_every_standalone_benchmark_config_trains_at_the_demo_budget(name):
    """The standalone configs repeat demo/config.yaml's training settings (its compressed schedule, environment
    map and pruning): RT-Splatting and 2DGS build the same trainer configs as in the demo, the stated seed aside,
    so that "the demo's budget" means one thing in every benchmark."""
    from rtsplat.config import trainer_options

    demo = load_config_dict(DEMO, source="demo/config.yaml")
    cfg = load_config(ROOT / "benchmarks" / f"{name}.yaml")
    for method in ("rtsplat", "2dgs"):
        ours = trainer_options(cfg, cfg.scenes[0], method)
        reference = trainer_options(demo, demo.scenes[0], method)
        assert ours.pop("seed", 0) == reference.pop("seed", 0) == 0
        assert ours == reference, f"benchmarks/{name}.yaml's {method} differs from the demo's"


def test_the_held_out_time_benchmark_pairs_both_methods_at_three_budgets_on_held_out_scenes_only():
    """benchmarks/heldout_time.yaml: one held-out seed of every kind of the family (no tuning or seen scene),
    RT-Splatting and 2DGS at 0.5, 1 and 2 times the demo's iterations with convergence.yaml's settings,
    which the report's convergence section reads as one budget series per method."""
    from rtsplat.config import roles_json, trainer_options
    from rtsplat.report import Roles, Run
    from rtsplat.report_convergence import scene_budgets
    from rtsplat.synth.family import KINDS, parse_name

    cfg = load_config(ROOT / "benchmarks" / "heldout_time.yaml")
    members = [parse_name(scene) for scene in cfg.scenes]
    assert sorted(m.kind for m in members) == sorted(KINDS) and {m.split for m in members} == {"held_out"}
    convergence = load_config(ROOT / "benchmarks" / "convergence.yaml")
    for method in ("rtsplat", "2dgs"):
        for budget in (0.5, 1, 2):
            name = method if budget == 1 else f"{method}_x{budget:g}"
            options = trainer_options(cfg, cfg.scenes[0], name)
            assert options == trainer_options(convergence, convergence.scenes[0], name)
            assert TrainConfig.from_dict(options).schedule.iterations == DEMO_ITERATIONS * budget
    roles = Roles.from_dict(json.loads(roles_json(cfg, quote=False)))
    budgets = scene_budgets({m: Run(cfg.scenes[0], m) for m in cfg.methods}, roles)
    assert [(b.factor, b.ours.method, b.theirs.method) for b in budgets] == [
        (0.5, "rtsplat_x0.5", "2dgs_x0.5"), (1.0, "rtsplat", "2dgs"), (2.0, "rtsplat_x2", "2dgs_x2")]


@pytest.mark.parametrize("layer", ["targets.yaml", "targets_quick.yaml"])
def test_the_benchmark_configs_over_the_demo_build_every_method(layer):
    """`make targets` layers benchmarks/<layer> over demo/config.yaml: every method must build a valid
    trainer config on every scene before an hour of training starts."""
    from rtsplat.config import deep_merge, trainer_options

    data = deep_merge(yaml.safe_load((ROOT / "demo" / "config.yaml").read_text()),
                      yaml.safe_load((ROOT / "benchmarks" / layer).read_text()))
    cfg = load_config_dict(data, source=layer)
    assert {"rtsplat", "2dgs", "rtsplat_x4", "2dgs_x4"} <= set(cfg.methods)
    trees = {(scene, m): trainer_options(cfg, scene, m) for scene in cfg.scenes for m in cfg.methods}
    demo_iterations = trees[("dome", "rtsplat")]["schedule"]["iterations"]
    assert trees[("dome", "rtsplat_x4")]["schedule"]["iterations"] == 4 * demo_iterations
    assert trees[("cabin", "rtsplat_mlp64")]["model"]["mlp_width"] == 64
    assert trees[("cabin", "rtsplat_init1")]["densify"]["initial_copies"] == 1
    if layer == "targets.yaml":
        assert trees[("dome", "rtsplat_densify_more")]["densify"]["grad_threshold"] == 1e-4
        light = trees[("dome", "rtsplat_prune_light")]
        assert trees[("dome", "rtsplat")]["densify"]["prune_occupancy"] == 0.2
        assert light["densify"]["prune_occupancy"] == 0.05
        assert light["schedule"]["iterations"] == 0.8 * demo_iterations
        early = trees[("dome", "rtsplat_densify_early")]["schedule"]
        assert (early["densify_from"], trees[("dome", "rtsplat")]["schedule"]["densify_from"]) == (124, 188)
        assert early["volume_until"] == trees[("dome", "rtsplat")]["schedule"]["volume_until"]  # the rest kept
    assert trees[("dome", "2dgs_x4")]["effects"] == {"transmission": "off", "specular": "off",
                                                      "near_reflection": "off", "appearance": "auto"}


def test_the_ablations_at_4x_layer_builds_each_ablation_at_the_budget_of_its_full_model():
    """benchmarks/ablations_x4.yaml over the demo and the quick subset: the six ablations at 4x on the dome,
    each switching off its own term, and the report compares each with rtsplat_x4."""
    from rtsplat.config import deep_merge, roles_json, trainer_options
    from rtsplat.report import Roles, ablation_reference

    data = yaml.safe_load((ROOT / "demo" / "config.yaml").read_text())
    for layer in ("targets_quick.yaml", "ablations_x4.yaml"):
        data = deep_merge(data, yaml.safe_load((ROOT / "benchmarks" / layer).read_text()))
    cfg = load_config_dict(data, source="ablations_x4.yaml")
    assert cfg.scenes == ["dome"]
    roles = Roles.from_dict(json.loads(roles_json(cfg, quote=False)))
    ablations = [m for m in cfg.methods if m.startswith("ablation_") and m.endswith("_x4")]
    assert len(ablations) == 6
    full = trainer_options(cfg, "dome", "rtsplat_x4")
    for m in ablations:
        tree = trainer_options(cfg, "dome", m)
        switched_off = [k for k, on in tree["ablations"].items() if not on]
        assert switched_off == [m[len("ablation_"):-len("_x4")]]
        assert tree["schedule"] == full["schedule"]
        assert ablation_reference(m, cfg.methods, roles) == "rtsplat_x4"


def test_a_repeat_trains_the_options_of_the_method_it_reruns():
    """benchmarks/family.yaml's `2dgs_seed1: {role: repeat, of: 2dgs, seed: 1}` is 2DGS with seed 1, not the
    default model with seed 1: a repeat takes the options of its `of` method (budget too), its own keys merged
    over them."""
    from rtsplat.config import trainer_options

    cfg = load_config(ROOT / "benchmarks" / "family.yaml")
    scene = cfg.scenes[0]
    plain, repeat = trainer_options(cfg, scene, "2dgs"), trainer_options(cfg, scene, "2dgs_seed1")
    assert TrainConfig.from_dict(repeat).effects.transmission == "off"
    assert TrainConfig.from_dict(repeat).effects.specular == "off"
    assert repeat["seed"] == 1 and TrainConfig.from_dict(plain).seed != 1
    assert {k: v for k, v in repeat.items() if k != "seed"} == {k: v for k, v in plain.items() if k != "seed"}

    cfg = load_config_dict({"methods": {
        "rtsplat": {"role": "main"},
        "narrow_x4": {"budget": 4, "model": {"mlp_width": 64, "sh_degree": 2}},
        "narrow_x4_again": {"role": "repeat", "of": "narrow_x4", "seed": 3, "model": {"mlp_width": 32}},
    }})
    base, again = trainer_options(cfg, "any", "narrow_x4"), trainer_options(cfg, "any", "narrow_x4_again")
    assert again["schedule"]["iterations"] == base["schedule"]["iterations"]  # the budget of narrow_x4
    plain_iterations = TrainConfig.from_dict(trainer_options(cfg, "any", "rtsplat")).schedule.iterations
    assert again["schedule"]["iterations"] == 4 * plain_iterations
    assert again["model"]["mlp_width"] == 32 and again["model"]["sh_degree"] == 2 and again["seed"] == 3
    assert base["model"]["mlp_width"] == 64  # the rerun method keeps its own


def test_schema_also_accepts_what_snakemake_validates():
    import jsonschema

    data = yaml.safe_load((ROOT / "config.yaml").read_text())
    jsonschema.validate(data, json.loads(SCHEMA_PATH.read_text()))


@pytest.mark.parametrize(
    "data, expect",
    [
        (
            {"defaults": {"prepare": {"downsampel": 2}}},
            ["'defaults.prepare.downsampel' does not exist", "did you mean 'downsample'"],
        ),
        ({"scenez": []}, ["'scenez' does not exist", "did you mean 'scenes'"]),
        ({"defaults": {"sfm": {"matcher": "vocab"}}}, ["'defaults.sfm.matcher'", "exhaustive"]),
        ({"defaults": {"prepare": {"downsample": "four"}}}, ["'defaults.prepare.downsample'", "integer"]),
        ({"defaults": {"prepare": {"downsample": 0}}}, ["'defaults.prepare.downsample'", "minimum"]),
        ({"defaults": {"prepare": {"resolution": 0}}}, ["'defaults.prepare.resolution'", "minimum"]),
        ({"overrides": {"a": {"prepare": {"resolution": "800px"}}}}, ["'overrides.a.prepare.resolution'", "integer"]),
        (
            {"overrides": {"sedan": {"prepare": {"roi": {"center": [0, 0], "radius": 1}}}}},
            ["'overrides.sedan.prepare.roi.center'", "too short"],
        ),
        (
            {"overrides": {"sedan": {"train": {"iteration": 5}}}},
            ["'overrides.sedan.train.iteration' does not exist", "did you mean 'iterations'"],
        ),
        (
            {"defaults": {"train": {"options": {"schedule": {"iteratons": 5}}}}},
            ["'defaults.train.options.schedule.iteratons' does not exist", "did you mean 'iterations'"],
        ),
        (
            {"overrides": {"sedan": {"train": {"options": {"ablations": {"gating": "no"}}}}}},
            ["'overrides.sedan.train.options.ablations.gating'", "boolean"],
        ),
    ],
)
def test_errors_name_the_key_and_the_fix(data, expect):
    with pytest.raises(ConfigError) as err:
        validate_config(data, "my.yaml")
    msg = str(err.value)
    assert msg.startswith("my.yaml: ") and "Fix:" in msg
    for text in expect:
        assert text in msg, msg


def test_per_scene_overrides_merge_over_defaults():
    cfg = load_config_dict(
        {
            "defaults": {
                "prepare": {"downsample": 4},
                "train": {"iterations": 100, "options": {"schedule": {"log_every": 7}}},
            },
            "overrides": {
                "sedan": {
                    "prepare": {"downsample": 8, "roi": {"center": [1, 2, 3], "radius": 2}},
                    "train": {"backend": "reference"},
                }
            },
        }
    )
    sedan, other = scene_config(cfg, "sedan"), scene_config(cfg, "truck")
    assert sedan.prepare.downsample == 8 and sedan.prepare.roi.radius == 2.0
    assert sedan.train.iterations == 100 and sedan.train.backend == "reference"
    assert sedan.train.options == {"schedule": {"log_every": 7}}
    assert other.prepare.downsample == 4 and other.prepare.roi is None and other.train.backend == "auto"
    # the JSON a rule passes to the CLI round-trips into the same section
    text = section_json(cfg, "sedan", "prepare", quote=False)
    assert section_from_dict("prepare", json.loads(text)) == sedan.prepare


def test_a_scenes_resolution_decides_its_factor_over_the_default_downsample():
    from rtsplat.prepare import downsample_factor

    cfg = load_config_dict(
        {"defaults": {"prepare": {"downsample": 4}}, "overrides": {"cape": {"prepare": {"resolution": 800}}}}
    )
    cape, other = scene_config(cfg, "cape").prepare, scene_config(cfg, "other").prepare
    assert (cape.downsample, cape.resolution, other.resolution) == (4, 800, None)
    f, why = downsample_factor({(3648, 3648)}, cape, Path("images"))
    assert 3648 // f <= 800 < 3648 // (f - 1) and "prepare.resolution 800" in why
    assert downsample_factor({(3648, 3648)}, other, Path("images")) == (4, "prepare.downsample 4")


def test_method_overrides_reach_the_trainer_config():
    from rtsplat.train_config import TrainConfig

    cfg = load_config_dict(
        {
            "methods": {
                "rtsplat": {},
                "2dgs": {"effects": {"transmission": "off", "specular": "off"}},
                "ablation_gating": {"ablations": {"gating": False}, "schedule": {"log_every": 3}},
            },
            "defaults": {"train": {"iterations": 50, "options": {"schedule": {"log_every": 7}}}},
            "overrides": {"sedan": {"train": {"backend": "reference"}}},
        }
    )
    plain = TrainConfig.from_dict(json.loads(train_json(cfg, "sedan", "2dgs", quote=False)))
    assert (plain.effects.transmission, plain.effects.specular) == ("off", "off")
    assert plain.schedule.iterations == 50 and plain.schedule.log_every == 7 and plain.backend == "reference"
    ablation = TrainConfig.from_dict(json.loads(train_json(cfg, "truck", "ablation_gating", quote=False)))
    assert ablation.ablations.gating is False and ablation.schedule.log_every == 3 and ablation.backend == "auto"
    with pytest.raises(ConfigError, match="unknown method"):
        train_json(cfg, "sedan", "nerf")


def test_budget_method_scales_every_iteration_count_and_bad_methods_fail_at_load():
    from rtsplat.train_config import ITERATION_COUNTS, TrainConfig

    options = {"schedule": {"volume_until": 100, "specular_from": 200, "densify_every": 100, "eval_every": 0}}
    cfg = load_config_dict({
        "methods": {"rtsplat": {}, "rtsplat_x4": {"budget": 4}, "rtsplat_short": {"budget": 0.25},
                    "fixed": {"budget": 2, "schedule": {"iterations": 100}}},
        "defaults": {"train": {"iterations": 600, "options": options}},
    })
    base, x4, short, fixed = (TrainConfig.from_dict(json.loads(train_json(cfg, "s", m, quote=False)))
                              for m in ("rtsplat", "rtsplat_x4", "rtsplat_short", "fixed"))
    for section, names in ITERATION_COUNTS.items():
        for name in names:
            value = getattr(getattr(base, section), name)
            if value is None:  # a count that follows the run's length (densify_until, position_max_steps)
                assert getattr(getattr(x4, section), name) is None and getattr(getattr(short, section), name) is None
                continue
            assert getattr(getattr(x4, section), name) == 4 * value, (section, name)
            assert getattr(getattr(short, section), name) == (max(round(value / 4), 1) if value else 0), name
    assert (x4.schedule.iterations, x4.schedule.volume_until, x4.schedule.specular_from) == (2400, 400, 800)
    assert x4.schedule.log_every == base.schedule.log_every and x4.lr.position_init == base.lr.position_init
    assert (x4.schedule.densify_stop(), base.schedule.densify_stop()) == (1200, 300)
    assert fixed.schedule.iterations == 200  # the method's own iterations win over train.iterations, then scale
    for bad, match in (({"budget": 0}, "budget factor must be > 0"), ({"budget": "x"}, "'x' is not a time"),
                       ({"budget": "0s"}, "'0s' is not a time"), ({"budget": True}, "budget must be a number"),
                       ({"schedule": {"iteration": 3}}, "train.schedule.iteration")):
        with pytest.raises(ConfigError, match=match):
            load_config_dict({"methods": {"bad": bad}})


def test_a_time_budget_sets_the_seconds_and_keeps_the_plan():
    from rtsplat.config import slurm_resources
    from rtsplat.train_config import TrainConfig

    cfg = load_config_dict({
        "methods": {"rtsplat": {}, "five": {"budget": "5min"}, "quick": {"budget": " 90.5 s"},
                    "long": {"budget": "2h"}},
        "defaults": {"train": {"iterations": 600}},
    })
    base, five, quick, long = (TrainConfig.from_dict(json.loads(train_json(cfg, "s", m, quote=False)))
                               for m in ("rtsplat", "five", "quick", "long"))
    assert (base.schedule.seconds, five.schedule.seconds, quick.schedule.seconds, long.schedule.seconds) == (
        None, 300.0, 90.5, 7200.0)
    five.schedule.seconds = None
    assert five == base  # only the time budget differs: the plan's iteration counts are the method's own
    # a SLURM job of a time-budget training asks for the fixed minutes plus twice the budget
    fixed = slurm_resources(cfg, "train", "s", "rtsplat")["runtime"] - math.ceil(
        cfg.slurm.train_minutes_per_1000_iterations * 600 / 1000)
    assert slurm_resources(cfg, "train", "s", "long")["runtime"] == fixed + 240


def test_a_method_with_time_of_trains_the_other_runs_time_and_is_validated():
    from rtsplat.config import MethodRole, method_roles, roles_json, slurm_resources

    methods = {"rtsplat": {"role": "main"}, "2dgs": {"effects": {"specular": "off"}, "budget": 2},
               "rtsplat_eq": {"time_of": "2dgs", "seed": 3},
               "rtsplat_eq_seed1": {"role": "repeat", "of": "rtsplat_eq", "seed": 4}}
    cfg = load_config_dict({"methods": methods, "defaults": {"train": {"iterations": 600}}})
    roles = method_roles(cfg)
    assert roles["rtsplat_eq"] == MethodRole("baseline", None, "2dgs")
    assert roles["rtsplat_eq_seed1"] == MethodRole("repeat", "rtsplat_eq", "2dgs")  # a repeat keeps the time
    assert roles["2dgs"] == MethodRole("baseline") and roles["rtsplat"] == MethodRole("main")
    assert json.loads(roles_json(cfg, quote=False))["rtsplat_eq"]["time_of"] == "2dgs"
    # no trainer key, no time budget yet (the other run's seconds come with rtsplat train --seconds-of)
    eq = json.loads(train_json(cfg, "s", "rtsplat_eq", quote=False))
    assert "time_of" not in eq and eq["schedule"].get("seconds") is None and eq["seed"] == 3
    # a SLURM job of it asks for the other method's time (2dgs at budget 2: twice the iterations)
    assert slurm_resources(cfg, "train", "s", "rtsplat_eq") == slurm_resources(cfg, "train", "s", "2dgs")
    assert slurm_resources(cfg, "train", "s", "2dgs") != slurm_resources(cfg, "train", "s", "rtsplat")
    for bad, match in (({"a": {}, "b": {"time_of": "c"}}, "methods.b.time_of is 'c'"),
                       ({"a": {}, "b": {"time_of": "b"}}, "methods.b.time_of is 'b'"),
                       ({"a": {"time_of": "b"}, "b": {}, "c": {"time_of": "a"}}, "methods.c.time_of is 'a'"),
                       ({"a": {}, "b": {"time_of": "a", "budget": 2}}, "both time_of and budget")):
        with pytest.raises(ConfigError, match=match):
            load_config_dict({"methods": bad})


@pytest.mark.parametrize("name", ["family", "heldout"])
def test_the_family_benchmarks_train_rtsplat_for_2dgs_time_too(name):
    """The family's benchmarks have RT-Splatting's options trained for the time the 2dgs run took: the
    report's comparison of finished runs at equal time."""
    from rtsplat.config import method_roles, trainer_options

    cfg = load_config(ROOT / "benchmarks" / f"{name}.yaml")
    scene = cfg.scenes[0]
    assert method_roles(cfg)["rtsplat_at_2dgs_time"].time_of == "2dgs"
    assert trainer_options(cfg, scene, "rtsplat_at_2dgs_time") == trainer_options(cfg, scene, "rtsplat")


def test_method_roles_are_explicit_validated_and_not_trainer_keys():
    from rtsplat.config import MethodRole, main_method, method_roles, roles_json

    methods = {"base": {"role": "baseline"}, "full": {"role": "main", "seed": 2},
               "no_gating": {"role": "ablation", "ablations": {"gating": False}},
               "again": {"role": "repeat", "of": "full", "seed": 5}, "other": {}}
    cfg = load_config_dict({"methods": methods})
    assert method_roles(cfg) == {"base": MethodRole("baseline"), "full": MethodRole("main"),
                                 "no_gating": MethodRole("ablation"), "again": MethodRole("repeat", "full"),
                                 "other": MethodRole("baseline")}
    assert main_method(cfg) == "full"
    assert json.loads(roles_json(cfg, quote=False))["again"] == {"role": "repeat", "of": "full", "time_of": None}
    # role keys never reach the trainer; the method's own keys do
    again = json.loads(train_json(cfg, "s", "again", quote=False))
    assert "role" not in again and "of" not in again and again["seed"] == 5
    # without any role: the first method listed is the main one, the others baselines
    plain = load_config_dict({"methods": {"b": {}, "a": {}}})
    assert main_method(plain) == "b" and method_roles(plain)["a"] == MethodRole("baseline")
    for bad, match in (({"a": {"role": "star"}}, r"methods\.a\.role.*one of"),
                       ({"a": {"role": "main"}, "b": {"role": "main"}}, "several methods have role main"),
                       ({"a": {}, "b": {"role": "repeat"}}, "methods.b.of is None"),
                       ({"a": {}, "b": {"role": "repeat", "of": "c"}}, "methods.b.of is 'c'"),
                       ({"a": {}, "b": {"role": "ablation", "of": "a"}}, "its role is ablation")):
        with pytest.raises(ConfigError, match=match):
            load_config_dict({"methods": bad})


def test_scene_discovery(tmp_path):
    for s in ("b", "a"):
        (tmp_path / s / "images").mkdir(parents=True)
    (tmp_path / "notes").mkdir()
    assert discover_scenes(load_config_dict({"data": str(tmp_path)})) == ["a", "b"]
    assert discover_scenes(load_config_dict({"data": str(tmp_path), "scenes": ["b"]})) == ["b"]
    with pytest.raises(ConfigError, match="listed scenes have no images/ folder: c"):
        discover_scenes(load_config_dict({"data": str(tmp_path), "scenes": ["c"]}))
    with pytest.raises(ConfigError, match="overrides given for unknown scenes: z"):
        discover_scenes(load_config_dict({"data": str(tmp_path), "overrides": {"z": {}}}))
    with pytest.raises(ConfigError, match="no scenes found"):
        discover_scenes(load_config_dict({"data": str(tmp_path / "notes")}))


def test_config_file_errors(tmp_path):
    p = tmp_path / "c.yaml"
    p.write_text("defaults: [1, 2\n")
    with pytest.raises(ConfigError, match="not valid YAML"):
        load_config(p)
    with pytest.raises(ConfigError, match="config file not found"):
        load_config(tmp_path / "missing.yaml")


def test_stage_cli_reads_config_file_with_scene_overrides(tmp_path):
    import argparse

    from rtsplat.config import add_config_arguments, stage_config_from_args

    p = tmp_path / "c.yaml"
    p.write_text(
        yaml.safe_dump(
            {"defaults": {"prepare": {"downsample": 2}}, "overrides": {"sedan": {"prepare": {"downsample": 8}}}}
        )
    )
    parser = argparse.ArgumentParser()
    add_config_arguments(parser)
    sedan = parser.parse_args(["--config", str(p), "--scene", "sedan"])
    assert stage_config_from_args(sedan, "prepare").downsample == 8
    assert stage_config_from_args(parser.parse_args(["--config", str(p)]), "prepare").downsample == 2
    assert stage_config_from_args(parser.parse_args([]), "prepare").downsample == 1
    args = parser.parse_args(["--config-json", '{"downsampel": 3}'])
    with pytest.raises(ConfigError, match="'defaults.prepare.downsampel' does not exist"):
        stage_config_from_args(args, "prepare")


def test_stage_flags_are_validated_overrides_of_the_config_section():
    import argparse

    from rtsplat.config import add_config_arguments, stage_config_from_args

    parser = argparse.ArgumentParser()
    add_config_arguments(parser)
    args = parser.parse_args(["--config-json", '{"downsample": 2, "test_every": 5}'])
    cfg = stage_config_from_args(args, "prepare", {"downsample": 4})
    assert (cfg.downsample, cfg.test_every) == (4, 5)  # the flag wins, the rest of the section stays
    assert stage_config_from_args(args, "prepare", {"downsample": None}).downsample == 2  # flag not given
    with pytest.raises(ConfigError, match=r"prepare\.downsample.*less than the minimum of 1"):
        stage_config_from_args(args, "prepare", {"downsample": 0})
    masks = stage_config_from_args(parser.parse_args([]), "masks", {"source": "none", "onnx.model": "m.onnx"})
    assert masks.source == "none" and masks.onnx.model == "m.onnx" and masks.onnx.kind == "auto"


def test_gpus_of_a_slurm_cluster_are_read_from_its_gres_lists():
    from rtsplat.slurm import gpus_in_gres

    assert gpus_in_gres("(null)\n(null)\n") == 0
    assert gpus_in_gres("gpu:a100:4(S:0-1)\n(null)\n") == 4
    assert gpus_in_gres("gpu:2,shard:8\ngpu:v100:1\n") == 2
    assert gpus_in_gres("gpu\n") == 1
    assert gpus_in_gres("shard:8\nmps:100\n") == 0


def test_slurm_pre_flight_names_the_setting_when_the_cluster_has_no_gpu(tmp_path):
    from rtsplat.errors import ConfigError
    from rtsplat.slurm import check_cluster_gpus

    sinfo = tmp_path / "sinfo"
    sinfo.write_text("#!/bin/sh\necho '(null)'\n")
    sinfo.chmod(0o755)
    check_cluster_gpus(0, sinfo=str(sinfo))  # a CPU-only run asks nothing of it
    with pytest.raises(ConfigError, match=r"(?s)this cluster has no GPUs.*slurm.gpus: 0"):
        check_cluster_gpus(1, sinfo=str(sinfo))
    sinfo.write_text("#!/bin/sh\necho 'gpu:h100:4'\n")
    check_cluster_gpus(2, sinfo=str(sinfo))
