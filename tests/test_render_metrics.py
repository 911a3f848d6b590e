"""Render and metrics stages: layers add up, edits do what they say, metrics match their definitions."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest
import torch
from skimage.metrics import structural_similarity

from rtsplat.bench.toy_scene import train_quietly, write_scene
from rtsplat.io.images import read_image
from rtsplat.metrics import NOT_AVAILABLE, image_metrics
from rtsplat.model.checkpoint import read_checkpoint
from rtsplat.quality import ssim_map
from rtsplat.render import Edits, apply_parameter_edits, render_run

QUANT = 1.5 / 255  # 8-bit PNGs: each layer is rounded separately


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    root = tmp_path_factory.mktemp("render")
    scene = write_scene(root / "scene", views=8, width=48, height=36)
    summary = train_quietly(scene, root / "run",
                            {"iterations": 30, "volume_until": 5, "specular_from": 10, "densify_from": 1000,
                             "reset_every": 0, "checkpoint_every": 0, "log_every": 10},
                            {"env_height": 16, "env_width": 32, "env_levels": 3, "mlp_width": 32})
    return root, scene, summary


def read_layers(out, name):
    return {layer: read_image(out / layer / f"{name}.png") for layer in ("color", "reflection", "transmission",
                                                                          "scatter")}


def test_ssim_matches_scikit_image_inside_the_border():
    g = np.random.default_rng(0)
    a = g.random((40, 50, 3))
    b = np.clip(a + 0.1 * g.standard_normal(a.shape), 0, 1)
    ours = ssim_map(torch.from_numpy(a), torch.from_numpy(b))[5:-5, 5:-5].mean().item()
    theirs = structural_similarity(a, b, gaussian_weights=True, sigma=1.5, use_sample_covariance=False,
                                   data_range=1, channel_axis=-1)
    assert ours == pytest.approx(theirs, abs=1e-6)


def test_ssim_border_pixels_use_a_zero_padded_window():
    """Direct sums over the 11x11 Gaussian window, zeros outside the image, at corner and edge pixels."""
    g = np.random.default_rng(1)
    a, b = g.random((14, 17, 2)), g.random((14, 17, 2))
    ours = ssim_map(torch.from_numpy(a), torch.from_numpy(b)).numpy()
    taps = np.exp(-((np.arange(11) - 5.0) ** 2) / (2 * 1.5**2))
    window = np.outer(taps, taps) / taps.sum() ** 2
    pad = lambda x: np.pad(x, ((5, 5), (5, 5), (0, 0)))  # noqa: E731
    for i, j in [(0, 0), (0, 16), (13, 3), (7, 8), (13, 16)]:
        def mean(x, i=i, j=j):
            return (pad(x)[i : i + 11, j : j + 11] * window[..., None]).sum((0, 1))
        mx, my = mean(a), mean(b)
        sxx, syy, sxy = mean(a * a) - mx**2, mean(b * b) - my**2, mean(a * b) - mx * my
        c1, c2 = 0.01**2, 0.03**2
        want = (2 * mx * my + c1) * (2 * sxy + c2) / ((mx**2 + my**2 + c1) * (sxx + syy + c2))
        np.testing.assert_allclose(ours[i, j], want, rtol=1e-10, atol=1e-12)


def test_region_psnr_and_ssim_follow_their_definitions():
    g = torch.Generator().manual_seed(0)
    target = torch.rand(30, 40, 3, generator=g, dtype=torch.float64) * 0.8
    mask = torch.zeros(30, 40, dtype=torch.bool)
    mask[10:20, 5:25] = True
    render = target.clone()
    render[mask] += 0.1
    m = image_metrics(render, target, mask)
    assert m["psnr_transparent"] == pytest.approx(20.0, abs=1e-9)  # MSE 0.01 inside the region
    assert m["psnr"] == pytest.approx(-10 * np.log10(0.01 * mask.double().mean().item()), abs=1e-6)
    smap = ssim_map(render, target)
    assert m["ssim_transparent"] == pytest.approx(smap[mask].mean().item(), abs=1e-12)
    assert m["ssim"] == pytest.approx(smap.mean().item(), abs=1e-12)
    assert m["lpips"] == NOT_AVAILABLE and m["lpips_transparent"] == NOT_AVAILABLE
    assert "psnr_transparent" not in image_metrics(render, target, torch.zeros_like(mask))


def test_render_writes_layers_that_add_up_and_fps(trained, tmp_path):
    root, scene, _ = trained
    info = render_run(root / "run", scene.root, tmp_path / "renders", progress=False)
    assert info["fps"] > 0 and info["views"] == [c.name for c in scene.test_cameras]
    assert json.loads((tmp_path / "renders" / "render.json").read_text())["fps"] == info["fps"]
    # the FPS says how it was timed: wall seconds of the timed frames, inside the render job, not alone
    timing = info["timing"]
    assert info["fps"] == pytest.approx(info["frames"] / info["seconds"])
    assert timing["wall_seconds"] == pytest.approx(info["seconds"], abs=5e-4)
    assert timing["scheduled_alone"] is False and timing["threads"] == torch.get_num_threads()
    assert 0 < timing["cpu_seconds"] <= timing["wall_seconds"] * timing["threads"] * 1.05 + 0.01
    for name in info["views"]:
        layers = read_layers(tmp_path / "renders", name)
        total = layers["reflection"] + layers["transmission"] + layers["scatter"]
        # layers are clamped to [0,1] before writing; compare where the colour is not clipped
        ok = (layers["color"] > QUANT) & (layers["color"] < 1 - QUANT)
        np.testing.assert_allclose(total[ok], layers["color"][ok], atol=3 * QUANT)
        for layer in ("normal", "depth"):
            assert (tmp_path / "renders" / layer / f"{name}.png").is_file()
    assert any(read_layers(tmp_path / "renders", n)["reflection"].max() > 0 for n in info["views"])


def test_edits_remove_reflections_and_tint_the_transmission(trained, tmp_path):
    root, scene, _ = trained
    plain = render_run(root / "run", scene.root, tmp_path / "plain", progress=False)
    render_run(root / "run", scene.root, tmp_path / "noref", progress=False, edits=Edits(reflections=False))
    render_run(root / "run", scene.root, tmp_path / "black", progress=False, edits=Edits(tint=(0.0, 0.0, 0.0)))
    for name in plain["views"]:
        base = read_layers(tmp_path / "plain", name)
        noref = read_layers(tmp_path / "noref", name)
        black = read_layers(tmp_path / "black", name)
        assert noref["reflection"].max() == 0
        np.testing.assert_allclose(noref["transmission"], base["transmission"], atol=QUANT)
        ok = base["color"] < 1 - QUANT
        np.testing.assert_allclose(noref["color"][ok], (base["color"] - base["reflection"])[ok].clip(0, 1),
                                   atol=2 * QUANT)
        assert black["transmission"].max() == 0
        np.testing.assert_allclose(black["reflection"], base["reflection"], atol=QUANT)


def test_roughness_and_transparency_edits_change_the_model(trained):
    root, scene, _ = trained
    camera = scene.test_cameras[0].to_camera()

    def render(edits):
        model = read_checkpoint(root / "run" / "model.pt").build_model()
        with torch.no_grad():  # a textured environment, so that blur is visible (30 iterations learn little)
            model.env.features.copy_(torch.randn(model.env.features.shape, generator=torch.Generator().manual_seed(0)))
        apply_parameter_edits(model, edits)
        with torch.no_grad():
            return model.render(camera), model

    base, model = render(Edits())
    sharp, sharp_model = render(Edits(roughness=0.25))
    clear, clear_model = render(Edits(transparency=0.0))
    torch.testing.assert_close(sharp_model.surfels.roughness, 0.25 * model.surfels.roughness, rtol=1e-4, atol=1e-6)
    torch.testing.assert_close(clear_model.surfels.opacity, torch.full_like(model.surfels.opacity, 1e-6),
                               rtol=1e-3, atol=1e-9)
    again, _ = render(Edits())
    assert torch.equal(again.layers["reflection"], base.layers["reflection"])  # deterministic without edits
    # the reflected light itself (C_spec, before the region and coverage weights that scale the reflection layer)
    assert (base.layers["spec"] - sharp.layers["spec"]).abs().max() > 1e-3
    assert (base.layers["reflection"] - sharp.layers["reflection"]).abs().max() > 0
    assert (base.color - clear.color).abs().max() > 1e-2
    # the transparency edit leaves surface (G-buffer) weights alone: occupancy is untouched
    torch.testing.assert_close(base.raster.alpha, clear.raster.alpha)


def test_metrics_cli_writes_json_with_both_regions(trained, tmp_path):
    root, scene, summary = trained
    render_run(root / "run", scene.root, tmp_path / "renders", progress=False)
    out = tmp_path / "metrics" / "rt.json"
    result = subprocess.run([sys.executable, "-m", "rtsplat.cli", "metrics", "--renders", str(tmp_path / "renders"),
                             "--data", str(scene.root), "--out", str(out), "--lpips-weights", str(tmp_path / "none")],
                            capture_output=True, text=True)
    assert result.returncode == 0, result.stderr
    data = json.loads(out.read_text())
    assert set(data["views"]) == {c.name for c in scene.test_cameras}
    # PNG quantisation moves PSNR a little from the trainer's float evaluation
    assert data["mean"]["psnr"] == pytest.approx(summary["test_psnr"], abs=0.3)
    assert data["mean"]["psnr_transparent"] == pytest.approx(summary["test_psnr_transparent"], abs=0.3)
    assert data["mean"]["lpips"] == NOT_AVAILABLE and data["lpips"].startswith("off")
    assert data["config_hash"] and data["provenance"]["versions"]["torch"] == torch.__version__
    assert data["fps"] > 0 and data["provenance"]["machine"]["cpus"] >= 1
    # the training's record, carried by render.json into the metrics
    assert data["training_provenance"] == summary["provenance"] and summary["provenance"]["device"] == "cpu"


def test_metrics_record_and_print_the_split_and_the_report_labels_it(trained, tmp_path, capsys):
    """Renders of every view (training views included) are scored as such: the JSON records the split,
    the printout says it is not a held-out score, the report's quality table labels the run."""
    from rtsplat.cli import main
    from rtsplat.report import Run, quality_rows

    root, scene, _ = trained
    render_run(root / "run", scene.root, tmp_path / "renders", split="all", progress=False, warmup=0)
    out = tmp_path / "metrics.json"
    assert main(["metrics", "--renders", str(tmp_path / "renders"), "--data", str(scene.root), "--out", str(out),
                 "--lpips-weights", str(tmp_path / "none")]) == 0
    data = json.loads(out.read_text())
    assert data["split"] == "all" and set(data["views"]) == {c.name for c in scene.cameras}
    captured = capsys.readouterr()
    assert f"all views ({len(scene.cameras)})" in captured.out
    assert "training views included" in captured.err
    test_run = Run(scene="s", method="a", metrics={"split": "test", "mean": {}})
    all_run = Run(scene="s", method="b", metrics=data)
    assert [row[0] for row in quality_rows({"a": test_run, "b": all_run})] == ["a", "b [all views]"]


