"""Training stops on a non-finite loss, gradient or parameter without writing the diverged state,
and a resume with a config that differs from the checkpoint's is an error unless asked for."""

from __future__ import annotations

import json

import pytest
import torch
import yaml

from rtsplat.bench.toy_scene import write_scene
from rtsplat.cli import main
from rtsplat.io.outputs import mark_output
from rtsplat.model.checkpoint import CheckpointError, read_checkpoint
from rtsplat.train import trainer as trainer_module
from rtsplat.train.divergence import TrainingDiverged
from rtsplat.train.trainer import Trainer
from rtsplat.train_config import TrainConfig


def config(iterations: int = 10, **sections) -> TrainConfig:
    data = {"schedule": {"iterations": iterations, "volume_until": 2, "specular_from": 4, "densify_from": 10**6,
                         "reset_every": 0, "log_every": 5, "checkpoint_every": 3, "separate_background_until": 0},
            "model": {"env_height": 8, "env_width": 16, "env_levels": 2, "mlp_width": 8}}
    for key, value in sections.items():
        data.setdefault(key, {}).update(value)
    return TrainConfig.from_dict(data)


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    return write_scene(tmp_path_factory.mktemp("scene"), views=5, width=24, height=18, n_side=8)


def quiet(scene, cfg, run):
    return Trainer(scene, cfg, run, progress=False, log=lambda m: None)


def assert_nothing_diverged_written(run, before: int):
    """last.pt is from an iteration before ``before`` and finite; no final outputs exist."""
    checkpoint = read_checkpoint(run / "checkpoints" / "last.pt")
    assert checkpoint.training["iteration"] < before
    for name, value in checkpoint.surfels.items():
        assert torch.isfinite(value).all(), name
    for name in ("model.pt", "point_cloud.ply", "summary.json"):
        assert not (run / name).exists(), name


def test_a_nan_loss_stops_the_run_and_keeps_the_last_good_checkpoint(scene, tmp_path, monkeypatch):
    image_loss, calls = trainer_module.losses.image_loss, []

    def nan_at_seven(*args, **kwargs):
        calls.append(1)
        value = image_loss(*args, **kwargs)
        return value * float("nan") if len(calls) == 7 else value

    monkeypatch.setattr(trainer_module.losses, "image_loss", nan_at_seven)
    run = tmp_path / "run"
    trainer = quiet(scene, config(10), run)
    with pytest.raises(TrainingDiverged) as error:
        trainer.train()
    message = str(error.value)
    assert "diverged at iteration 7:" in message and "the loss" in message
    assert "lower the learning rates" in message and "input data" in message
    assert f"{run / 'checkpoints' / 'last.pt'} (iteration 6)" in message and "--resume-with-new-config" in message
    assert trainer.iteration == 7  # stopped at once on a CPU
    assert_nothing_diverged_written(run, 7)
    assert read_checkpoint(run / "checkpoints" / "last.pt").training["iteration"] == 6
    logged = [json.loads(line)["iteration"] for line in (run / "train_log.jsonl").read_text().splitlines()]
    assert max(logged) < 7


def test_a_nan_gradient_names_its_group_and_learning_rate(scene, tmp_path):
    trainer = quiet(scene, config(10), tmp_path / "run")
    sh_dc = trainer.model.surfels.sh_dc  # densification is off: the parameter stays this tensor
    sh_dc.register_hook(lambda grad: grad * float("nan") if trainer.iteration == 4 else grad)
    with pytest.raises(TrainingDiverged, match="iteration 4") as error:
        trainer.train()
    message = str(error.value)
    assert "the gradients of sh_dc" in message and "lower train.lr.sh_dc" in message
    assert "the loss" not in message
    assert_nothing_diverged_written(tmp_path / "run", 4)


def test_a_huge_position_learning_rate_exits_1_through_the_cli(scene, tmp_path, capsys):
    cfg = config(6, lr={"position_init": 1e45}, schedule={"checkpoint_every": 0})
    (tmp_path / "train.yaml").write_text(yaml.safe_dump({"train": cfg.to_dict()}))
    run = tmp_path / "run"
    code = main(["train", "--data", str(scene.root), "--out", str(run), "--config", str(tmp_path / "train.yaml"),
                 "--quiet"])
    err = capsys.readouterr().err
    assert code == 1
    assert "rtsplat train: error: training diverged at iteration 1:" in err
    assert "the parameters means" in err and "train.lr.position_init" in err
    assert "no checkpoint was written" in err
    for name in ("model.pt", "point_cloud.ply", "summary.json", "checkpoints/last.pt"):
        assert not (run / name).exists(), name


def test_resuming_with_a_different_config_names_the_keys(scene, tmp_path):
    run = tmp_path / "run"
    quiet(scene, config(6), run).train()
    changed = config(9, lr={"sh_dc": 0.01}, losses={"ssim_weight": 0.5}, schedule={"log_every": 2})
    with pytest.raises(CheckpointError) as error:
        quiet(scene, changed, run).train()
    message = str(error.value)
    assert "train.lr.sh_dc: 0.002 -> 0.01" in message and "train.losses.ssim_weight: 0.2 -> 0.5" in message
    assert "schedule" not in message.split("Fix:")[0]  # iterations and log_every may change
    assert "--resume-with-new-config" in message
    assert read_checkpoint(run / "checkpoints" / "last.pt").training["iteration"] == 6

    lines = []
    resumed = Trainer(scene, changed, run, progress=False, log=lines.append)
    assert resumed.train(new_config=True)["iterations"] == 9
    assert any("resumed from" in line and "iteration 6" in line for line in lines)
    assert any("changed config" in line and "train.lr.sh_dc" in line for line in lines)
    # only the run's length changed: no flag needed
    assert quiet(scene, config(12, lr={"sh_dc": 0.01}, losses={"ssim_weight": 0.5}), run).train()["iterations"] == 12


def test_resume_with_new_config_flag_of_the_cli(scene, tmp_path, capsys):
    run = tmp_path / "run"
    quiet(scene, config(6), run).train()
    mark_output(run, "train")
    (tmp_path / "train.yaml").write_text(yaml.safe_dump({"train": config(8, lr={"opacity": 0.02}).to_dict()}))
    argv = ["train", "--data", str(scene.root), "--out", str(run), "--config", str(tmp_path / "train.yaml"), "--quiet"]
    assert main(argv) == 1
    assert "train.lr.opacity: 0.05 -> 0.02" in capsys.readouterr().err
    assert read_checkpoint(run / "checkpoints" / "last.pt").training["iteration"] == 6
    assert main([*argv, "--resume-with-new-config"]) == 0
    assert json.loads((run / "summary.json").read_text())["iterations"] == 8
