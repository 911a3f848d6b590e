"""The schedule clock: plan positions by iterations or by the share of a time budget spent, and events
that recur every N plan iterations happening once per multiple passed."""

from __future__ import annotations

import json

import pytest

from rtsplat.train.clock import ScheduleClock, passed


def test_passed_finds_the_multiple_a_step_moves_over():
    assert passed(49, 50, 50) == 50
    assert passed(50, 51, 50) is None
    assert passed(47, 103, 50) == 100  # two multiples in one step: the event happens once
    assert passed(50, 50, 50) is None  # a step that does not move the plan passes nothing
    assert passed(0, 10, 0) is None  # 0: never
    # within a window: a step from 40 to 281 passes 100 and 200; with the window [50, 200) only 100 counts
    assert passed(40, 281, 100, start=50, stop=200) == 100
    assert passed(40, 99, 100, start=50, stop=200) is None and passed(40, 281, 100, start=250) is None
    # one step at a time, it is the usual `iteration % every == 0`
    assert [i for i in range(1, 40) if passed(i - 1, i, 7) is not None] == [7, 14, 21, 28, 35]


def test_an_iteration_budget_steps_the_plan_one_iteration_at_a_time():
    clock = ScheduleClock(iterations=5)
    assert [clock.advance(spent=123.0) for _ in range(5)] == [(0, 1), (1, 2), (2, 3), (3, 4), (4, 5)]
    assert not clock.done(4, 1e9) and clock.done(5, 0.0)


@pytest.mark.parametrize("seconds_per_step", [0.3, 1.0, 7.0])
def test_a_time_budget_places_each_step_by_the_share_spent(seconds_per_step):
    # a 100-iteration plan in 10 s: every plan iteration is reached in order, never passed backwards, the
    # last ones at the end of the budget, whether a step takes a fraction of a plan iteration or several
    clock = ScheduleClock(iterations=100, seconds=10.0)
    spent, steps, positions = 0.0, 0, []
    while not clock.done(steps, spent):
        previous, current = clock.advance(spent)
        assert previous <= current <= 100
        assert current - 1 <= 100 * spent / 10.0 + 1e-9 and (current == 100 or 100 * spent / 10.0 < current + 1e-9)
        positions.append(current)
        spent += seconds_per_step
        steps += 1
    assert spent >= 10.0 and spent - seconds_per_step < 10.0
    assert positions[0] == 1 and positions == sorted(positions)
    assert positions[-1] >= 100 * (spent - seconds_per_step) / 10.0 - 1e-9  # the last step is at the budget's end


def test_training_with_a_time_budget_stops_at_it_and_keeps_the_plans_order(tmp_path):
    from rtsplat.bench.toy_scene import write_scene
    from rtsplat.train.trainer import Trainer, stage_at
    from rtsplat.train_config import TrainConfig

    scene = write_scene(tmp_path / "scene", views=6, width=32, height=24)
    cfg = TrainConfig.from_dict({
        "schedule": {"iterations": 400, "seconds": 3.0, "volume_until": 100, "specular_from": 200,
                     "densify_from": 50, "densify_every": 100, "reset_every": 0, "log_every": 1, "eval_every": 100,
                     "checkpoint_every": 0},
        "model": {"env_height": 16, "env_width": 32, "env_levels": 3, "mlp_width": 32}})
    summary = Trainer(scene, cfg, tmp_path / "run", progress=False, log=lambda m: None).train()
    log = [json.loads(line) for line in (tmp_path / "run" / "train_log.jsonl").read_text().splitlines()]
    steps = [r for r in log if r["iteration"] > 0]
    assert summary["time_budget_seconds"] == 3.0 and summary["iterations"] == len(steps)
    assert summary["train_seconds"] >= 3.0 and steps[-2]["seconds"] < 3.0  # stopped once the budget was spent
    positions = [r["position"] for r in steps]
    assert positions == sorted(positions) and positions[-1] <= 400
    assert all(r["stage"] == stage_at(r["position"], cfg) for r in steps)
    # density control ran at the one step that passed 100, the only multiple of densify_every in
    # [densify_from, densify_until) = [50, 200) (every step is logged: log_every 1)
    passing = [p for q, p in zip([0, *positions], positions, strict=False) if q < 100 <= p]
    assert len(passing) == 1 and [r["position"] for r in steps if r.get("density")] == passing
    assert "test_psnr" in steps[-1]  # the last step was evaluated


def test_seconds_of_trains_for_the_training_time_of_another_run(tmp_path, capsys):
    # rtsplat train --seconds-of RUN: the time budget is RUN's train_seconds (the comparison at equal time)
    from rtsplat.bench.toy_scene import write_scene
    from rtsplat.cli import main

    scene = write_scene(tmp_path / "scene", views=6, width=32, height=24)
    other = tmp_path / "other"
    other.mkdir()
    (other / "summary.json").write_text(json.dumps({"train_seconds": 1.5, "iterations": 40}))
    options = json.dumps({"schedule": {"iterations": 400, "seconds": 60.0, "log_every": 1, "eval_every": 0,
                                       "checkpoint_every": 0},
                          "model": {"env_height": 16, "env_width": 32, "env_levels": 3, "mlp_width": 32}})
    args = ["train", "--data", str(scene.root), "--config-json", options, "--quiet"]
    assert main([*args, "--out", str(tmp_path / "run"), "--seconds-of", str(other)]) == 0
    summary = json.loads((tmp_path / "run" / "summary.json").read_text())
    assert summary["time_budget_seconds"] == 1.5  # replaces the config's 60 s
    assert 1.5 <= summary["train_seconds"] < 1.5 + 1.0 and summary["iterations"] < 400
    # a run that has not finished (no summary) or a summary without a positive time: an error naming the file,
    # and no run folder left behind
    (other / "summary.json").write_text(json.dumps({"train_seconds": 0}))
    for run_dir, seconds_of in ((tmp_path / "bad1", tmp_path / "missing"), (tmp_path / "bad2", other)):
        capsys.readouterr()
        assert main([*args, "--out", str(run_dir), "--seconds-of", str(seconds_of)]) != 0
        error = capsys.readouterr().err
        assert f"{seconds_of / 'summary.json'}: --seconds-of" in error and "Fix:" in error
        assert not run_dir.exists()


def test_a_method_with_time_of_needs_the_other_run_on_the_command_line(tmp_path):
    import argparse

    import yaml

    from rtsplat.errors import ConfigError
    from rtsplat.train.cli import trainer_config_from_args

    config = tmp_path / "config.yaml"
    config.write_text(yaml.safe_dump({"methods": {"rtsplat": {"role": "main"}, "2dgs": {"seed": 2},
                                                  "rtsplat_eq": {"time_of": "2dgs", "seed": 3}}}))

    def args(**given):
        return argparse.Namespace(**{"config": str(config), "config_json": None, "scene": None, "method": "rtsplat_eq",
                                     "seconds_of": None, **given})

    with pytest.raises(ConfigError, match=r"(?s)rtsplat_eq trains for as long as the run of 2dgs took.*--seconds-of"):
        trainer_config_from_args(args())
    assert trainer_config_from_args(args(seconds_of=tmp_path)).seed == 3  # with it: the method's own options
    assert trainer_config_from_args(args(method="2dgs")).seed == 2