def test_render_refuses_a_model_with_non_finite_parameters(trained, tmp_path):
    from rtsplat.model.checkpoint import CheckpointError

    root, scene, _ = trained
    state = torch.load(root / "run" / "model.pt", weights_only=False)
    state["model"]["surfels"]["opacity_logit"][3] = float("inf")
    torch.save(state, tmp_path / "model.pt")
    with pytest.raises(CheckpointError, match="'opacity_logit' holds 1 non-finite value") as info:
        read_checkpoint(tmp_path / "model.pt")
    assert str(tmp_path / "model.pt") in str(info.value)


def test_decomposition_is_scored_against_ground_truth_layers_in_the_region(trained, tmp_path):
    """With ground-truth layers in <data>/gt_layers the metrics score our reflection and our transmission
    (scatter included: colour - reflection) on the transparent region, as an independent numpy PSNR says."""
    import shutil

    from rtsplat.io.images import write_png
    from rtsplat.metrics import compute_metrics

    root, scene, _ = trained
    renders = tmp_path / "renders"
    render_run(root / "run", scene.root, renders, progress=False)
    data = tmp_path / "data"
    shutil.copytree(scene.root, data)
    g = np.random.default_rng(0)
    names = [c.name for c in scene.test_cameras]
    for name in names[:1]:  # one view has ground truth, the others do not
        for layer in ("reflection", "transmission"):
            (data / "gt_layers" / layer).mkdir(parents=True, exist_ok=True)
            write_png(data / "gt_layers" / layer / f"{name}.png", g.random((36, 48, 3)), bits=16)
    result = compute_metrics(renders, data)
    assert result["layer_views"] == 1 and result["gt_layers"] == str(data / "gt_layers")
    name = names[0]
    mask = scene.load_mask(name)
    ours = read_layers(renders, name)
    expected = {"reflection": ours["reflection"],
                "transmission": np.clip(ours["color"] - ours["reflection"], 0, 1)}
    for layer, mine in expected.items():
        truth = read_image(data / "gt_layers" / layer / f"{name}.png")
        mse = ((mine.astype(np.float64) - truth)[mask] ** 2).mean()
        assert result["views"][name][f"psnr_{layer}_layer"] == pytest.approx(-10 * np.log10(mse), abs=1e-3)
        assert result["mean"][f"psnr_{layer}_layer"] == result["views"][name][f"psnr_{layer}_layer"]
    assert all("psnr_reflection_layer" not in result["views"][n] for n in names[1:])
    # without ground truth there is no decomposition score
    assert "psnr_reflection_layer" not in compute_metrics(renders, scene.root)["mean"]


