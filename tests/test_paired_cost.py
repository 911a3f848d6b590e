"""``python -m rtsplat.bench.paired_cost``: two or more methods trained at the same time, their CPU seconds split by the
parts of the schedule. The split is checked on a log written here; the whole bench on a toy scene."""

from __future__ import annotations

import json

import pytest

from rtsplat.bench import paired_cost
from rtsplat.bench.toy_scene import write_scene
from rtsplat.train_config import TrainConfig


def _schedule():
    return TrainConfig.from_dict({"schedule": {"iterations": 100, "volume_until": 20, "specular_from": 40,
                                               "specular_coarse_share": 0.5}}).validate().schedule


def test_the_seconds_between_log_lines_count_for_the_part_of_the_later_line():
    # one line every 10 iterations; each interval costs its own number of seconds, so a misplaced one shows
    stages = {10: "volume", 20: "volume", 30: "subsurface", 40: "subsurface", 50: "full", 60: "full", 70: "full",
              80: "full", 90: "full", 100: "full"}
    costs = {10: 1.0, 20: 2.0, 30: 4.0, 40: 8.0, 50: 16.0, 60: 32.0, 70: 64.0, 80: 128.0, 90: 256.0, 100: 512.0}
    records, total = [{"iteration": 0, "cpu_seconds": 0.0, "test_psnr": 10.0}], 0.0
    for it in range(10, 101, 10):
        total += costs[it]
        records.append({"iteration": it, "cpu_seconds": total, "stage": stages[it], "loss": 0.1})
        if it == 50:
            records.append({"iteration": it, "test_psnr": 20.0})  # an evaluation line carries no time
    parts = paired_cost.part_seconds(records, _schedule())
    # the full stage runs from iteration 41; its first half (up to 70) shades 2x2 blocks
    assert parts == {"volume": 1.0 + 2.0, "subsurface": 4.0 + 8.0, "full, 2x2 shading": 16.0 + 32.0 + 64.0,
                     "full": 128.0 + 256.0 + 512.0}
    assert list(parts) == ["volume", "subsurface", "full, 2x2 shading", "full"]


def test_bad_inputs_are_named_before_anything_trains(tmp_path, capsys):
    config = tmp_path / "config.yaml"
    config.write_text("methods:\n  rtsplat: {role: main}\n  2dgs: {role: baseline}\n")
    assert paired_cost.main(["--config", str(config), "--prepared", str(tmp_path), "--out",
                             str(tmp_path / "out"), "--methods", "rtsplat,refgs"]) == 1
    assert "refgs" in capsys.readouterr().err
    assert paired_cost.main(["--config", str(config), "--prepared", str(tmp_path / "nothing"), "--out",
                             str(tmp_path / "out")]) == 1
    assert "not a prepared scene" in capsys.readouterr().err
    assert not (tmp_path / "out").exists()


def test_the_out_folder_is_never_a_folder_of_the_users(tmp_path, capsys):
    prepared = tmp_path / "scene" / "prepared"
    write_scene(prepared, views=4, width=16, height=12)
    config = tmp_path / "config.yaml"
    config.write_text("methods:\n  rtsplat: {role: main}\n  2dgs: {role: baseline}\n")
    user = tmp_path / "user"
    user.mkdir()
    (user / "notes.txt").write_text("mine")
    cases = {user: "exists, is not empty", prepared: "exists, is not empty", prepared / "inside": "input"}
    for out, message in cases.items():
        assert paired_cost.main(["--config", str(config), "--prepared", str(prepared), "--out", str(out)]) == 1
        assert message in capsys.readouterr().err
    assert (user / "notes.txt").read_text() == "mine" and sorted(p.name for p in user.iterdir()) == ["notes.txt"]
    assert not (prepared / "inside").exists() and not (prepared / "paired_cost.json").exists()


@pytest.mark.slow
def test_two_methods_train_side_by_side_and_their_ratio_is_that_of_their_summaries(tmp_path, capsys):
    prepared = tmp_path / "toy" / "prepared"
    write_scene(prepared, views=6, width=32, height=24)
    schedule = {"iterations": 16, "volume_until": 5, "specular_from": 8, "densify_from": 100, "log_every": 2,
                "eval_every": 0, "checkpoint_every": 0}
    model = {"env_height": 16, "env_width": 32, "env_levels": 3, "mlp_width": 16}
    config = tmp_path / "config.yaml"
    config.write_text(json.dumps({"methods": {
        "rtsplat": {"role": "main", "schedule": schedule, "model": model},
        "2dgs": {"role": "baseline", "schedule": schedule, "model": model,
                 "effects": {"transmission": "off", "specular": "off"}},
        "narrow": {"role": "ablation", "schedule": schedule, "model": {**model, "mlp_width": 8}}}}))
    out = tmp_path / "out"
    assert paired_cost.main(["--config", str(config), "--prepared", str(prepared), "--out", str(out),
                             "--methods", "rtsplat,2dgs,narrow", "--equal-time"]) == 0
    result = json.loads((out / "paired_cost.json").read_text())
    scene = result["scenes"][0]
    assert scene["scene"] == "toy"
    summaries = {m: json.loads((out / "toy" / m / "summary.json").read_text()) for m in ("rtsplat", "2dgs")}
    assert summaries["rtsplat"]["iterations"] == summaries["2dgs"]["iterations"] == 16
    assert scene["ratio"] == pytest.approx(summaries["rtsplat"]["train_cpu_seconds"]
                                           / summaries["2dgs"]["train_cpu_seconds"])
    # the parts hold the CPU seconds of the logged iterations (the first log line's come before any part)
    for method in ("rtsplat", "2dgs"):
        parts = scene["runs"][method]["parts"]
        assert set(parts) == {"volume", "subsurface", "full, 2x2 shading", "full"}
        assert 0 < sum(parts.values()) <= summaries[method]["train_cpu_seconds"] + 1e-6
    assert set(scene["wall_seconds"]) == {"rtsplat", "2dgs", "narrow"}
    assert not (out / "toy" / ".filler").exists()  # the filler runs are gone
    printed = capsys.readouterr().out
    assert "median ratio rtsplat / 2dgs" in printed and "median ratio narrow / 2dgs" in printed
    assert result["complete"] and result["median_ratio"] == scene["ratio"]
    narrow = json.loads((out / "toy" / "narrow" / "summary.json").read_text())["train_cpu_seconds"]
    assert scene["ratios"]["narrow"] == pytest.approx(narrow / summaries["2dgs"]["train_cpu_seconds"])
    assert set(scene["ratios"]) == set(scene["equal_time_runs"]) == {"rtsplat", "narrow"}
    # the equal-time runs: every iteration count of each method's config times 2dgs's / its CPU seconds
    for method in ("rtsplat", "narrow"):
        config_json = json.loads((out / "toy" / f"{method}_equal_time" / "config.json").read_text())
        equal, ratio = config_json["schedule"], scene["ratios"][method]
        assert scene["equal_time_runs"][method]["budget"] == pytest.approx(1 / ratio)
        for count, planned in (("iterations", 16), ("volume_until", 5), ("specular_from", 8)):
            assert equal[count] == max(round(planned / ratio), 1)
        assert scene["equal_time_runs"][method]["iterations"] == equal["iterations"]
    assert config_json["model"]["mlp_width"] == 8  # the method's own config, scaled
    assert scene["equal_time"] == scene["equal_time_runs"]["rtsplat"]
    # a second run into its own folder is allowed; it replaces the runs
    assert paired_cost.check_out_folder(out, [prepared]) is None
