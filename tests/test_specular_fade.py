"""The full model's specular branch fading in after ``schedule.specular_from`` (``schedule.specular_fade``)."""

from __future__ import annotations

import torch

from rtsplat.bench.toy_scene import write_scene
from rtsplat.train.trainer import Trainer, stage_at
from rtsplat.train_config import Schedule, TrainConfig, scale_budget


def test_the_weight_rises_linearly_over_its_share_of_the_plan_after_specular_from():
    s = Schedule(iterations=750, specular_from=250, specular_fade=0.1)  # 75 iterations
    assert [s.specular_weight_at(i) for i in (0, 250)] == [0.0, 0.0]
    assert abs(s.specular_weight_at(251) - 1 / 75) < 1e-12
    assert abs(s.specular_weight_at(280) - 30 / 75) < 1e-12
    assert [s.specular_weight_at(i) for i in (325, 326, 750)] == [1.0, 1.0, 1.0]
    abrupt = Schedule(iterations=750, specular_from=250, specular_fade=0.0)
    assert [abrupt.specular_weight_at(i) for i in (250, 251)] == [0.0, 1.0]


def test_a_scaled_budget_keeps_the_fade_at_its_place_in_the_run():
    cfg = TrainConfig.from_dict({"schedule": {"iterations": 600, "specular_from": 200, "specular_fade": 0.1}})
    doubled = scale_budget(cfg, 2.0).schedule
    assert doubled.specular_from == 400 and doubled.specular_fade == 0.1
    for i in (201, 230, 259, 261):
        assert abs(doubled.specular_weight_at(2 * i) - cfg.schedule.specular_weight_at(i)) < 1e-12


def test_the_trainer_fades_the_branch_in_over_the_first_full_stage_renders(tmp_path):
    scene = write_scene(tmp_path / "scene", views=6, width=32, height=24)
    cfg = TrainConfig.from_dict({
        "schedule": {"iterations": 10, "volume_until": 1, "specular_from": 3, "specular_fade": 0.35,
                     "densify_from": 100, "reset_every": 0, "log_every": 5, "checkpoint_every": 0},
        "model": {"env_height": 16, "env_width": 32, "env_levels": 3, "mlp_width": 32},
    })
    trainer = Trainer(scene, cfg, tmp_path / "run", progress=False, log=lambda m: None)
    weights, render = [], trainer.model.render
    def recording(camera, **kwargs):
        if torch.is_grad_enabled():
            weights.append((kwargs.get("stage"), kwargs.get("specular_weight", 1.0)))
        return render(camera, **kwargs)
    trainer.model.render = recording
    summary = trainer.train()
    full = [w for stage, w in weights[:10] if stage == "full"]
    assert [stage for stage, _ in weights[:10]] == [stage_at(i, cfg) for i in range(1, 11)]
    # 3.5 iterations of fade after iteration 3: weights 1/3.5, 2/3.5, 3/3.5, then the whole branch
    assert len(full) == 7 and 0.0 < full[0] < full[1] < full[2] < 1.0 and full[3:] == [1.0] * 4
    assert torch.isfinite(torch.tensor(summary["test_psnr"]))
