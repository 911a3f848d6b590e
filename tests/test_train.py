"""Trainer: learning, resume after a kill, stability, ablation switches, effects, export, errors."""

from __future__ import annotations

import copy
import json
import math
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml

from rtsplat.bench.toy_scene import write_scene
from rtsplat.errors import ConfigError
from rtsplat.model.checkpoint import CheckpointError, read_checkpoint
from rtsplat.model.export import read_surfel_ply
from rtsplat.model.rtmodel import STAGES
from rtsplat.train.optim import load_optimizer_state
from rtsplat.train.trainer import Trainer
from rtsplat.train.warmup import warm_up_kernels
from rtsplat.train_config import TrainConfig
from rtsplat.usage import machine_steal_seconds

SMALL_MODEL = {"env_height": 16, "env_width": 32, "env_levels": 3, "mlp_width": 32}


def config(iterations: int, **sections) -> TrainConfig:
    data = {
        "schedule": {"iterations": iterations, "volume_until": iterations // 6, "specular_from": iterations // 3,
                     "densify_from": iterations // 3, "densify_every": max(iterations // 6, 1), "reset_every": 0,
                     "log_every": 5, "checkpoint_every": 0, "separate_background_until": iterations // 2},
        "model": dict(SMALL_MODEL),
    }
    for key, value in sections.items():
        data.setdefault(key, {}).update(value) if isinstance(value, dict) else data.__setitem__(key, value)
    return TrainConfig.from_dict(data)


@pytest.fixture(scope="module")
def glass_scene(tmp_path_factory):
    return write_scene(tmp_path_factory.mktemp("glass"), views=10, width=48, height=36)


@pytest.fixture(scope="module")
def opaque_scene(tmp_path_factory):
    return write_scene(tmp_path_factory.mktemp("opaque"), views=6, width=32, height=24, with_pane=False)


def read_log(run: Path) -> list[dict]:
    return [json.loads(line) for line in (run / "train_log.jsonl").read_text().splitlines()]


@pytest.mark.slow
def test_training_reduces_loss_and_raises_heldout_psnr(tmp_path):
    scene = write_scene(tmp_path / "scene", views=12, width=64, height=48)
    trainer = Trainer(scene, config(300, effects={"near_reflection": "auto"}), tmp_path / "run", progress=False,
                      log=lambda m: None)
    before = trainer.evaluate()
    summary = trainer.train()
    log = read_log(tmp_path / "run")
    first = np.mean([r["loss"] for r in log[:3]])
    last = np.mean([r["loss"] for r in log[-3:]])
    assert last < 0.6 * first
    assert summary["test_psnr"] > before["test_psnr"] + 5.0
    assert summary["test_psnr_transparent"] > before["test_psnr_transparent"] + 3.0
    assert summary["effects"] == {"transmission": True, "specular": True, "near_reflection": True}
    assert summary["near_reflection"]["iteration"] == 101  # the planes were fitted as the reflections started


def test_a_rerun_with_the_same_seed_trains_the_same_model_and_another_seed_does_not(glass_scene, tmp_path):
    # through every stage (volume, subsurface, full model) and two density steps: an option's run minus the
    # default's is the option's effect only if a rerun of one config is exact
    def trained(name: str, seed: int) -> dict:
        trainer = Trainer(glass_scene, config(24, seed=seed, schedule={"eval_every": 0}), tmp_path / name,
                          progress=False, log=lambda m: None)
        trainer.train()
        return trainer.model.state_dict()

    first, again, other = trained("a", 0), trained("b", 0), trained("c", 1)
    assert first.keys() == again.keys()
    for key, value in first.items():
        assert torch.equal(value, again[key]), key
    means, other_means = first["surfels.means"], other["surfels.means"]
    assert means.shape != other_means.shape or not torch.equal(means, other_means)


def test_the_kernel_warm_up_draws_in_every_stage_and_leaves_the_training_as_it_was(glass_scene, tmp_path):
    # the warm-up renders a throwaway model before the run's clock starts, so that compiling the kernels is not
    # counted as training time; the run itself must train the same model with it as without it
    def trained(name: str, warm: bool) -> dict:
        trainer = Trainer(glass_scene, config(12, schedule={"eval_every": 0}), tmp_path / name, progress=False,
                          log=lambda m: None)
        if warm:
            rng = torch.get_rng_state()
            warmed = warm_up_kernels(trainer)
            assert torch.equal(torch.get_rng_state(), rng)  # the throwaway model drew from a forked generator
            assert set(warmed.drawn) == set(STAGES) and min(warmed.drawn.values()) > 0, warmed.drawn
            assert all(p.grad is None for p in trainer.model.parameters())
        stages = {trainer.step().stage for _ in range(12)}
        assert stages == set(STAGES)
        return trainer.model.state_dict()

    plain, warmed = trained("plain", False), trained("warmed", True)
    assert plain.keys() == warmed.keys()
    for key, value in plain.items():
        assert torch.equal(value, warmed[key]), key


def test_run_directory_contents_and_ply_export(glass_scene, tmp_path):
    run = tmp_path / "run"
    trainer = Trainer(glass_scene, config(12, schedule={"eval_every": 8}), run, progress=False, log=lambda m: None)
    summary = trainer.train()
    for name in ("config.json", "effects.json", "train_log.jsonl", "model.pt", "point_cloud.ply", "summary.json"):
        assert (run / name).is_file(), name
    log = read_log(run)
    # every log_every steps, every density operation (densify_from 4, every 2) and every evaluation
    iterations = [r["iteration"] for r in log]
    assert iterations == sorted(iterations) and {0, 5, 8, 10, 12} <= set(iterations)
    for r in log:
        if r["iteration"] not in (0, 5, 8, 10, 12):
            assert r["iteration"] in (4, 6) and set(r["density"]) <= {"cloned", "split", "pruned", "pruned_occupancy",
                                                                        "pruned_size", "reset"}
    # test-view PSNR of the initialisation and at the evaluation steps (accuracy-against-time curves)
    assert [r["iteration"] for r in log if "test_psnr" in r] == [0, 8, 12]
    assert log[-1]["test_psnr"] == pytest.approx(summary["test_psnr"])
    # the summary names the best evaluation and how far the final one is from it
    evaluated = [(r["test_psnr"], r["iteration"]) for r in log if "test_psnr" in r]
    assert summary["best_test_psnr"] == pytest.approx(max(p for p, _ in evaluated))
    assert (summary["best_test_psnr"], summary["best_test_psnr_iteration"]) in evaluated
    assert summary["final_minus_best_test_psnr"] == pytest.approx(summary["test_psnr"] - summary["best_test_psnr"])
    assert "test_psnr_transparent" in read_log(run)[-1]
    assert log[0]["seconds"] == 0 and all(r["seconds"] > 0 for r in log[1:])
    # CPU seconds of the same steps: counted as they run, never more than the threads' wall time
    cpu = [r["cpu_seconds"] for r in log]
    assert cpu == sorted(cpu) and cpu[0] == 0 and cpu[1] > 0
    assert cpu[-1] == pytest.approx(summary["train_cpu_seconds"], abs=1e-3)
    threads = summary["threads"]
    assert threads == torch.get_num_threads()
    assert 0 < summary["train_cpu_seconds"] <= summary["train_seconds"] * threads * 1.05 + 0.01
    # the summary rounds both times and the share to 1 ms / 0.001: the ratio of the rounded times
    # may differ from the share by what that rounding can move it
    share = summary["train_cpu_seconds"] / (summary["train_seconds"] * threads)
    rounding = share * (5e-4 / summary["train_cpu_seconds"] + 5e-4 / summary["train_seconds"]) + 5e-4
    assert summary["cpu_share"] == pytest.approx(share, abs=rounding + 1e-9)
    # the whole run (evaluations, pose fits, checkpoints too) holds the steps
    whole = summary["run_usage"]
    assert whole["wall_seconds"] >= summary["train_seconds"] and whole["cpu_seconds"] >= summary["train_cpu_seconds"]
    assert whole["other_busy_cores"] is None or 0 <= whole["other_busy_cores"] <= whole["cpus"]
    ply = read_surfel_ply(run / "point_cloud.ply")
    n = summary["surfels"]
    assert len(ply["x"]) == n == len(trainer.model.surfels)
    for key in ("x", "y", "z", "f_dc_0", "f_rest_44", "opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_3",
                "occupancy", "optical_opacity", "transmissivity", "roughness", "reflectance", "material_3"):
        assert key in ply, key
    effective = 1 / (1 + np.exp(-ply["opacity"]))
    np.testing.assert_allclose(effective, np.clip(ply["occupancy"] * ply["optical_opacity"], 1e-6, 1 - 1e-6),
                               rtol=1e-4, atol=1e-6)
    np.testing.assert_allclose(ply["x"], trainer.model.surfels.means[:, 0].detach().numpy())


def test_effects_auto_on_a_scene_without_glass(opaque_scene, tmp_path):
    trainer = Trainer(opaque_scene, config(6), tmp_path / "run", progress=False, log=lambda m: None)
    assert trainer.effects.transmission is False
    assert not trainer.model.uses_opacity and not trainer.model.uses_scatter
    trainer.train()
    saved = json.loads((tmp_path / "run" / "effects.json").read_text())
    assert saved["transmission"] is False and "no transparent pixel" in saved["reasons"]["transmission"]
    # the test machine has no LPIPS weights (tests/test_lpips.py covers loading): the run says so
    if trainer.perceptual is None:
        assert saved["perceptual"].startswith("off: LPIPS-VGG weights not found")
    assert trainer.effects.specular is True and "given in the config" in saved["reasons"]["specular"]
    # one opacity: the optical opacity parameter never receives a gradient
    assert trainer.model.surfels.opacity_logit.grad is None or trainer.model.surfels.opacity_logit.grad.abs().max() == 0


def test_effects_auto_trains_plain_2dgs_without_glass_or_requested_reflections(tmp_path):
    scene = write_scene(tmp_path / "scene", views=5, width=32, height=24, with_pane=False, roi_source="estimated")
    trainer = Trainer(scene, config(4), tmp_path / "run", progress=False, log=lambda m: None)
    assert (trainer.effects.transmission, trainer.effects.specular) == (False, False)
    assert trainer.model.env is None and trainer.model.specular_net is None
    trainer.train()
    reasons = json.loads((tmp_path / "run" / "effects.json").read_text())["reasons"]
    assert "no region of interest given" in reasons["specular"]


def test_mask_loss_switch(glass_scene, tmp_path):
    on = Trainer(glass_scene, config(5), tmp_path / "on", progress=False, log=lambda m: None)
    on.train()
    off = Trainer(glass_scene, config(5, ablations={"mask_loss": False}), tmp_path / "off", progress=False,
                  log=lambda m: None)
    off.train()
    assert "loss_mask" in read_log(tmp_path / "on")[-1]
    assert "loss_mask" not in read_log(tmp_path / "off")[-1]


def test_mask_loss_asks_a_background_pixel_for_a_surface_only_with_the_paper_target():
    """Pixels the mask does not mark: the paper's target 1 pulls the surface alpha up even where the
    view sees the background; the surface target leaves an opaque surface's alpha alone and asks a
    half-clear one for opacity. See-through pixels get the same loss either way."""
    from rtsplat.train.losses import transparent_mask_loss

    alpha = torch.tensor([0.02, 0.3, 0.9], dtype=torch.float64).reshape(1, 3, 1).requires_grad_(True)
    opacity = torch.tensor([1.0, 1.0, 0.5], dtype=torch.float64).reshape(1, 3, 1).requires_grad_(True)
    clear = torch.zeros(1, 3, 1, dtype=torch.float64)

    def grads(surface_alpha):
        loss = transparent_mask_loss(alpha * opacity, clear, surface_alpha)
        return torch.autograd.grad(loss, (alpha, opacity))

    g_alpha, _ = grads(None)
    assert (g_alpha[0, :, 0] < 0).all()  # descent grows a surface on every pixel, the background's too
    g_alpha, g_opacity = grads(alpha)
    assert g_alpha[0, :2, 0].abs().max() < 1e-12  # opaque surfaces: nothing to ask
    assert g_opacity[0, 2, 0] < 0 and g_alpha[0, 2, 0] < 0  # half-clear: more opacity (its alpha follows)
    see_through = torch.ones(1, 3, 1, dtype=torch.float64)
    assert torch.equal(transparent_mask_loss(alpha * opacity, see_through),
                       transparent_mask_loss(alpha * opacity, see_through, alpha))


def test_mask_coverage_loss_asks_marked_pixels_for_a_surface_and_leaves_the_others_alone():
    from rtsplat.train.losses import mask_coverage_loss

    alpha = torch.tensor([0.0, 0.4, 1.0, 0.4], dtype=torch.float64).reshape(1, 4, 1).requires_grad_(True)
    mask = torch.tensor([1.0, 1.0, 1.0, 0.0], dtype=torch.float64).reshape(1, 4, 1)
    loss = mask_coverage_loss(alpha, mask)
    (grad,) = torch.autograd.grad(loss, alpha)
    assert torch.isfinite(loss) and torch.isfinite(grad).all()  # alpha exactly 0 and exactly 1
    assert math.isclose(float(loss.detach()), -(math.log(1e-6) + math.log(0.4) + math.log(1 - 1e-6)) / 4)
    assert grad[0, 1, 0] < 0  # descent raises a marked pixel's coverage
    assert grad[0, 2, 0] == 0 and grad[0, 3, 0] == 0  # covered already; not marked
    assert mask_coverage_loss(alpha, torch.zeros_like(mask)) == 0


def _renders_after_training_with(term: str, weight: float, cfg, scene, run_dir):
    """Train ``cfg`` (whose ``losses.<term>_weight`` is ``weight``) on ``scene``; check that the log has the term
    exactly when it weighs, and return (render, mask) for every training view of the trained model."""
    trainer = Trainer(scene, cfg, run_dir, progress=False, log=lambda m: None)
    trainer.train()
    assert (f"loss_{term}" in read_log(run_dir)[-1]) == (weight > 0)
    with torch.no_grad():
        return [(trainer.model.render(camera, raster_settings=cfg.raster, backend=cfg.backend), mask)
                for camera, mask in zip(trainer.train_views.cameras, trainer.train_views.masks, strict=True)]


def test_the_mask_coverage_term_raises_the_glass_coverage(glass_scene, tmp_path):
    """With the term the toy pane's marked pixels end up covered more (surface alpha), and the log shows it."""
    def coverage(weight: float) -> float:
        cfg = config(12, losses={"mask_coverage_weight": weight})
        renders = _renders_after_training_with("mask_coverage", weight, cfg, glass_scene, tmp_path / f"w{weight}")
        return float(torch.cat([result.layers["alpha"][mask > 0.5] for result, mask in renders]).mean())

    assert coverage(1.0) > coverage(0.0) + 0.01


def test_the_reflection_prior_dims_the_reflection_layer(glass_scene, tmp_path):
    def mean_reflection(weight: float) -> float:
        cfg = config(16, losses={"reflection_weight": weight}, schedule={"volume_until": 2, "specular_from": 4})
        renders = _renders_after_training_with("reflection", weight, cfg, glass_scene, tmp_path / f"w{weight}")
        return float(torch.stack([result.layers["reflection"].mean() for result, _ in renders]).mean())

    free, dimmed = mean_reflection(0.0), mean_reflection(5.0)
    assert free > 0.01  # the toy scene's pane does get a reflection without the prior
    assert dimmed < 0.7 * free


def test_shading_smoothness_sees_only_pairs_inside_the_mask_and_stays_finite():
    from rtsplat.train.losses import shading_smoothness

    H, W = 6, 8
    alpha = torch.ones(H, W, 1, dtype=torch.float64)
    values = torch.zeros(H, W, 2, dtype=torch.float64)
    values[:, 4:] = 1.0  # two materials, the edge between columns 3 and 4
    mask = torch.zeros(H, W, 1, dtype=torch.float64)
    mask[:, :4] = 1.0
    assert shading_smoothness(values * alpha, alpha, mask) == 0  # the edge lies outside the mask
    mask[:] = 1.0
    loss = shading_smoothness(values * alpha, alpha, mask)
    pairs = H * (W - 1) + (H - 1) * W
    assert torch.isclose(loss, torch.tensor(H / pairs, dtype=torch.float64))  # H pairs differ by 1
    assert shading_smoothness(values * alpha, alpha, torch.zeros_like(mask)) == 0  # no mask, no pairs
    # hard cases: no surface (alpha exactly 0), a surface from nothing to fully opaque; the gradient stays
    # bounded where the division by alpha would not
    alpha = torch.rand(H, W, 1, dtype=torch.float64)
    alpha[0] = 0.0
    alpha[1] = 1e-12
    alpha[2] = 1.0
    shading = (torch.rand(H, W, 2, dtype=torch.float64) * alpha).requires_grad_(True)
    loss = shading_smoothness(shading, alpha, mask)
    (grad,) = torch.autograd.grad(loss, shading)
    assert torch.isfinite(loss) and torch.isfinite(grad).all()
    assert grad.abs().max() < 1.0  # unweighted, the rows at alpha 1e-12 would get gradients near 1e12


def test_the_shading_prior_evens_the_panes_reflectance(glass_scene, tmp_path):
    """The toy pane is one material: with the prior its reflectance varies less across the pane's pixels."""

    def spread(weight: float) -> float:
        cfg = config(24, losses={"shading_smoothness_weight": weight},
                     schedule={"volume_until": 2, "specular_from": 4}, lr={"reflectance": 0.05})
        values = []
        for result, mask in _renders_after_training_with("shading_smoothness", weight, cfg, glass_scene,
                                                         tmp_path / f"w{weight}"):
            raster = result.raster
            inside = (mask[..., 0] > 0.5) & (raster.alpha[..., 0] > 0.5)
            values.append((result.gbuffer["reflectance"] / raster.alpha)[inside])
        return float(torch.cat(values).std())

    free, held = spread(0.0), spread(5.0)
    assert free > 0
    assert held < 0.8 * free


def test_separate_optimization_freezes_the_background(glass_scene, tmp_path):
    cfg = config(20, ablations={"joint_optimization": False})
    trainer = Trainer(glass_scene, cfg, tmp_path / "run", progress=False, log=lambda m: None)
    n_start = len(trainer.model.surfels)  # the initial set: SfM points x densify.initial_copies
    assert n_start == trainer.points[0].shape[0] * cfg.densify.initial_copies
    while trainer.iteration < 11:  # background phase is iterations 1..10
        trainer.step()
    frozen = trainer.frozen.clone()
    assert frozen.sum() >= n_start and (~frozen).sum() == n_start  # a fresh initial set for the glass
    before = {k: v.detach()[frozen].clone() for k, v in trainer.model.surfels.tensors().items()}
    while trainer.iteration < 20:
        trainer.step()
    for name, value in before.items():
        assert torch.equal(getattr(trainer.model.surfels, name).detach()[trainer.frozen], value), name


def test_resume_after_kill_matches_an_uninterrupted_run(glass_scene, tmp_path):
    cfg = config(40, schedule={"checkpoint_every": 10, "densify_from": 12, "densify_every": 8})
    straight = Trainer(glass_scene, cfg, tmp_path / "straight", progress=False, log=lambda m: None)
    straight.train()

    cfg_file = tmp_path / "cfg.yaml"
    cfg_file.write_text(yaml.safe_dump({"train": cfg.to_dict() | {"raster": {}}}))
    run = tmp_path / "killed"
    proc = subprocess.Popen(
        [sys.executable, "-m", "rtsplat.cli", "train", "--data", str(glass_scene.root), "--out", str(run),
         "--config", str(cfg_file), "--quiet"],
        stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
    )
    checkpoint = run / "checkpoints" / "last.pt"
    deadline = time.time() + 300
    while not checkpoint.exists() and proc.poll() is None and time.time() < deadline:
        time.sleep(0.05)
    assert proc.poll() is None, f"training ended before it could be killed: {proc.stderr.read()}"
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    assert not (run / "summary.json").exists()  # a killed run does not look finished
    killed = read_checkpoint(checkpoint).training
    killed_at = killed["iteration"]
    assert 10 <= killed_at < 40

    resumed = Trainer(glass_scene, cfg, run, progress=False, log=lambda m: None)
    summary = resumed.train(resume=True)
    # the time of the killed part is in the resumed run's, CPU seconds as well as wall seconds
    assert 0 < killed["cpu_elapsed"] < summary["train_cpu_seconds"]
    assert killed["run_usage"]["wall_seconds"] < summary["run_usage"]["wall_seconds"]
    a, b = straight.model.surfels.tensors(), resumed.model.surfels.tensors()
    assert len(straight.model.surfels) == len(resumed.model.surfels)
    for name in a:
        torch.testing.assert_close(b[name], a[name], rtol=1e-4, atol=1e-5, msg=name)
    assert [r["iteration"] for r in read_log(run)] == [r["iteration"] for r in read_log(tmp_path / "straight")]


@pytest.mark.slow
@pytest.mark.parametrize("occupancy,opacity", [(0.0, 1.0), (1.0, 0.0)])
def test_high_learning_rates_and_extreme_initialisation_stay_finite(tmp_path, occupancy, opacity):
    scene = write_scene(tmp_path / "scene", views=6, width=24, height=18)
    cfg = config(500, model={"occupancy_init": occupancy, "opacity_init": opacity},
                 schedule={"reset_every": 100, "densify_every": 50})
    cfg.lr = cfg.lr.scaled(10.0)
    trainer = Trainer(scene, cfg, tmp_path / "run", progress=False, log=lambda m: None)
    trainer.train()
    for name, value in trainer.model.surfels.tensors().items():
        assert torch.isfinite(value).all(), name
    for name, value in trainer.model.named_parameters():
        assert torch.isfinite(value).all(), name
    assert all(np.isfinite(r["loss"]) for r in read_log(tmp_path / "run"))


def test_a_truncated_checkpoint_gives_a_clear_error(glass_scene, tmp_path):
    run = tmp_path / "run"
    (run / "checkpoints").mkdir(parents=True)
    (run / "checkpoints" / "last.pt").write_bytes(b"PK\x03\x04 truncated")
    trainer = Trainer(glass_scene, config(3), run, progress=False, log=lambda m: None)
    with pytest.raises(CheckpointError, match="cannot read checkpoint.*delete it"):
        trainer.train(resume=True)


def test_the_separate_background_phase_follows_the_run_length_and_must_end_before_it():
    ablated = {"ablations": {"joint_optimization": False}}
    for iterations in (600, 2400):
        cfg = TrainConfig.from_dict({**ablated, "schedule": {"iterations": iterations}}).validate()
        assert cfg.schedule.background_phase_end() == iterations // 2
    long_phase = {**ablated, "schedule": {"iterations": 600, "separate_background_until": 600}}
    with pytest.raises(ConfigError, match="separate_background_until.*must be below.*iterations"):
        TrainConfig.from_dict(long_phase).validate()
    # the joint model has no such phase, so the same count is not an error there
    TrainConfig.from_dict({"schedule": long_phase["schedule"]}).validate()


def test_unknown_config_key_is_named(glass_scene, tmp_path):
    with pytest.raises(ConfigError, match="train.schedule.iteration"):
        TrainConfig.from_dict({"schedule": {"iteration": 5}})
    bad = tmp_path / "bad.yaml"
    bad.write_text("train:\n  ablations:\n    gatting: false\n")
    result = subprocess.run(
        [sys.executable, "-m", "rtsplat.cli", "train", "--data", str(glass_scene.root), "--out",
         str(tmp_path / "run"), "--config", str(bad)], capture_output=True, text=True,
    )
    assert result.returncode == 1
    assert "train.ablations.gatting" in result.stderr and "valid keys" in result.stderr
    assert not (tmp_path / "run").exists()


def test_train_downsample_trains_small_and_evaluates_at_the_prepared_size(glass_scene, tmp_path):
    from rtsplat.io.images import area_downsample

    trainer = Trainer(glass_scene, config(6, train_downsample=2), tmp_path / "run", progress=False, log=lambda m: None)
    full = glass_scene.train_cameras[0].to_camera()
    small = trainer.train_views.cameras[0]
    assert (small.width, small.height) == (full.width // 2, full.height // 2)
    image = glass_scene.load_image(trainer.train_views.names[0])
    np.testing.assert_allclose(trainer.train_views.images[0].numpy(), area_downsample(image, 2))
    # the same world point lands at half the pixel coordinates (pixel corners at integers)
    point = torch.tensor([0.1, -0.05, 0.2], dtype=full.K.dtype)
    def pixel(cam):
        p = cam.world_to_camera[:3, :3] @ point + cam.world_to_camera[:3, 3]
        q = cam.K @ p
        return q[:2] / q[2]
    torch.testing.assert_close(pixel(small), pixel(full) / 2)
    assert trainer.test_views.images[0].shape[:2] == (full.height, full.width)
    summary = trainer.train()
    assert np.isfinite(summary["test_psnr"])
    with pytest.raises(ConfigError, match="train_downsample"):
        config(6, train_downsample=0).validate()


def test_progressive_resolution_renders_each_step_at_its_levels_size(glass_scene, tmp_path):
    # coarse_downsample 4 up to iteration 8 of 12: iterations 1-4 at a quarter, 5-7 at half, 8-12 at full size
    cfg = config(12, schedule={"coarse_downsample": 4, "full_resolution_from": 8, "eval_every": 0})
    trainer = Trainer(glass_scene, cfg, tmp_path / "run", progress=False, log=lambda m: None)
    full = glass_scene.train_cameras[0].to_camera()
    sizes, render = [], trainer.model.render
    def recording(camera, **kwargs):
        sizes.append((camera.width, camera.height))
        return render(camera, **kwargs)
    trainer.model.render = recording
    summary = trainer.train()
    quarter, half, whole = ((full.width // f, full.height // f) for f in (4, 2, 1))
    assert sizes[:12] == [quarter] * 4 + [half] * 3 + [whole] * 5
    # the coarse levels are the training views box-filtered, with the same names and order
    level = trainer.train_levels[4]
    assert level.names == trainer.train_views.names
    from rtsplat.io.images import area_downsample
    np.testing.assert_allclose(level.images[0].numpy(), area_downsample(glass_scene.load_image(level.names[0]), 4))
    logged = {r["iteration"]: r.get("downsample") for r in read_log(tmp_path / "run")}
    assert logged[5] == 2 and logged[10] == 1
    assert np.isfinite(summary["test_psnr"])


def test_progressive_resolution_refuses_bad_factors(glass_scene, tmp_path):
    with pytest.raises(ConfigError, match="power of two"):
        config(6, schedule={"coarse_downsample": 3, "full_resolution_from": 4}).validate()
    # 36-pixel-high views at 1/8 would be 4 pixels high
    from rtsplat.errors import PipelineError
    with pytest.raises(PipelineError, match="coarse_downsample 8 leaves training views of 4 pixels"):
        Trainer(glass_scene, config(6, schedule={"coarse_downsample": 8, "full_resolution_from": 4}), tmp_path / "r",
                progress=False, log=lambda m: None)


def test_sh_degree_grows_every_sh_degree_every_iterations(glass_scene, tmp_path):
    trainer = Trainer(glass_scene, config(5, schedule={"sh_degree_every": 2}), tmp_path / "run", progress=False,
                      log=lambda m: None)
    degrees, render = [], trainer.model.render

    def recording_render(*args, **kwargs):
        degrees.append(kwargs["sh_degree"])
        return render(*args, **kwargs)

    trainer.model.render = recording_render
    for _ in range(5):
        trainer.step()
    assert degrees == [0, 1, 1, 2, 2]
    assert TrainConfig().schedule.sh_degree_every == 1000


def test_train_cli_reads_a_method_of_the_pipeline_config_like_the_workflow(tmp_path):
    import argparse

    from rtsplat.config import load_config, train_json
    from rtsplat.train.cli import add_arguments, trainer_config_from_args

    pipeline = {"methods": {"rtsplat": {}, "2dgs": {"effects": {"transmission": "off"}, "budget": 2}},
                "defaults": {"train": {"iterations": 50, "options": {"schedule": {"log_every": 7}}}},
                "overrides": {"sedan": {"train": {"backend": "reference"}}}}
    (tmp_path / "config.yaml").write_text(yaml.safe_dump(pipeline))
    (tmp_path / "tree.yaml").write_text("train:\n  seed: 4\n  schedule: {iterations: 9}\n")
    parser = argparse.ArgumentParser()
    add_arguments(parser)

    def read(*flags):
        return trainer_config_from_args(parser.parse_args(["--data", "d", "--out", "o", *flags]))

    cfg = load_config(tmp_path / "config.yaml")
    sedan = read("--config", str(tmp_path / "config.yaml"), "--scene", "sedan", "--method", "2dgs")
    assert sedan == TrainConfig.from_dict(json.loads(train_json(cfg, "sedan", "2dgs", quote=False)))
    assert (sedan.schedule.iterations, sedan.schedule.log_every, sedan.backend) == (100, 7, "reference")
    assert read("--config", str(tmp_path / "config.yaml")).effects.transmission == "auto"  # rtsplat, defaults
    tree = read("--config", str(tmp_path / "tree.yaml"))
    assert (tree.seed, tree.schedule.iterations) == (4, 9)
    assert read("--config-json", '{"schedule": {"iterations": 3}}').schedule.iterations == 3
    with pytest.raises(ConfigError, match="train.schedule.iteratons"):
        read("--config-json", '{"schedule": {"iteratons": 3}}')
    with pytest.raises(ConfigError, match="--scene"):
        read("--config", str(tmp_path / "tree.yaml"), "--scene", "sedan")


def test_surfels_start_on_the_transparent_surface_only_with_transmission(tmp_path):
    from rtsplat.raster.projection import quat_to_rotmat

    scene = write_scene(tmp_path / "scene", views=5, width=32, height=24)
    xyz = np.array([[0.0, 0.0, 0.0], [0.1, 0.0, 0.0], [0.0, 0.1, 0.0], [0.1, 0.1, 0.0], [0.05, 0.05, 0.0]])
    normal = np.tile([[0.0, 0.6, 0.8]], (5, 1))
    np.savez(tmp_path / "scene" / "transparent_surface.npz", xyz=xyz, normal=normal)
    n_points = scene.load_points()[0].shape[0] * config(4).densify.initial_copies
    rt = Trainer(scene, config(4), tmp_path / "rt", progress=False, log=lambda m: None)
    surfels = rt.model.surfels
    assert len(surfels) == n_points + 5
    seeds = slice(n_points, None)
    assert torch.allclose(surfels.means[seeds].detach(), torch.as_tensor(xyz, dtype=torch.float32))
    R = quat_to_rotmat(surfels.quats[seeds].detach())
    assert torch.allclose(R[:, :, 2], torch.tensor([0.0, 0.6, 0.8]).expand(5, 3), atol=1e-6)
    assert torch.allclose(surfels.opacity[seeds], torch.tensor(0.1)) and (surfels.transmissivity[seeds] > 0.85).all()
    # the seeds' scale: transparent_surface_scale times the RMS distance to their 3 nearest seeds
    nearest = np.sort(np.linalg.norm(xyz[:, None] - xyz[None], axis=-1), 1)[:, 1:4]
    spacing = np.sqrt((nearest ** 2).mean(1))[:, None]
    factor = config(4).transparent_surface_scale
    assert np.allclose(surfels.scales[seeds].detach().numpy(), factor * spacing, rtol=1e-5)
    halved = Trainer(scene, config(4, transparent_surface_scale=factor / 2), tmp_path / "halved", progress=False,
                     log=lambda m: None)
    assert np.allclose(halved.model.surfels.scales[seeds].detach().numpy(), factor / 2 * spacing, rtol=1e-5)
    assert torch.equal(halved.model.surfels.scales[:n_points], surfels.scales[:n_points])  # the SfM surfels' stay
    rt.train()  # the seeded model trains
    plain = Trainer(scene, config(4, effects={"transmission": "off"}), tmp_path / "2dgs", progress=False,
                    log=lambda m: None)
    assert len(plain.model.surfels) == n_points
    off = Trainer(scene, config(4, seed_transparent_surface=False), tmp_path / "off", progress=False,
                  log=lambda m: None)
    assert len(off.model.surfels) == n_points


def _train_cli(*args: str) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "rtsplat.cli", "train", *args, "--quiet"],
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)


def _cli_with_checkpoint_dir(glass_scene, tmp_path, cfg):
    """`rtsplat train` arguments for ``cfg`` (written as a config file) with the run in runs/rtsplat and its
    checkpoint folder beside it in checkpoints/rtsplat, as the workflow lays them out: (args, run, kept)."""
    cfg_file = tmp_path / "cfg.yaml"
    cfg_file.write_text(yaml.safe_dump({"train": cfg.to_dict() | {"raster": {}}}))
    run, kept = tmp_path / "runs" / "rtsplat", tmp_path / "checkpoints" / "rtsplat"
    args = ("--data", str(glass_scene.root), "--out", str(run), "--config", str(cfg_file),
            "--checkpoint-dir", str(kept))
    return args, run, kept


def test_checkpoint_dir_outlives_a_deleted_run_folder_and_training_resumes_from_it(glass_scene, tmp_path):
    """What a training job killed under Snakemake goes through: the run folder is deleted, the checkpoint
    folder beside it is not, and the next job resumes at the checkpoint's iteration with the log kept."""
    cfg = config(40, schedule={"checkpoint_every": 10, "densify_from": 1000, "eval_every": 0})
    args, run, kept = _cli_with_checkpoint_dir(glass_scene, tmp_path, cfg)
    proc = _train_cli(*args)
    deadline = time.time() + 300
    while not (kept / "last.pt").exists() and proc.poll() is None and time.time() < deadline:
        time.sleep(0.05)
    assert proc.poll() is None, f"training ended before it could be killed: {proc.stderr.read()}"
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    assert not (run / "checkpoints").exists()  # the checkpoint is written to --checkpoint-dir only
    shutil.rmtree(run)  # what Snakemake does with the output folder of a failed job
    killed_at = read_checkpoint(kept / "last.pt").training["iteration"]
    assert 10 <= killed_at < 40 and killed_at % 10 == 0

    proc = _train_cli(*args)
    _, err = proc.communicate(timeout=600)
    assert proc.returncode == 0, err
    assert f"resumed from {kept / 'last.pt'} at iteration {killed_at}" in err
    summary = json.loads((run / "summary.json").read_text())
    assert summary["iterations"] == 40
    logged = [r["iteration"] for r in read_log(run)]
    # the lines up to the checkpoint come from the first job (restored from the kept copy), once each
    assert logged == list(range(5, 41, 5))
    assert not kept.exists()  # a finished run removes its checkpoint folder


def test_checkpoint_dir_keeps_only_a_checkpoint_of_the_same_data_and_config(glass_scene, tmp_path):
    from rtsplat.errors import PipelineError
    from rtsplat.train.cli import claim_checkpoint_dir

    data = Path(shutil.copytree(glass_scene.root, tmp_path / "prepared"))
    run, kept = tmp_path / "run", tmp_path / "kept"
    messages: list[str] = []
    claim_checkpoint_dir(kept, run, data, config(20), messages.append)
    (kept / "last.pt").write_bytes(b"state")
    claim_checkpoint_dir(kept, run, data, config(20), messages.append)
    assert (kept / "last.pt").exists() and messages == []
    claim_checkpoint_dir(kept, run, data, config(20, seed=3), messages.append)
    assert not (kept / "last.pt").exists() and "training starts at iteration 0" in messages[0]
    (kept / "last.pt").write_bytes(b"state")
    os.utime(data / "scene.json", ns=(0, 0))  # a prepared scene written again
    claim_checkpoint_dir(kept, run, data, config(20, seed=3), messages.append)
    assert not (kept / "last.pt").exists() and len(messages) == 2
    with pytest.raises(PipelineError, match="--checkpoint-dir is, contains or lies inside --out"):
        claim_checkpoint_dir(run / "checkpoints", run, data, config(20), messages.append)


def test_the_median_depth_gives_a_pane_its_own_normal_where_the_expected_depth_mixes_in_what_is_behind(
        glass_scene, tmp_path, monkeypatch):
    """A tilted pane holding most of the surface weight in front of a wall: the normals of the median
    depth are the pane's, those of the expected depth are bent towards the wall's. The trainer's
    ``losses.normal_depth`` picks which one the normal term uses."""
    from raster_scenes import facing_quat, small_camera

    from rtsplat.raster import Surfels, rasterize
    from rtsplat.train import losses

    camera = small_camera(32, 24, eye=(0.0, -3.0, 0.0))
    pane_normal = torch.nn.functional.normalize(torch.tensor([0.5, -1.0, 0.0], dtype=torch.float64), dim=0)
    surfels = Surfels(
        means=torch.tensor([[0.0, -1.0, 0.0], [0.0, 1.5, 0.0]], dtype=torch.float64),
        quats=torch.stack([facing_quat(pane_normal), facing_quat((0.0, -1.0, 0.0))]),
        scales=torch.full((2, 2), 6.0, dtype=torch.float64),
        occupancy=torch.tensor([0.7, 1.0], dtype=torch.float64), opacity=torch.ones(2, dtype=torch.float64),
        features=torch.zeros(2, 1, dtype=torch.float64), colors=torch.zeros(2, 3, dtype=torch.float64),
    )
    out = rasterize(surfels, camera, backend="reference")
    inner = (slice(4, -4), slice(4, -4))
    assert float(out.alpha.detach()[inner].min()) > 0.95

    def degrees_off_the_pane(depth):
        n = losses.depth_normals(depth, camera)[inner]
        return torch.rad2deg(torch.arccos((n @ pane_normal).abs().clamp(max=1.0)))

    assert float(degrees_off_the_pane(out.depth_median).max()) < 0.5
    assert float(degrees_off_the_pane(out.depth).median()) > 5.0

    original = losses.normal_consistency
    for choice, field in (("median", "depth_median"), ("expected", "depth")):
        cfg = config(3, losses={"normal_depth": choice})
        trainer = Trainer(glass_scene, cfg, tmp_path / choice, progress=False, log=lambda m: None)
        renders, used = [], []
        render = trainer.model.render

        def remember(*args, render=render, renders=renders, **kwargs):
            renders.append(render(*args, **kwargs))
            return renders[-1]

        def spy(normal, depth, alpha, cam, renders=renders, used=used, field=field):
            used.append(depth is getattr(renders[-1].raster, field))
            return original(normal, depth, alpha, cam)

        monkeypatch.setattr(trainer.model, "render", remember)
        monkeypatch.setattr(losses, "normal_consistency", spy)
        trainer.train()
        assert used and all(used)


def test_point_normals_start_each_surfel_and_its_copies_flat_on_the_point_clouds_surface(glass_scene, tmp_path):
    from rtsplat.model.surfels import point_cloud_normals
    from rtsplat.raster.projection import quat_to_rotmat

    def initial_normals(orientation):
        cfg = config(2, densify={"initial_orientation": orientation, "initial_copies": 3})
        trainer = Trainer(glass_scene, cfg, tmp_path / orientation, progress=False, log=lambda m: None)
        n_points = trainer.points[0].shape[0]
        quats = trainer.model.surfels.quats.detach()[: 3 * n_points]
        return quat_to_rotmat(torch.nn.functional.normalize(quats, dim=-1))[:, :, 2], trainer.points[0]

    normals, points = initial_normals("point_normals")
    expected = point_cloud_normals(points).repeat(3, 1)
    assert float((normals * expected).sum(-1).abs().min()) > 1 - 1e-5
    random_normals, _ = initial_normals("random")
    assert float((random_normals * expected).sum(-1).abs().median()) < 0.9


def test_mirror_planes_are_fitted_once_as_the_reflections_start_and_come_back_on_resume(glass_scene, tmp_path):
    cfg = config(12, effects={"near_reflection": "on"})
    trainer = Trainer(glass_scene, cfg, tmp_path / "run", progress=False, log=lambda m: None)
    fits = []
    fit = trainer.fit_mirror_planes
    trainer.fit_mirror_planes = lambda: fits.append(trainer.iteration) or fit()
    for _ in range(6):
        trainer.step()
    assert fits == [cfg.schedule.specular_from + 1]  # once, at the first iteration of the full model
    near = trainer.near_fit
    assert near["points"] > 100 and near["planes"] >= 1 and near["on"] and near["seconds"] >= 0
    assert 0.0 <= near["coverage"] <= 1.0 and f"covers {near['coverage']:.0%}" in near["reason"]
    assert trainer.model.uses_near_reflection
    normal = trainer.model.mirror_planes[0, :3]
    assert abs(float(normal.norm()) - 1.0) < 1e-5
    path = trainer.save_checkpoint()
    resumed = Trainer(glass_scene, cfg, tmp_path / "run", progress=False, log=lambda m: None)
    resumed.load_checkpoint(path)
    assert resumed.near_fit == near
    torch.testing.assert_close(resumed.model.mirror_planes, trainer.model.mirror_planes)
    refits = []
    resumed.fit_mirror_planes = lambda: refits.append(resumed.iteration)
    resumed.step()
    assert refits == []
    # the default config: the near term is off, so no plane is fitted and no mirrored pass runs
    off = Trainer(glass_scene, config(12), tmp_path / "off", progress=False, log=lambda m: None)
    off_fits = []
    off.fit_mirror_planes = lambda: off_fits.append(off.iteration)
    for _ in range(6):
        off.step()
    assert off_fits == [] and off.near_fit is None and not off.model.uses_near_reflection
    assert off.model.effects.transmission and off.model.effects.specular


def test_mirror_planes_learnt_from_the_images_move_stay_planes_and_resume(glass_scene, tmp_path):
    lr = {"mirror_plane_rotation": 1e-3, "mirror_plane_shift": 1e-3}
    cfg = config(12, effects={"near_reflection": "on"}, lr=lr)
    trainer = Trainer(glass_scene, cfg, tmp_path / "run", progress=False, log=lambda m: None)
    for _ in range(cfg.schedule.specular_from):
        trainer.step()
    assert trainer.plane_refinement is None  # nothing to refine before the planes are fitted
    trainer.step()
    fitted = trainer.near_fit and trainer.plane_refinement.fitted.clone()
    assert trainer.model.uses_near_reflection and fitted is not None
    for _ in range(4):
        trainer.step()
    planes = trainer.model.mirror_planes
    assert not torch.equal(planes, fitted.to(planes))  # the image loss moved them
    torch.testing.assert_close(planes[:, :3].norm(dim=-1), torch.ones(planes.shape[0]))
    assert float((planes[:, :3] * planes[:, 6:9]).sum(-1).abs().max()) < 1e-5  # the rectangle turned with them
    torch.testing.assert_close(planes[:, 9:], fitted[:, 9:].to(planes))  # extents and thickness kept
    moved = trainer.plane_refinement.moved()
    # five Adam steps of 1e-3 rad at most (to rounding); a shift of at most 5e-3 x the extent
    assert any(m["degrees"] > 0 for m in moved) and all(m["degrees"] <= math.degrees(5e-3) + 1e-3 for m in moved)
    assert all(abs(m["shift"]) <= 5e-3 * trainer.extent * 1.001 for m in moved)
    path = trainer.save_checkpoint()
    resumed = Trainer(glass_scene, cfg, tmp_path / "run", progress=False, log=lambda m: None)
    resumed.load_checkpoint(path)
    torch.testing.assert_close(resumed.plane_refinement.fitted, trainer.plane_refinement.fitted)
    torch.testing.assert_close(resumed.model.mirror_planes, trainer.model.mirror_planes)
    assert resumed.plane_refinement.moved() == moved
    # off by default: the fitted planes are kept as they are
    still = Trainer(glass_scene, config(12, effects={"near_reflection": "on"}), tmp_path / "still", progress=False,
                    log=lambda m: None)
    for _ in range(cfg.schedule.specular_from + 3):
        still.step()
    assert still.plane_refinement is None and still.model.uses_near_reflection


SPIN = "while True: pass\n"


def _cpu_seconds_of(pid: int) -> float:
    """utime + stime of a process from /proc/<pid>/stat (after the command name, fields 14 and 15)."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


@pytest.mark.skipif(not Path("/proc/stat").is_file(), reason="no /proc (not Linux)")
def test_a_run_with_a_busy_neighbour_records_the_cpu_time_the_neighbour_used(glass_scene, tmp_path):
    """A process spinning beside the training: every CPU second it used while the run's clock ran is in
    the run's other_busy_core_seconds (the machine's busy time minus the training's own)."""
    spinner = subprocess.Popen([sys.executable, "-c", SPIN])
    window = {}

    class Watched(Trainer):
        def run_usage(self):  # the run's clock is read here; the summary's reading is the last one
            window["end"] = _cpu_seconds_of(spinner.pid)
            window["steal_end"] = machine_steal_seconds()
            return super().run_usage()

    def log(message: str) -> None:
        if message.startswith("effects:") and "start" not in window:  # logged after train() started its clock
            window["start"] = _cpu_seconds_of(spinner.pid)
            window["steal_start"] = machine_steal_seconds()

    try:
        summary = Watched(glass_scene, config(12), tmp_path / "run", progress=False, log=log).train()
    finally:
        spinner.kill()
        spinner.wait()
    neighbour = window["end"] - window["start"]
    assert neighbour > 0.1  # the neighbour did run beside the training
    run = summary["run_usage"]
    # clock ticks: a few hundredths of a second; on a virtual machine the neighbour's own CPU time can include
    # time the hypervisor stole, which /proc/stat counts as steal, not as busy (rtsplat/usage.py); and with both
    # cores contended this machine's /proc/stat showed 2-5% less busy time than the two processes' own clocks
    steal = window["steal_end"] - window["steal_start"]
    assert run["other_busy_core_seconds"] >= 0.94 * neighbour - 0.1 - steal
    assert run["other_busy_cores"] == pytest.approx(run["other_busy_core_seconds"] / run["wall_seconds"], rel=0.02,
                                                    abs=0.01)


def test_the_starting_plan_keeps_every_copy_under_the_cap_then_fewer_copies_then_fewer_points():
    from rtsplat.train.initial import plan_starting_surfels

    for points in (1, 7, 100, 1000):
        for copies in (1, 3, 4):
            for cap in (1, 5, 99, 100, 250, 400, 4000):
                plan = plan_starting_surfels(points, copies, cap)
                assert plan.surfels <= max(cap, 1) and 1 <= plan.copies <= copies and plan.points <= points
                if points * copies <= cap:  # within the cap: exactly as without it
                    assert (plan.points, plan.copies) == (points, copies)
                elif points <= cap:  # all points, the most copies that fit
                    assert plan.points == points and points * (plan.copies + 1) > cap
                else:
                    assert (plan.points, plan.copies) == (cap, 1)
                assert str(plan.surfels) in json.dumps(plan.to_dict())


def test_the_starting_cap_follows_the_budget_and_the_training_pixels():
    from rtsplat.train.initial import starting_cap
    from rtsplat.train_config import Densification

    assert starting_cap(Densification(max_surfels=200_000), 10**9) == 100_000  # the budget's share
    assert starting_cap(Densification(max_surfels=200_000, initial_budget_share=0.25), 10**9) == 50_000
    assert starting_cap(Densification(max_surfels=200_000), 30_000) == 30_000  # one surfel per pixel
    assert starting_cap(Densification(max_surfels=200_000, initial_pixels_per_surfel=4), 30_000) == 7_500
    assert starting_cap(Densification(max_surfels=200_000, initial_pixels_per_surfel=0), 30_000) == 100_000


def test_the_density_start_comes_early_for_a_dense_start_only():
    from rtsplat.train.initial import StartingSurfels, density_start
    from rtsplat.train_config import Densification, Schedule

    def start(surfels: int, early: int | None = 124, **schedule):
        plan = StartingSurfels(surfels, surfels, 1, 10**6, "")
        schedule = {"iterations": 750, "densify_from": 188, "densify_every": 62, **schedule}
        return density_start(Schedule(dense_start_densify_from=early, **schedule), Densification(), plan, 7500.0)

    # 4 starting surfels per pixel of a training view by default: 30000 at 7500 pixels
    assert (start(29_999).densify_from, start(29_999).first_step) == (188, 248)  # sparse: 186 < 188
    assert (start(30_000).densify_from, start(30_000).first_step) == (124, 124)  # dense
    assert "a dense start: 4.00" in start(30_000).reason and "a sparse start: 4.00" in start(29_999).reason
    assert start(10**6, early=None).densify_from == 188 and "null" in start(10**6, early=None).reason
    assert start(10**6, early=300, densify_until=280).first_step is None  # no step before density control stops
    assert start(10**6, early=0).first_step == 62  # the first step is never iteration 0


def test_the_trainer_places_the_first_density_step_by_its_starting_surfels_per_pixel_of_a_view(glass_scene, tmp_path):
    train_pixels = sum(c.width * c.height for c in glass_scene.train_cameras)
    per_pixel = 4 * glass_scene.load_points()[0].shape[0] / (train_pixels / len(glass_scene.train_cameras))

    def density_steps(run: str, threshold: float) -> tuple[list[int], dict]:
        # every surfel cloned at every step (grad_threshold 0), so that each step shows in the log
        cfg = config(12, schedule={"dense_start_densify_from": 2, "densify_until": 5},
                     densify={"grad_threshold": 0.0, "dense_start_per_pixel": threshold})
        trainer = Trainer(glass_scene, cfg, tmp_path / run, progress=False, log=lambda m: None)
        steps = [trainer.step() for _ in range(5)]
        assert len(trainer.model.surfels) > trainer.starting.surfels
        return [s.iteration for s in steps if s.density], trainer.density_start.to_dict()

    dense, record = density_steps("dense", 0.99 * per_pixel)
    assert dense == [2, 4] and record["densify_from"] == 2 and "a dense start" in record["reason"]
    sparse, record = density_steps("sparse", 1.01 * per_pixel)
    assert sparse == [4] and record["densify_from"] == 4 and "a sparse start" in record["reason"]


def test_a_capped_start_uses_a_seeded_subset_of_the_points_with_the_whole_clouds_normals(glass_scene, tmp_path):
    from rtsplat.model.surfels import point_cloud_normals
    from rtsplat.raster.projection import quat_to_rotmat

    n_points = glass_scene.load_points()[0].shape[0]
    train_pixels = sum(c.width * c.height for c in glass_scene.train_cameras)
    assert n_points * 4 < train_pixels  # the default cap leaves this small scene as it was
    default = Trainer(glass_scene, config(2, seed_transparent_surface=False), tmp_path / "default", progress=False,
                      log=lambda m: None)
    assert len(default.model.surfels) == 4 * n_points and default.starting.surfels == 4 * n_points

    def capped(run: str, cap: int, seed: int = 0) -> Trainer:
        cfg = config(2, seed=seed, seed_transparent_surface=False,
                     densify={"max_surfels": 2 * cap, "initial_budget_share": 0.5})
        return Trainer(glass_scene, cfg, tmp_path / run, progress=False, log=lambda m: None)

    fewer_copies = capped("copies", 2 * n_points + n_points // 2)  # room for 2.5 copies: 2
    assert (fewer_copies.starting.points, fewer_copies.starting.copies) == (n_points, 2)
    assert len(fewer_copies.model.surfels) == 2 * n_points
    assert torch.equal(fewer_copies.model.surfels.means.detach()[:n_points], fewer_copies.points[0])

    cap = n_points // 3
    trainer = capped("subset", cap)
    means = trainer.model.surfels.means.detach()
    assert len(means) == cap and trainer.starting.points == cap and trainer.starting.copies == 1
    # each surfel sits on a distinct SfM point, with that point's colour ...
    match = torch.cdist(means, trainer.points[0]).argmin(1)
    assert torch.equal(trainer.points[0][match], means) and len(set(match.tolist())) == cap
    colour = torch.sigmoid(trainer.model.surfels.scatter_logit.detach())
    torch.testing.assert_close(colour, trainer.points[1][match].clamp(0.02, 0.98))
    # ... facing along the whole cloud's normal there (not that of the sparser subset)
    normals = quat_to_rotmat(torch.nn.functional.normalize(trainer.model.surfels.quats.detach(), dim=-1))[:, :, 2]
    expected = point_cloud_normals(trainer.points[0])[match]
    assert float((normals * expected).sum(-1).abs().min()) > 1 - 1e-5
    # the subset is the seed's: the same again with it, another with another seed
    assert torch.equal(capped("again", cap).model.surfels.means.detach(), means)
    assert not torch.equal(capped("other", cap, seed=1).model.surfels.means.detach(), means)
    summary = trainer.train()
    assert summary["starting_surfels"]["surfels"] == cap and "random" in summary["starting_surfels"]["reason"]
    assert json.loads((tmp_path / "subset" / "summary.json").read_text())["starting_surfels"]["cap"] == cap


def test_a_stop_signal_checkpoints_at_the_next_iteration_and_the_rerun_resumes_there(glass_scene, tmp_path):
    """SIGUSR1 (what a batch system sends before a time limit) stops `rtsplat train` cleanly: the checkpoint
    of the iteration it stopped at is written, the exit code says it was stopped (a failure to a workflow
    manager), and the same command resumes from that iteration to the model an uninterrupted run ends with."""
    cfg = config(120, schedule={"densify_from": 12, "densify_every": 8, "eval_every": 0, "log_every": 1})
    args, run, kept = _cli_with_checkpoint_dir(glass_scene, tmp_path, cfg)
    proc = _train_cli(*args)
    deadline = time.time() + 300
    while proc.poll() is None and time.time() < deadline:
        if (run / "train_log.jsonl").exists() and len(read_log(run)) >= 15:
            break
        time.sleep(0.02)
    assert proc.poll() is None, f"training ended before the signal: {proc.stderr.read()}"
    os.kill(proc.pid, signal.SIGUSR1)
    _, err = proc.communicate(timeout=300)
    assert proc.returncode == 128 + signal.SIGUSR1, err
    stopped_at = read_checkpoint(kept / "last.pt").training["iteration"]
    assert 15 <= stopped_at < 120 and f"stopped by SIGUSR1 at iteration {stopped_at} of 120" in err
    assert read_log(run)[-1]["iteration"] == stopped_at  # the checkpoint is of the last iteration logged
    assert not (run / "summary.json").exists()
    shutil.rmtree(run)  # what Snakemake does with the output folder of a failed job

    proc = _train_cli(*args)
    _, err = proc.communicate(timeout=600)
    assert proc.returncode == 0, err
    assert f"resumed from {kept / 'last.pt'} at iteration {stopped_at}" in err
    assert [r["iteration"] for r in read_log(run)] == list(range(1, 121))

    straight = Trainer(glass_scene, cfg, tmp_path / "straight", progress=False, log=lambda m: None)
    straight.train()
    a, b = straight.model.surfels.tensors(), read_checkpoint(run / "model.pt").surfels
    assert a.keys() == b.keys() and len(b["means"]) == len(a["means"])
    for name in a:
        torch.testing.assert_close(b[name], a[name], rtol=1e-4, atol=1e-5, msg=name)


def test_a_run_resumed_by_other_code_records_each_part_that_trained_it(glass_scene, tmp_path):
    """The checkpoint carries what trained each part: a resume from a checkpoint of another commit ends with
    that part under ``earlier_parts``; a resume by the same code adds none."""
    run = tmp_path / "run"

    def train_to(iterations: int) -> dict:
        cfg = config(10, schedule={"checkpoint_every": 5})
        cfg.schedule.iterations = iterations  # the one setting a resume may change without a word
        Trainer(glass_scene, cfg, run, progress=False, log=lambda m: None).train(resume=True)
        return json.loads((run / "summary.json").read_text())["provenance"]

    train_to(10)
    first = json.loads((run / "summary.json").read_text())["provenance"]
    assert "earlier_parts" not in first and first["device"] == "cpu"
    checkpoint = run / "checkpoints" / "last.pt"
    state = torch.load(checkpoint, weights_only=False)
    assert state["training"]["provenance"] == [first]
    other = {**first, "commit": "b" * 40, "dirty": True, "diff_sha256": "0" * 16}
    state["training"]["provenance"] = [other]
    torch.save(state, checkpoint)
    resumed = train_to(15)
    assert resumed["earlier_parts"] == [other] and {k: v for k, v in resumed.items() if k != "earlier_parts"} == first
    assert train_to(20)["earlier_parts"] == [other]


def test_restored_adam_moments_take_their_parameters_memory_layout():
    """The environment map is kept channels last, and the fused Adam step pairs values in memory order: moments
    restored in another layout (a checkpoint's contiguous ones) are laid out as their parameter is, so the step
    after a resume is the step of a contiguous twin."""
    base = torch.randn(1, 4, 8, 16, generator=torch.Generator().manual_seed(0))
    grad = torch.randn(1, 4, 8, 16, generator=torch.Generator().manual_seed(1))
    twin = torch.nn.Parameter(base.clone())
    twin_optimizer = torch.optim.Adam([twin], lr=0.1, fused=True)
    twin.grad = grad.clone()
    twin_optimizer.step()
    kept = torch.nn.Parameter(twin.detach().clone().to(memory_format=torch.channels_last))
    kept_optimizer = torch.optim.Adam([kept], lr=0.1, fused=True)
    load_optimizer_state(kept_optimizer, copy.deepcopy(twin_optimizer.state_dict()))  # as read from a file
    twin.grad = grad.clone()
    kept.grad = grad.clone().to(memory_format=torch.channels_last)  # as autograd lays out a parameter's gradient
    twin_optimizer.step()
    kept_optimizer.step()
    assert torch.equal(kept.detach(), twin.detach())
