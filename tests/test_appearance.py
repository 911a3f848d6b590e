"""Per-view appearance (exposure, white balance): the correction, its fits, the data's decision, training
and rendering with it."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch

from rtsplat.bench.toy_scene import write_scene
from rtsplat.model.appearance import LOG_GAIN_LIMIT, apply_appearance, fit_appearance, remove_appearance
from rtsplat.model.checkpoint import read_checkpoint
from rtsplat.train.appearance import (
    APPEARANCE_SPREAD,
    PROJECTED_SPREAD,
    ExposureSpread,
    ViewGains,
    appearance_spread,
    decide_appearance,
    exposure_spread,
    view_log_gains,
)
from rtsplat.train.data import load_views
from rtsplat.train.trainer import Trainer
from rtsplat.train_config import TrainConfig

SMALL_MODEL = {"env_height": 16, "env_width": 32, "env_levels": 3, "mlp_width": 32}


def exposures(views: int, seed: int = 0, log_gain: float = 0.15, offset: float = 0.02) -> torch.Tensor:
    """A phone's shot-to-shot exposure and white balance: per view and channel, a log gain in
    [-log_gain, log_gain] (a common exposure plus a smaller white-balance tilt) and a small offset."""
    g = torch.Generator().manual_seed(seed)
    exposure = (torch.rand(views, 1, generator=g) * 2 - 1) * log_gain
    balance = (torch.rand(views, 3, generator=g) * 2 - 1) * log_gain / 3
    shift = (torch.rand(views, 3, generator=g) * 2 - 1) * offset
    return torch.cat([(exposure + balance).clamp(-log_gain, log_gain), shift], 1)


def train_config(iterations: int, **effects) -> TrainConfig:
    return TrainConfig.from_dict({
        "schedule": {"iterations": iterations, "volume_until": iterations // 6, "specular_from": iterations // 3,
                     "densify_from": iterations // 3, "densify_every": max(iterations // 6, 1), "reset_every": 0,
                     "log_every": 5, "checkpoint_every": 0},
        "model": dict(SMALL_MODEL), "effects": effects,
    })


def test_zero_is_the_identity_and_remove_inverts_apply():
    g = torch.Generator().manual_seed(1)
    color = torch.rand(5, 7, 3, generator=g)
    assert torch.equal(apply_appearance(color, torch.zeros(6)), color)
    correction = torch.tensor([0.3, -0.2, 0.1, 0.05, -0.02, 0.0])
    out = apply_appearance(color, correction)
    assert not torch.allclose(out, color)
    assert torch.allclose(remove_appearance(out, correction), color, atol=1e-6)
    assert torch.allclose(out[..., 0], color[..., 0] * math.exp(0.3) + 0.05, atol=1e-6)


@pytest.mark.parametrize("log_gain", [1e6, -1e6, 1e30])
def test_extreme_gains_are_clamped_and_stay_finite_with_finite_gradients(log_gain):
    color = torch.rand(4, 4, 3, requires_grad=True)
    correction = torch.tensor([log_gain, 0.0, -log_gain, 0.0, 0.0, 0.0], requires_grad=True)
    out = apply_appearance(color, correction)
    out.sum().backward()
    assert torch.isfinite(out).all() and torch.isfinite(color.grad).all() and torch.isfinite(correction.grad).all()
    assert float(out.detach()[..., 0].max()) <= math.exp(LOG_GAIN_LIMIT) + 1e-4
    assert torch.isfinite(remove_appearance(out, correction)).all()


def test_the_closed_form_fit_recovers_a_known_exposure():
    g = torch.Generator().manual_seed(2)
    rendered = torch.rand(40, 50, 3, generator=g)
    truth = torch.tensor([0.2, -0.1, 0.05, 0.03, -0.01, 0.02])
    photo = apply_appearance(rendered, truth) + 0.01 * torch.randn(40, 50, 3, generator=g)
    fitted = fit_appearance(rendered, photo, prior=1e-4)
    assert torch.allclose(fitted, truth, atol=0.01)
    # the fit lowers the error against the photo below that of the plain render
    assert (apply_appearance(rendered, fitted) - photo).abs().mean() < 0.5 * (rendered - photo).abs().mean()


def test_a_flat_or_dark_render_gets_a_finite_fit_that_keeps_its_gain_near_one():
    for rendered in (torch.full((8, 8, 3), 0.4), torch.zeros(8, 8, 3)):
        photo = torch.full((8, 8, 3), 0.6)
        fitted = fit_appearance(rendered, photo)
        assert torch.isfinite(fitted).all()
        assert float(fitted[:3].abs().max()) < 0.5  # the offset takes the difference, not a wild gain
        assert torch.allclose(apply_appearance(rendered, fitted), photo, atol=0.05)


def _gains(scene) -> torch.Tensor:
    views = load_views(scene, "train")
    xyz, rgb = scene.load_points()
    return view_log_gains(views.cameras, views.images, views.masks, torch.as_tensor(np.asarray(xyz)).float(),
                          torch.as_tensor(np.asarray(rgb)).float() / 255).log_gains


def test_the_views_log_gains_are_read_from_the_point_colours(tmp_path):
    truth = exposures(8, log_gain=0.12, offset=0.0)
    scene = write_scene(tmp_path / "exposed", views=8, width=64, height=48, with_pane=False, test_every=100,
                        exposures=truth)
    gains = _gains(scene)  # the training views: all but view 0
    assert torch.isfinite(gains).all()
    # each view's measured gain against its true one, up to the common factor the points' colours carry
    error = (gains - truth[1:, :3]) - (gains - truth[1:, :3]).median(0).values
    assert float(error.abs().max()) < 0.04
    spread = appearance_spread(gains)
    assert spread is not None and spread >= PROJECTED_SPREAD
    flat = appearance_spread(_gains(write_scene(tmp_path / "flat", views=8, width=64, height=48, with_pane=False,
                                                test_every=100)))
    assert flat is not None and flat < PROJECTED_SPREAD


def test_the_decision_says_why():
    assert decide_appearance("auto", ExposureSpread(APPEARANCE_SPREAD * 2, 8, 300, 0.0)).on
    off = decide_appearance("auto", ExposureSpread(APPEARANCE_SPREAD / 2, 8, 300, 0.0))
    assert not off.on and "one exposure" in off.reason and off.confidence == "high"
    none = decide_appearance("auto", ExposureSpread(None, 2, 12))
    assert not none.on and "too few reliable observations (12 per view)" in none.reason and none.confidence == "low"
    assert decide_appearance("on", ExposureSpread(0.0, 8)).on
    assert not decide_appearance("off", ExposureSpread(1.0, 8)).on
    assert appearance_spread(torch.full((2, 3), 0.1)) is None  # fewer than 3 views
    # the spread the noise explains does not count: 0.02 measured with 0.014 of noise is 0.0143 beyond it
    noisy = decide_appearance("auto", ExposureSpread(0.02, 8, 300, 0.014))
    assert not noisy.on and "0.014 beyond the 0.014" in noisy.reason and noisy.confidence == "low"
    # a scene prepared before the noise was recorded: the spread alone decides, its confidence unknown
    old = decide_appearance("auto", ExposureSpread(0.02, 8))
    assert old.on and old.confidence == "unknown" and "rerun rtsplat prepare" in old.reason


GLASS_PHOTO = (80, 100)  # height, width of the synthetic photos below


def _measured_views(glass: float, log_gains: list[float], keypoints: int = 400, scatter: float = 0.25,
                    seed: int = 0) -> list:
    """Each view's exposure as prepare measures it (its ``_exposure``) from synthetic SfM observations: a photo
    whose see-through mask covers the fraction ``glass`` of it (a pane filling the view but for a strip of wall
    at the bottom), ``keypoints`` observations spread over it, each showing its point's colour at the view's log
    gain times a per-observation scatter (view-dependent colour, keypoints off by a pixel) of ``scatter``."""
    from rtsplat.prepare import _exposure

    height, width = GLASS_PHOTO
    rng = np.random.default_rng(seed)
    mask = np.zeros((height, width), bool)
    mask[: int(round(glass * height))] = True
    out = []
    for gain in log_gains:
        pixels = rng.choice(height * width, keypoints, replace=False)
        xy = np.stack([pixels % width + 0.5, pixels // width + 0.5], 1)
        rgb = rng.integers(60, 220, (keypoints, 3)).astype(np.uint8)
        seen = rgb / 255 * np.exp(gain + scatter * rng.standard_normal((keypoints, 1)))
        image = np.zeros((height, width, 3), np.float32)
        image[pixels // width, pixels % width] = np.clip(seen, 0, 1)
        out.append(_exposure(image, (xy, rgb), (width, height), mask))
    return out


def _view_gains(estimates: list) -> ViewGains:
    nan = torch.full((3,), float("nan"))
    return ViewGains(torch.stack([nan if e.log_gain is None else e.log_gain for e in estimates]),
                     torch.tensor([e.points for e in estimates]),
                     torch.tensor([float("nan") if e.error is None else e.error for e in estimates]))


def test_one_exposure_seen_through_photos_mostly_of_glass_stays_off_for_too_few_reliable_observations():
    estimates = _measured_views(glass=0.9, log_gains=[0.0] * 12)
    outside = [e.points for e in estimates]
    assert max(outside) < 70  # ~10% of the 400 keypoints lie off the glass
    measured = exposure_spread(_view_gains(estimates))
    assert measured.spread >= APPEARANCE_SPREAD  # the few keypoints' scatter alone looks like an exposure spread
    decision = decide_appearance("auto", measured)
    assert not decision.on and decision.confidence == "low"
    assert f"too few reliable observations ({round(np.median(outside))} per view)" in decision.reason
    # the same photos with their glass taking a tenth of the view: measured on ten times the keypoints
    clear = exposure_spread(_view_gains(_measured_views(glass=0.1, log_gains=[0.0] * 12)))
    assert clear.noise < APPEARANCE_SPREAD  # measurable
    off = decide_appearance("auto", clear)
    assert not off.on and "one exposure" in off.reason


def test_a_real_exposure_spread_measured_on_enough_observations_turns_on():
    estimates = _measured_views(glass=0.1, log_gains=[0.0, -0.2] * 6)  # every other photo 0.2 darker
    measured = exposure_spread(_view_gains(estimates))
    assert measured.views == 12 and measured.observations >= 300
    decision = decide_appearance("auto", measured)
    assert decision.on and decision.confidence == "high", decision.reason
    assert measured.spread == pytest.approx(0.1, abs=0.03)


def test_the_trainer_decides_from_the_scenes_recorded_observations(tmp_path):
    """prepare's per-view counts and errors (scene.json's exposure_points, exposure_error) reach the trainer's
    decision and its summary: one exposure measured on photos mostly of glass stays off, a real spread on
    enough observations turns on."""
    from rtsplat.scene import PreparedScene

    for case, glass, gains in (("glass", 0.9, [0.0] * 7), ("spread", 0.1, [0.0, -0.2] * 3 + [0.0])):
        scene = write_scene(tmp_path / case, views=8, width=32, height=24, with_pane=False, test_every=100)
        names = [c.name for c in scene.train_cameras]
        estimates = _measured_views(glass, gains)
        by_name = dict(zip(names, estimates, strict=True))
        scene.exposure = {n: None if e.log_gain is None else e.log_gain.tolist() for n, e in by_name.items()}
        scene.exposure_points = {n: e.points for n, e in by_name.items()}
        scene.exposure_error = {n: e.error for n, e in by_name.items()}
        scene.save(tmp_path / case)
        trainer = Trainer(PreparedScene.load(tmp_path / case), train_config(10), tmp_path / f"{case}_run",
                          progress=False, log=lambda m: None)
        summary = trainer.appearance_summary()
        assert summary["observations_per_view"] == round(np.median([e.points for e in estimates]))
        assert summary["views_measured"] == sum(e.log_gain is not None for e in estimates)
        if case == "glass":
            assert trainer.appearance is None and not summary["on"] and summary["confidence"] == "low"
            assert summary["reason"].startswith("auto: too few reliable observations (")
        else:
            assert trainer.appearance is not None and summary["on"] and summary["confidence"] == "high"
            assert summary["noise"] < APPEARANCE_SPREAD


def test_training_learns_and_saves_every_views_correction_and_render_applies_it(tmp_path):
    from rtsplat.render import render_run

    scene = write_scene(tmp_path / "scene", views=8, width=40, height=30, with_pane=False,
                        exposures=exposures(8, seed=3))
    trainer = Trainer(scene, train_config(40), tmp_path / "run", progress=False, log=lambda m: None)
    summary = trainer.train()
    effects = json.loads((tmp_path / "run" / "effects.json").read_text())
    assert effects["appearance"] is True and "auto" in effects["reasons"]["appearance"]
    assert summary["appearance"]["on"] and summary["appearance"]["spread"] >= APPEARANCE_SPREAD
    corrections = read_checkpoint(tmp_path / "run" / "model.pt").training["appearance_corrections"]
    assert sorted(corrections) == sorted(r.name for r in scene.cameras)
    test_name = scene.test_cameras[0].name
    assert any(abs(v) > 1e-4 for v in corrections[test_name])  # the test view's fit moved it
    assert any(any(abs(v) > 1e-4 for v in corrections[r.name]) for r in scene.train_cameras)

    plain = tmp_path / "plain"
    render_run(tmp_path / "run", tmp_path / "scene", tmp_path / "render", progress=False)
    # the same render without the correction: the run's corrections dropped from a copy of the model
    checkpoint = torch.load(tmp_path / "run" / "model.pt", weights_only=False)
    checkpoint["training"]["appearance_corrections"] = {}
    (plain / "run").mkdir(parents=True)
    torch.save(checkpoint, plain / "run" / "model.pt")
    render_run(plain / "run", tmp_path / "scene", plain / "render", progress=False)
    from rtsplat.io.images import read_image

    with_fit = torch.as_tensor(read_image(tmp_path / "render" / "color" / f"{test_name}.png"))
    without = torch.as_tensor(read_image(plain / "render" / "color" / f"{test_name}.png"))
    expected = apply_appearance(without, torch.as_tensor(corrections[test_name]).float()).clamp(0, 1)
    assert (with_fit - expected).abs().max() < 3 / 255  # 8-bit rounding of both PNGs
    assert (with_fit - without).abs().max() > 3 / 255


def test_a_scene_with_one_exposure_learns_no_corrections(tmp_path):
    scene = write_scene(tmp_path / "scene", views=6, width=32, height=24, with_pane=False)
    trainer = Trainer(scene, train_config(10), tmp_path / "run", progress=False, log=lambda m: None)
    summary = trainer.train()
    assert trainer.appearance is None and not summary["appearance"]["on"]
    assert "one exposure" in summary["appearance"]["reason"]
    assert read_checkpoint(tmp_path / "run" / "model.pt").training["appearance_corrections"] == {}


@pytest.mark.slow
def test_per_view_appearance_raises_held_out_psnr_on_photos_of_varying_exposure(tmp_path):
    scene = write_scene(tmp_path / "scene", views=12, width=48, height=36, with_pane=False,
                        exposures=exposures(12, seed=4, log_gain=0.25, offset=0.03))
    scores = {}
    for mode in ("on", "off"):
        trainer = Trainer(scene, train_config(240, appearance=mode), tmp_path / mode, progress=False,
                          log=lambda m: None)
        scores[mode] = trainer.train()["test_psnr"]
    assert scores["on"] > scores["off"] + 1.0, scores


@pytest.mark.slow
def test_prepare_measures_each_photos_exposure_at_the_sfm_observations(tmp_path):
    """Half of the photos taken 0.2 darker (log gain): prepare's per-view gains, read at the keypoints SfM tied
    to 3D points, put the two halves 0.2 apart, agree within each half, and make the scene call for
    corrections."""
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).parent))
    from fixtures_pipeline import make_corner_scene

    from rtsplat.config import PrepareConfig, SfmConfig
    from rtsplat.io.images import read_image, write_png
    from rtsplat.prepare import prepare_scene
    from rtsplat.scene import PreparedScene
    from rtsplat.sfm import run_sfm

    views = make_corner_scene(tmp_path / "s", n_views=12, width=200, height=150)
    darker = {Path(v.name).stem for v in views[1::2]}
    for v in views[1::2]:
        path = tmp_path / "s" / "images" / v.name
        write_png(path, read_image(path) * math.exp(-0.2))
    run_sfm(tmp_path / "s", tmp_path / "sfm", SfmConfig(use_dataset_model=False, camera_model="PINHOLE"),
            progress=False)
    prepare_scene(tmp_path / "s", tmp_path / "sfm", tmp_path / "prepared", PrepareConfig(), progress=False)
    prepared = PreparedScene.load(tmp_path / "prepared")
    exposure = prepared.exposure
    measured = {name: gain for name, gain in exposure.items() if gain is not None}
    assert len(measured) >= 10
    # each measured view's observation count and the gain's standard error are recorded beside it
    assert all(prepared.exposure_points[name] >= 20 and prepared.exposure_error[name] >= 0 for name in measured)
    dark = torch.tensor([g for n, g in measured.items() if n in darker])
    bright = torch.tensor([g for n, g in measured.items() if n not in darker])
    gap = dark.median(0).values - bright.median(0).values
    assert torch.allclose(gap, torch.full((3,), -0.2), atol=0.03), gap
    for group in (dark, bright):
        assert float((group - group.median(0).values).abs().max()) < 0.03
    spread = appearance_spread(torch.tensor(list(measured.values())))
    assert spread is not None and spread >= APPEARANCE_SPREAD