def test_bad_edit_and_missing_model_fail_cleanly(trained, tmp_path):
    root, scene, _ = trained
    base = [sys.executable, "-m", "rtsplat.cli", "render", "--data", str(scene.root), "--quiet"]
    bad = subprocess.run(base + ["--run", str(root / "run"), "--out", str(tmp_path / "x"), "--edit", "glossy=2"],
                         capture_output=True, text=True)
    # bad input exits with status 1, the convention of every stage (argparse usage errors: 2)
    assert bad.returncode == 1 and "glossy=2" in bad.stderr and "roughness=S" in bad.stderr
    missing = subprocess.run(base + ["--run", str(tmp_path / "norun"), "--out", str(tmp_path / "y")],
                             capture_output=True, text=True)
    assert missing.returncode == 1 and "model.pt" in missing.stderr and "rtsplat train" in missing.stderr
    assert not (tmp_path / "x").exists() and not (tmp_path / "y").exists()


def test_fps_cli_times_the_test_views_alone_and_says_so(trained, tmp_path):
    """`rtsplat fps` renders every test view `--rounds` times, writes only its JSON file, and records
    scheduled_alone only when the caller says the job runs alone."""
    root, scene, _ = trained
    outs = {}
    for alone in (True, False):
        out = tmp_path / f"fps_{alone}.json"
        args = [sys.executable, "-m", "rtsplat.cli", "fps", "--run", str(root / "run"), "--data", str(scene.root),
                "--out", str(out), "--rounds", "2", "--warmup", "1"] + (["--scheduled-alone"] if alone else [])
        result = subprocess.run(args, capture_output=True, text=True)
        assert result.returncode == 0, result.stderr
        outs[alone] = json.loads(out.read_text())
    assert sorted(p.name for p in tmp_path.iterdir()) == ["fps_False.json", "fps_True.json"]
    for alone, info in outs.items():
        timing = info["timing"]
        assert timing["scheduled_alone"] is alone
        assert info["frames"] == 2 * len(scene.test_cameras) == 2 * info["views"]
        assert info["fps"] == pytest.approx(info["frames"] / info["seconds"])
        assert timing["wall_seconds"] == pytest.approx(info["seconds"], abs=5e-4)
        assert timing["cpu_seconds_per_frame"] == pytest.approx(timing["cpu_seconds"] / info["frames"], abs=1e-3)
        assert 0 < timing["cpu_seconds"] <= timing["wall_seconds"] * timing["threads"] * 1.05 + 0.01
